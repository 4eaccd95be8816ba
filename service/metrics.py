"""The service's Prometheus metrics, from ``prometheus-client`` (text exposition format 0.0.4).

Why the library: it implements the format, label escaping, histograms and — what a hand-written
registry cannot do — *multiprocess mode*: with ``quatrack serve --workers N`` every worker writes
its samples to memory-mapped files in ``$PROMETHEUS_MULTIPROC_DIR`` (set and wiped by ``serve``
before the workers start), and whichever worker answers ``/metrics`` merges them all: counters
and histograms are summed over the workers, ``quatrack_models_loaded`` is the largest of the live
workers'. Route templates (``/v1/objects/{name}/pose``), never raw paths, are used as labels so
that clients cannot blow up the number of series.

Without that variable (tests, the benchmark's in-process server) each :class:`Metrics` has its
own registry, so several apps in one process do not mix their counts.
"""

from __future__ import annotations

import os
from typing import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

from .workers import MULTIPROC_ENV  # (named there: `quatrack serve` sets it before this import)

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
STAGE_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0)
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


def multiprocess_dir() -> str | None:
    """The shared directory when the workers run in multiprocess mode, else None."""
    return os.environ.get(MULTIPROC_ENV) or os.environ.get(MULTIPROC_ENV.lower()) or None


class _Computed(Collector):
    """A gauge whose value is computed at scrape time (e.g. sessions open in the whole server)."""

    def __init__(self, name: str, help_text: str, value: Callable[[], float]) -> None:
        self.name, self.help, self.value = name, help_text, value

    def collect(self):
        g = GaugeMetricFamily(self.name, self.help)
        g.add_metric([], float(self.value()))
        yield g


class _PerWorker(Collector):
    """``quatrack_worker_sessions{pid}`` and ``quatrack_worker_listening{pid}``, read at scrape
    time from the workers' placement board (service/placement.py), so that only live workers are
    reported (a crashed worker's prometheus files would keep its last value)."""

    def __init__(self, read: Callable[[], dict]) -> None:
        self.read = read

    def collect(self):
        board = self.read()
        sessions = GaugeMetricFamily("quatrack_worker_sessions", "open tracking sessions of each worker process "
                                     "(quatrack serve --workers N, N > 1)", labels=["pid"])
        listening = GaugeMetricFamily("quatrack_worker_listening", "1 if the worker accepts new connections: it holds "
                                      "no more sessions and handshakes than the least-loaded worker", labels=["pid"])
        for pid, (n, on) in sorted(board.items()):
            sessions.add_metric([str(pid)], float(n))
            listening.add_metric([str(pid)], 1.0 if on else 0.0)
        yield sessions
        yield listening


class Metrics:
    """The service's metrics; one instance per app (tests start several apps in one process).

    ``sessions_open`` (a callable) gives the number of sessions open in the whole server; it is
    read at scrape time, so a worker that died holds no stale count. ``per_worker`` (a callable,
    optional) gives ``{pid: (sessions, listening)}`` of the live workers, likewise.
    """

    def __init__(self, sessions_open: Callable[[], float] = lambda: 0,
                 per_worker: Callable[[], dict] | None = None) -> None:
        self.multiprocess = multiprocess_dir() is not None
        # in multiprocess mode samples go to the shared files whatever registry the metrics are
        # registered with; a private registry keeps several apps in one process apart
        reg = CollectorRegistry(auto_describe=True)
        self.registry = reg
        self.requests = Counter("quatrack_http_requests", "HTTP requests by route and status",
                                ("method", "route", "status"), registry=reg)
        self.latency = Histogram("quatrack_http_request_duration_seconds", "HTTP request latency", ("route",),
                                 buckets=LATENCY_BUCKETS, registry=reg)
        self.sessions = Counter("quatrack_ws_sessions", "tracking sessions by outcome", ("outcome",), registry=reg)
        self.frames = Counter("quatrack_ws_frames", "WebSocket frames by result", ("result",), registry=reg)
        # handshakes refused before a session opens (no token, unknown object, sessions full, ...):
        # they reach no session outcome, and a full server was invisible in the metrics
        self.ws_refused = Counter("quatrack_ws_refused", "WebSocket handshakes refused, by error code", ("code",),
                                  registry=reg)
        self.frame_latency = Histogram("quatrack_ws_frame_latency_seconds", "frame arrival to pose message",
                                       buckets=LATENCY_BUCKETS, registry=reg)
        self.frame_wait = Histogram("quatrack_ws_frame_wait_seconds", "frame arrival to its processing starting "
                                    "(waiting for the session's previous frame and a free thread)",
                                    buckets=LATENCY_BUCKETS, registry=reg)
        self.statuses = Counter("quatrack_track_frames", "processed frames by tracker status (init, tracking, lost)",
                                ("status",), registry=reg)
        self.losses = Counter("quatrack_track_losses", "transitions of a session to status lost", registry=reg)
        self.inits = Counter("quatrack_track_inits", "transitions of a session to status init (recognition found the object)",
                             registry=reg)
        self.stages = Histogram("quatrack_track_stage_seconds", "per-frame time of each tracker stage", ("stage",),
                                buckets=STAGE_BUCKETS, registry=reg)
        self.locate_stages = Histogram("quatrack_locate_stage_seconds", "per-request time of each recognition stage (REST pose)",
                                       ("stage",), buckets=STAGE_BUCKETS, registry=reg)
        self.models = Gauge("quatrack_models_loaded", "object models in memory (the largest over live workers)",
                            registry=reg, multiprocess_mode="livemax")
        self.model_loads = Counter("quatrack_model_loads", "object model loads by result (ok, failed)", ("result",),
                                   registry=reg)
        self.models.set(0)
        self._sessions_open = _Computed("quatrack_ws_sessions_active", "open tracking sessions (whole server)", sessions_open)
        reg.register(self._sessions_open)
        self._per_worker = _PerWorker(per_worker) if per_worker is not None else None
        if self._per_worker is not None:
            reg.register(self._per_worker)

    def observe_stages(self, histogram: Histogram, timings_ms: dict | None) -> None:
        for stage, ms in (timings_ms or {}).items():
            histogram.labels(str(stage)).observe(float(ms) / 1e3)

    def render(self) -> bytes:
        """The text exposition: this process's metrics, or every worker's in multiprocess mode."""
        if not self.multiprocess:
            return generate_latest(self.registry)
        from prometheus_client import multiprocess

        reg = CollectorRegistry()
        multiprocess.MultiProcessCollector(reg)
        reg.register(self._sessions_open)
        if self._per_worker is not None:
            reg.register(self._per_worker)
        return generate_latest(reg)


def worker_exit(pid: int | None = None) -> None:
    """Tell multiprocess mode a worker is gone (drops its ``live*`` gauge files)."""
    if multiprocess_dir() is not None:
        from prometheus_client import multiprocess

        multiprocess.mark_process_dead(pid or os.getpid())

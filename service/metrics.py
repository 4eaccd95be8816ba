"""A small Prometheus text-format registry (exposition format 0.0.4), written by hand.

Counters, gauges and histograms with labels are all the service needs; one lock, no
dependency. Route templates (``/v1/objects/{name}/pose``), never raw paths, are used as labels so
that clients cannot blow up the number of series.
"""

from __future__ import annotations

import threading
from collections import defaultdict

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


def _labels(names: tuple[str, ...], values: tuple) -> str:
    if not names:
        return ""
    esc = (str(v).replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") for v in values)
    return "{" + ",".join(f'{n}="{v}"' for n, v in zip(names, esc)) + "}"


class _Metric:
    def __init__(self, name: str, help_text: str, kind: str, labels: tuple[str, ...] = ()) -> None:
        self.name, self.help, self.kind, self.labelnames = name, help_text, kind, labels
        self.lock = threading.Lock()


class Counter(_Metric):
    def __init__(self, name, help_text, labels=()):
        super().__init__(name, help_text, "counter", labels)
        self.values: dict[tuple, float] = defaultdict(float)

    def inc(self, *labels, amount: float = 1.0) -> None:
        with self.lock:
            self.values[labels] += amount

    def get(self, *labels) -> float:
        with self.lock:
            return self.values.get(labels, 0.0)

    def lines(self):
        with self.lock:
            items = sorted(self.values.items())
        return [f"{self.name}{_labels(self.labelnames, k)} {v:g}" for k, v in items]


class Gauge(Counter):
    def __init__(self, name, help_text, labels=()):
        super().__init__(name, help_text, labels)
        self.kind = "gauge"

    def set(self, value: float, *labels) -> None:
        with self.lock:
            self.values[labels] = value

    def dec(self, *labels) -> None:
        self.inc(*labels, amount=-1.0)


class Histogram(_Metric):
    def __init__(self, name, help_text, labels=(), buckets=LATENCY_BUCKETS):
        super().__init__(name, help_text, "histogram", labels)
        self.buckets = tuple(buckets)
        self.data: dict[tuple, list] = {}

    def observe(self, value: float, *labels) -> None:
        with self.lock:
            d = self.data.setdefault(labels, [[0] * len(self.buckets), 0.0, 0])
            for i, b in enumerate(self.buckets):
                if value <= b:
                    d[0][i] += 1
            d[1] += value
            d[2] += 1

    def lines(self):
        out = []
        with self.lock:
            items = sorted((k, (list(v[0]), v[1], v[2])) for k, v in self.data.items())
        names = self.labelnames + ("le",)
        for k, (counts, total, n) in items:
            for b, c in zip(self.buckets, counts):
                out.append(f"{self.name}_bucket{_labels(names, k + (f'{b:g}',))} {c}")
            out.append(f"{self.name}_bucket{_labels(names, k + ('+Inf',))} {n}")
            out.append(f"{self.name}_sum{_labels(self.labelnames, k)} {total:.6f}")
            out.append(f"{self.name}_count{_labels(self.labelnames, k)} {n}")
        return out


class Metrics:
    """The service's metrics; one instance per app (tests start several apps in one process)."""

    def __init__(self) -> None:
        self.requests = Counter("quatrack_http_requests_total", "HTTP requests by route and status", ("method", "route", "status"))
        self.latency = Histogram("quatrack_http_request_duration_seconds", "HTTP request latency", ("route",))
        self.sessions_active = Gauge("quatrack_ws_sessions_active", "open tracking sessions")
        self.sessions = Counter("quatrack_ws_sessions_total", "tracking sessions by outcome", ("outcome",))
        self.frames = Counter("quatrack_ws_frames_total", "WebSocket frames by result", ("result",))
        self.frame_latency = Histogram("quatrack_ws_frame_latency_seconds", "frame arrival to pose message")
        self.losses = Counter("quatrack_track_losses_total", "transitions of a session to status lost")
        self.models = Gauge("quatrack_models_loaded", "object models in memory")
        self.sessions_active.set(0)
        self.models.set(0)
        self._all = (self.requests, self.latency, self.sessions_active, self.sessions, self.frames,
                     self.frame_latency, self.losses, self.models)

    def render(self) -> str:
        out = []
        for m in self._all:
            out.append(f"# HELP {m.name} {m.help}")
            out.append(f"# TYPE {m.name} {m.kind}")
            out.extend(m.lines())
        return "\n".join(out) + "\n"

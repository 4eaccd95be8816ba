"""A prototype of the other process model for ``quatrack bench serve --pool`` (issue 15, item 1):
ONE event loop process (uvicorn, every connection) and a pool of N tracking processes behind it.

Measured against ``quatrack serve --workers N`` (N processes, each with its own event loop and
threads) in bench/RESULTS.md ("Serving many cameras"). Not the product: it exists to be measured.

Each session is pinned to one pool process (round robin at its start), which holds its tracker:
a frame goes to that process as its JPEG bytes plus the pending controls (pickled, ≈ 55 KB), the
pose message comes back. The event loop process only parses, routes and sends, so the interpreter
lock it needs is never held by tracking. The session logic is the product's own
(``TrackSession``): only ``_process`` runs elsewhere, on a stand-in that holds the same state.
"""

from __future__ import annotations

import argparse
import itertools
import os
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from types import SimpleNamespace

from quatrack.testing.loopback import Loopback, free_port

_WORKER: SimpleNamespace | None = None  # the pool process's state (set by its initializer)


def _init(store: str, threads: int) -> None:
    """Pool process start-up: models loaded once, a small thread pool for re-anchoring."""
    global _WORKER
    import cv2

    from quatrack.recognition.runtime import tune_allocator
    from quatrack.service.metrics import Metrics
    from quatrack.service.registry import ModelRegistry
    from quatrack.service.settings import Settings

    cv2.setNumThreads(1)
    tune_allocator()
    settings = Settings.from_env(store=store)
    registry = ModelRegistry(settings.store)
    registry.load_all()
    _WORKER = SimpleNamespace(settings=settings, registry=registry, sessions={},
                              executor=ThreadPoolExecutor(threads), metrics=Metrics())


def _step(sid: str, name: str, item) -> tuple[str, object]:
    """In the pool process: the session's ``TrackSession._process`` on its state here."""
    from quatrack.service.sessions import TrackSession, _SessionError

    w = _WORKER
    st = w.sessions.get(sid)
    if st is None:
        st = w.sessions[sid] = SimpleNamespace(sid=sid, name=name, model=w.registry.get(name), settings=w.settings,
                                               executor=w.executor, metrics=w.metrics, tracker=None,
                                               tracker_camera=None, last_status=None)
    try:
        return "ok", TrackSession._process(st, item)
    except _SessionError as exc:
        return "error", (exc.code, exc.message)


def _end(sid: str) -> None:
    _WORKER.sessions.pop(sid, None)


def build_app(store: str, procs: int, threads: int):
    """The product's app, with every session's tracking sent to its pool process."""
    from quatrack.service import routes
    from quatrack.service.app import create_app
    from quatrack.service.sessions import TrackSession, _SessionError
    from quatrack.service.settings import Settings

    pools = [ProcessPoolExecutor(1, initializer=_init, initargs=(store, threads)) for _ in range(procs)]
    for p in pools:  # start and load now, not on the first frame
        p.submit(int, 0).result()
    turn = itertools.cycle(range(procs))

    class PooledSession(TrackSession):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self.pool = pools[next(turn)]

        async def run(self) -> str:
            try:
                return await super().run()
            finally:
                self.pool.submit(_end, self.sid)

        def _process(self, item):  # called in the app's thread pool: wait there for the pool process
            kind, out = self.pool.submit(_step, self.sid, self.name, item).result()
            if kind == "error":
                raise _SessionError(*out)
            self.metrics.frames.labels("tracked_in_pool").inc()
            return out

    routes.TrackSession = PooledSession  # the prototype's only change to the product
    settings = Settings.from_env(store=store, workers=1, threads=max(8, 2 * procs))
    return create_app(settings)


def main() -> int:
    import uvicorn

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True)
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--procs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--threads", type=int, default=1, help="threads per pool process (re-anchoring)")
    args = ap.parse_args()
    app = build_app(args.store, args.procs, args.threads)
    uvicorn.run(app, host="127.0.0.1", port=args.port, log_level="warning", ws_max_size=20 * 1024 * 1024)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


class PoolServer(Loopback):
    """This prototype in a child process on a loopback port, for ``quatrack bench serve --workers pN``."""

    def __init__(self, store, procs: int, env: dict | None = None) -> None:
        self.store, self.procs, self.env = store, procs, dict(env or {})
        self.port = free_port()
        self.proc = None

    def pids(self) -> list[int]:
        """The event loop process, then its pool processes (its children, from /proc)."""
        out = [self.proc.pid]
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    with open(f"/proc/{entry}/stat") as f:
                        ppid = int(f.read().rsplit(")", 1)[1].split()[1])
                    with open(f"/proc/{entry}/cmdline", "rb") as f:
                        worker = b"resource_tracker" not in f.read()
                except OSError:
                    continue
                if ppid == self.proc.pid and worker:
                    out.append(int(entry))
        return out

    def __enter__(self) -> "PoolServer":
        import subprocess
        import sys

        from quatrack.testing.loopback import wait_for_http

        env = {k: v for k, v in os.environ.items() if not k.startswith("QUATRACK_")}
        env.update(self.env)
        self.proc = subprocess.Popen([sys.executable, "-m", "quatrack.bench.serve_pool", "--store", str(self.store),
                                      "--port", str(self.port), "--procs", str(self.procs)],
                                     env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            wait_for_http(f"{self.url}/readyz", "the pool prototype", 300, alive=lambda: self.proc.poll() is None)
        except RuntimeError:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        import signal
        import subprocess

        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=30)

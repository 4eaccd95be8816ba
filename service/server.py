"""Run the service on a loopback port for tests, the demo and the bench: in a thread, or as a process.

``uvicorn.Server`` in a thread, not a subprocess: starting is fast (the model store is loaded
once), and the caller can stop it deterministically. Port 0 picks a free port.
:class:`ServeProcess` runs ``quatrack serve`` itself (worker processes, signals), and
``testing.balancer.Nginx`` a balancer in front; all three share ``testing.loopback`` (their
addresses and their start-up wait), which sits below both layers.
"""

from __future__ import annotations

import threading

import uvicorn

from quatrack.testing.loopback import Loopback, free_port, wait_for_http

from .app import create_app
from .httphead import BoundedHttpToolsProtocol
from .logs import configure
from .settings import Settings
from .shutdown import GracefulWebSocketProtocol

__all__ = ["BackgroundServer", "ServeProcess", "Loopback", "free_port", "wait_for_http"]


class BackgroundServer(Loopback):
    """``with BackgroundServer(settings) as srv: srv.url`` — serves until the block ends."""

    def __init__(self, settings: Settings, port: int = 0, log_level: str = "warning", wait_ready: bool = True) -> None:
        port = self.port = port or free_port()
        self.settings = settings.replace(host="127.0.0.1", port=port)
        self.app = create_app(self.settings)
        config = uvicorn.Config(self.app, host="127.0.0.1", port=port, log_config=configure(log_level), ws=GracefulWebSocketProtocol,
                                ws_max_size=2 * self.settings.max_body_bytes, lifespan="on", timeout_graceful_shutdown=2,
                                ws_per_message_deflate=False, http=BoundedHttpToolsProtocol,
                                limit_concurrency=self.settings.max_connections)  # as quatrack serve (service/cli.py)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self._run, name=f"quatrack-serve-{port}", daemon=True)
        self.wait_ready = wait_ready
        self.error: BaseException | None = None

    def _run(self) -> None:
        try:
            self.server.run()
        except BaseException as exc:  # reported by start(), not lost in a thread
            self.error = exc

    def start(self) -> "BackgroundServer":
        self.thread.start()
        alive = self.thread.is_alive
        try:  # listening (any answer), then ready if asked
            wait_for_http(f"{self.url}/healthz", "the service", 120, alive, accept=lambda status: True)
            if self.wait_ready:  # (loading done: an empty store's /readyz stays 503, not ready to serve)
                wait_for_http(f"{self.url}/readyz", "the service", 120, alive,
                              accept=lambda status: status == 200 or self._loaded())
        except RuntimeError as exc:
            self.stop()
            raise RuntimeError(f"{exc} {self.error!r}" if self.error else str(exc)) from None
        return self

    def _loaded(self) -> bool:
        """The app's start-up loading is done (whatever ``/readyz`` answers of it)."""
        state = getattr(self.app.state, "quatrack", None)
        return state is not None and state.registry.ready

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)

    def __enter__(self) -> "BackgroundServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _die_with_parent():
    """A ``preexec_fn`` that makes the child get SIGTERM when the process that started it dies
    (Linux ``prctl(PR_SET_PDEATHSIG)``), so that a test or bench killed by a timeout leaves no
    server behind; None where there is no such call (``stop()`` still ends the child). The libc
    function is looked up here, in the parent: between fork and exec the child only calls it."""
    import ctypes
    import signal

    try:
        prctl = ctypes.CDLL("libc.so.6", use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    return lambda: prctl(1, int(signal.SIGTERM))  # 1 = PR_SET_PDEATHSIG


class ServeProcess(Loopback):
    """``quatrack serve`` in a child process on a loopback port: for the bench and the tests that
    need real worker processes or several replicas. ``env`` adds ``QUATRACK_*`` variables.

    ``stop()`` sends SIGTERM (open sessions are closed with code 1012) and waits; the child runs
    in its own process group so that its workers go with it.
    """

    def __init__(self, store, port: int = 0, workers: int = 1, env: dict | None = None,
                 log_level: str = "warning", log_path=None) -> None:
        self.store, self.port, self.workers = store, port or free_port(), workers
        self.env, self.log_level, self.log_path = dict(env or {}), log_level, log_path
        self.proc = None
        self._log = None

    def start(self, timeout: float = 180.0) -> "ServeProcess":
        import os
        import subprocess
        import sys

        env = {k: v for k, v in os.environ.items() if not k.startswith("QUATRACK_") and k != "PROMETHEUS_MULTIPROC_DIR"}
        env.update(self.env)
        self._log = open(self.log_path, "ab") if self.log_path else subprocess.DEVNULL
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "quatrack", "serve", "--store", str(self.store), "--host", "127.0.0.1",
             "--port", str(self.port), "--workers", str(self.workers), "--log-level", self.log_level],
            env=env, stdout=self._log, stderr=self._log, start_new_session=True, preexec_fn=_die_with_parent())
        try:
            wait_for_http(f"{self.url}/readyz", f"quatrack serve on port {self.port}", timeout,
                          alive=lambda: self.proc.poll() is None)
        except RuntimeError:
            self.stop()
            raise
        return self

    def worker_pids(self) -> list[int]:
        """The worker processes (children of the uvicorn supervisor), from /proc (Linux)."""
        import os

        if self.proc is None or self.workers == 1:
            return [self.proc.pid] if self.proc else []
        out = []
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    with open(f"/proc/{entry}/stat") as f:
                        fields = f.read().rsplit(")", 1)[1].split()
                    with open(f"/proc/{entry}/cmdline", "rb") as f:
                        worker = b"spawn_main" in f.read()  # not multiprocessing's resource tracker
                except OSError:
                    continue
                if int(fields[1]) == self.proc.pid and worker:
                    out.append(int(entry))
        return sorted(out)

    def stop(self, sig=None, timeout: float = 30.0) -> None:
        import os
        import signal
        import subprocess

        if self.proc is not None:
            # the whole process group, also when the supervisor has died already: its workers
            # (multiprocessing children, no death signal of their own) outlived it and kept the port
            alive = self.proc.poll() is None
            try:
                os.killpg(self.proc.pid, sig or signal.SIGTERM)
                if alive:
                    self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=timeout)
            except ProcessLookupError:
                pass
        if self._log not in (None, subprocess.DEVNULL):
            self._log.close()
            self._log = None

    def __enter__(self) -> "ServeProcess":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

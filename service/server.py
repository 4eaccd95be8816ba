"""Run the service in a background thread on a loopback port: for tests, the demo and the bench.

``uvicorn.Server`` in a thread, not a subprocess: starting is fast (the model store is loaded
once), and the caller can stop it deterministically. Port 0 picks a free port.
"""

from __future__ import annotations

import socket
import threading
import time
import uvicorn

from .app import create_app
from .logs import configure
from .settings import Settings


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class BackgroundServer:
    """``with BackgroundServer(settings) as srv: srv.url`` — serves until the block ends."""

    def __init__(self, settings: Settings, port: int = 0, log_level: str = "warning", wait_ready: bool = True) -> None:
        port = port or free_port()
        self.settings = settings.replace(host="127.0.0.1", port=port)
        self.app = create_app(self.settings)
        config = uvicorn.Config(self.app, host="127.0.0.1", port=port, log_config=configure(log_level),
                                ws_max_size=2 * self.settings.max_body_bytes, lifespan="on", timeout_graceful_shutdown=2)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self._run, name=f"quatrack-serve-{port}", daemon=True)
        self.wait_ready = wait_ready
        self.error: BaseException | None = None

    def _run(self) -> None:
        try:
            self.server.run()
        except BaseException as exc:  # reported by start(), not lost in a thread
            self.error = exc

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.settings.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.settings.port}"

    def start(self) -> "BackgroundServer":
        self.thread.start()
        deadline = time.monotonic() + 120  # generous: the machine may be busy
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"the service did not start ({self.error!r})")
            time.sleep(0.02)
        if self.wait_ready:
            import httpx

            headers = {"Authorization": f"Bearer {self.settings.api_token}"} if self.settings.api_token else {}
            while httpx.get(f"{self.url}/readyz", headers=headers).status_code != 200:
                if time.monotonic() > deadline:
                    raise RuntimeError("the service did not become ready")
                time.sleep(0.05)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)

    def __enter__(self) -> "BackgroundServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

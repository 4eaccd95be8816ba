"""Things started on a loopback port for tests, the demo and the bench: a free port, their
addresses, and the wait until they answer. Shared by ``service.server`` (the service in a thread
or a process) and :mod:`.balancer` (nginx in front of replicas), so it sits below both.
"""

from __future__ import annotations

import socket
import time
from typing import Callable


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Loopback:
    """Something serving HTTP and WebSocket on ``127.0.0.1:self.port``."""

    port: int

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"


def wait_for_http(url: str, what: str, timeout: float, alive: Callable[[], bool] = lambda: True,
                  accept: Callable[[int], bool] = lambda status: status == 200, headers: dict | None = None) -> None:
    """Poll ``GET url`` until ``accept(status)``; RuntimeError naming ``what`` when ``alive()`` turns
    false (the process died) or after ``timeout`` s (generous: the machine may be busy). A refused
    or reset connection means "not yet"."""
    import httpx

    deadline = time.monotonic() + timeout
    while True:
        try:
            if accept(httpx.get(url, timeout=5, headers=headers).status_code):
                return
        except httpx.TransportError:
            pass
        if not alive() or time.monotonic() > deadline:
            raise RuntimeError(f"{what} did not become ready ({url})")
        time.sleep(0.05)

"""A cap on a worker's open connections (``QUATRACK_MAX_CONNECTIONS``, uvicorn's
``limit_concurrency``): uvicorn had none, so connections held open by one client (slow headers,
idle keep-alive) cost the worker memory and file descriptors without bound. Slow request heads
themselves are a balancer's job (uvicorn has no header read timeout): README, Security."""

from __future__ import annotations

import socket

import pytest

from quatrack.cli import main
from quatrack.service.server import ServeProcess
from quatrack.service.settings import Settings, env_name
from quatrack.testing.loopback import free_port
from quatrack.testing.scenes import example_store


def test_the_default_cap_follows_the_limits():
    s = Settings(max_sessions=10, max_pending_requests=3)
    assert s.max_connections == 10 + 3 + 64
    assert Settings(max_connections=7).max_connections == 7
    with pytest.raises(ValueError, match="max_connections"):
        Settings.from_env(max_connections=0)


@pytest.mark.parametrize("value, expected", [(None, 4 + 8 + 64), ("300", 300)])
def test_serve_gives_uvicorn_the_cap(not_started, value, expected):
    env, started = not_started
    if value is not None:
        env.setenv(env_name("max_connections"), value)
    assert main(["serve", "--store", str(example_store()), "--port", str(free_port()), "--workers", "1"]) == 0
    assert started[0]["limit_concurrency"] == expected


def _get(s: socket.socket) -> bytes:
    s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
    got = b""
    while b"\r\n\r\n" not in got:
        chunk = s.recv(4096)
        assert chunk, got
        got += chunk
    return got.split(b"\r\n", 1)[0]


def test_a_request_beyond_the_cap_is_refused(tmp_path):
    """Two connections held open with QUATRACK_MAX_CONNECTIONS=2: a request on a third is 503
    (it was served: no cap). The held one answered first, so the server counts it."""
    with ServeProcess(example_store(), workers=1, env={env_name("max_connections"): "2"},
                      log_path=tmp_path / "serve.log") as srv:
        held = [socket.create_connection(("127.0.0.1", srv.port), timeout=60) for _ in range(2)]
        try:
            _get(held[0])  # (whatever it answers: the server has accepted both by now)
            with socket.create_connection(("127.0.0.1", srv.port), timeout=60) as s:
                assert b" 503 " in _get(s)
        finally:
            for s in held:
                s.close()

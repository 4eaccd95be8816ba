"""REST pose uploads under a security review: a request's pending slot is taken before its body
is read (uploads held open grew a worker's memory without bound, the "8 then 503" limit applying
only to bodies already read), and a body must arrive within ``QUATRACK_BODY_TIMEOUT_S``.

Raw sockets: the point is what the server does while a body has *not* arrived, which an HTTP
client library cannot hold back. Each test fails without its fix by getting no answer at all
(the server waiting for a body that never comes): the socket's timeout is a bound on a busy
machine, not a speed requirement."""

from __future__ import annotations

import json
import socket

import pytest
from conftest import box_frames_jpeg, wait_until

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

QUERY = "fx=669.7&fy=667.8&cx=320&cy=240"
PATHS = ("/v1/objects/cookie-box/pose", "/v1/pose")


def head(path: str, length: int) -> bytes:
    return (f"POST {path}?{QUERY} HTTP/1.1\r\nHost: x\r\nContent-Type: image/jpeg\r\n"
            f"Content-Length: {length}\r\n\r\n").encode()


def read_answer(s: socket.socket) -> tuple[int, dict, dict]:
    """Status, headers (lower-case names) and JSON body of one response on ``s``."""
    got = b""
    while b"\r\n\r\n" not in got:
        chunk = s.recv(65536)
        assert chunk, f"connection closed without an answer: {got!r}"
        got += chunk
    top, _, body = got.partition(b"\r\n\r\n")
    lines = top.decode("latin-1").split("\r\n")
    headers = dict((k.strip().lower(), v.strip()) for k, _, v in (h.partition(":") for h in lines[1:]))
    while len(body) < int(headers["content-length"]):
        chunk = s.recv(65536)
        assert chunk, "connection closed in the answer's body"
        body += chunk
    return int(lines[0].split()[1]), headers, json.loads(body)


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store(), max_pending_requests=1, body_timeout_s=2.0,
                                   model_poll_s=0)) as srv:
        yield srv


@pytest.mark.parametrize("path", PATHS)
def test_a_request_beyond_the_limit_is_refused_before_its_body(server, path):
    """All slots taken: 503 ``busy`` answered to the headers alone (the body was read whole
    first, then refused — 60 such uploads held open were 600 MB in the worker)."""
    state = server.app.state.quatrack
    state.pending = 1
    try:
        with socket.create_connection(("127.0.0.1", server.port), timeout=30) as s:
            s.sendall(head(path, 5_000_000))  # and not one byte of it
            status, headers, body = read_answer(s)
        assert status == 503 and body["error"]["code"] == "busy", body
        assert int(headers["retry-after"]) > 0
        assert state.pending == 1
    finally:
        state.pending = 0


def test_an_upload_in_progress_holds_its_slot(server):
    """A request still receiving its body counts: another one is 503 ``busy`` meanwhile (it was
    served, the slot being taken only once the first body was in memory)."""
    state = server.app.state.quatrack
    image = box_frames_jpeg(1)[0]
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as slow:
        slow.sendall(head(PATHS[0], len(image)) + image[:1000])
        assert wait_until(lambda: state.pending == 1, 30), "the upload never reached the endpoint"
        with socket.create_connection(("127.0.0.1", server.port), timeout=30) as s:
            s.sendall(head(PATHS[1], len(image)) + image)
            status, _, body = read_answer(s)
        assert status == 503 and body["error"]["code"] == "busy", body
        slow.sendall(image[1000:])
        status, _, body = read_answer(slow)
        assert status == 200 and body["found"] is True, body
    assert wait_until(lambda: state.pending == 0, 30)


@pytest.mark.parametrize("path", PATHS)
def test_a_body_that_never_ends_is_cut_at_the_deadline(server, path):
    """Half a body, then nothing: 408 ``body_timeout`` after ``QUATRACK_BODY_TIMEOUT_S`` and the
    connection closed; the slot is free again (it was held for as long as the client liked)."""
    state = server.app.state.quatrack
    with socket.create_connection(("127.0.0.1", server.port), timeout=60) as s:
        s.sendall(head(path, 100_000) + b"\xff\xd8" + b"x" * 50_000)
        status, headers, body = read_answer(s)
        assert status == 408 and body["error"]["code"] == "body_timeout", body
        assert headers.get("connection") == "close"
        assert s.recv(10) == b""  # closed by the server
    assert wait_until(lambda: state.pending == 0, 30)


def test_the_body_timeout_is_a_checked_setting():
    for bad in ("0", "-1", "inf", "x"):
        with pytest.raises(ValueError, match="QUATRACK_BODY_TIMEOUT_S|body_timeout_s"):
            Settings.from_env(body_timeout_s=bad)

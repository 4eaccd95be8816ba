"""The service's HTTP surface as monitors, browsers and curl meet it: HEAD on every GET page and
endpoint, and the opt-in allowed hosts (``QUATRACK_ALLOWED_HOSTS``, against DNS rebinding).
An empty store without preloading: these tests need no model."""

from __future__ import annotations

import socket

import pytest
from fastapi.testclient import TestClient

from quatrack.service.app import create_app
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings

GET_PATHS = ["/healthz", "/readyz", "/viewer", "/viewer/", "/viewer/viewer.js", "/viewer/viewer.css", "/docs",
             "/docs/oauth2-redirect", "/redoc", "/openapi.json", "/docs-assets/swagger-ui.css", "/v1/objects"]


def _settings(tmp_path, **kw) -> Settings:
    return Settings(store=tmp_path, preload=False, workers=1, threads=1, model_poll_s=0, **kw)


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(_settings(tmp_path))) as c:
        yield c


@pytest.mark.parametrize("path", GET_PATHS)
def test_head_answers_as_get_without_a_body(client, path):
    """``curl -I /viewer``, a monitor's HEAD on ``/docs``: 405 ``method_not_allowed``; only the
    probes and the docs' static assets answered HEAD."""
    get, head = client.get(path, follow_redirects=False), client.head(path, follow_redirects=False)
    assert head.status_code == get.status_code and head.status_code in (200, 307), (path, head.status_code)
    assert head.content == b""
    for name in ("content-type", "content-length", "location", "content-security-policy", "x-frame-options",
                 "x-content-type-options"):
        assert head.headers.get(name) == get.headers.get(name), (path, name)


def test_head_of_what_has_no_get_is_still_refused(client):
    """A POST-only endpoint or an unknown path answers HEAD as it answers GET (405 naming the
    method it has, 404), with the contract's error headers and no body."""
    for path, status in (("/v1/objects/cookie-box/pose", 405), ("/v1/pose", 405), ("/no-such-page", 404)):
        get, head = client.get(path), client.head(path)
        assert head.status_code == get.status_code == status, path
        assert head.content == b"" and head.headers.get("allow") == get.headers.get("allow")


def test_head_is_logged_and_counted_as_head(client):
    assert client.head("/viewer/").status_code == 200
    metrics = client.get("/metrics").text
    assert 'method="HEAD",route="/viewer/",status="200"' in metrics, metrics[:2000]


def _raw(port: int, request: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        s.sendall(request)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
    return out


def test_head_over_uvicorn_sends_the_length_and_no_body(tmp_path):
    """Through uvicorn itself (what a client gets on the wire): the GET's Content-Length, then the
    connection carries nothing more."""
    with BackgroundServer(_settings(tmp_path)) as srv:
        get = _raw(srv.port, b"GET /viewer/ HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        head = _raw(srv.port, b"HEAD /viewer/ HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
    get_head, body = get.split(b"\r\n\r\n", 1)
    status, rest = head.split(b"\r\n", 1)
    assert status == b"HTTP/1.1 200 OK", head[:200]
    assert rest.endswith(b"\r\n\r\n"), head[-200:]  # nothing after the headers
    assert f"content-length: {len(body)}".encode() in rest.lower() and len(body) > 1000


def test_a_token_read_with_its_line_end_is_the_token_clients_send(tmp_path):
    """``QUATRACK_API_TOKEN`` from a secret file ending in a line break: every request was 401,
    the header's value reaching the server without it."""
    with TestClient(create_app(_settings(tmp_path, api_token="s3cret\n"))) as c:
        assert c.get("/v1/objects", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert c.get("/v1/objects").status_code == 401

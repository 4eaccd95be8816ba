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
    ok = (503,) if path == "/readyz" else (200, 307)  # (/readyz: the store is empty, not ready)
    assert head.status_code == get.status_code and head.status_code in ok, (path, head.status_code)
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


def test_the_probes_answer_head_through_the_middleware_ready_or_not(client):
    """The probes have no HEAD routes of their own any more (``HeadAsGet`` answers HEAD for every
    GET route): ``/readyz`` not ready is 503 to HEAD as to GET, with the same headers, no body."""
    state = client.app.state.quatrack
    state.registry.ready = False
    try:
        get, head = client.get("/readyz"), client.head("/readyz")
    finally:
        state.registry.ready = True
    assert head.status_code == get.status_code == 503 and head.content == b""
    assert head.headers["content-length"] == get.headers["content-length"] != "0"
    assert client.head("/healthz").status_code == 200


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


@pytest.mark.parametrize("header, ok", [
    ("Bearer s3cret", True), ("Bearer  s3cret", True), ("Bearer s3cret ", True), ("bearer s3cret", True),
    ("BEARER   s3cret  ", True), ("Bearer s3cre", False), ("Bearer s3cret2", False), ("Basic s3cret", False),
    ("Bearers3cret", False), ("Bearer", False), ("s3cret", False), ("Bearer s3 cret", False),
])
def test_rest_and_websocket_read_the_bearer_header_by_one_rule(tmp_path, monkeypatch, header, ok):
    """``Authorization: Bearer  s3cret`` (two spaces) or with a trailing blank was 401 on REST
    with the FastAPI releases ``pyproject.toml`` allows whose HTTPBearer keeps the blanks (before
    fastapi PR #14786; this one strips them, so its reading is put back as it was here) and
    accepted by the WebSocket (which stripped them): one reading (``routes.bearer_token``) now
    decides both, whatever FastAPI's."""
    import fastapi.security.http
    from starlette.testclient import WebSocketDenialResponse

    def kept_blanks(value):  # FastAPI's reading before PR #14786
        scheme, _, param = (value or "").partition(" ")
        return scheme, param

    monkeypatch.setattr(fastapi.security.http, "get_authorization_scheme_param", kept_blanks)
    with TestClient(create_app(_settings(tmp_path, api_token="s3cret"))) as c:
        rest = c.get("/v1/objects", headers={"Authorization": header})
        assert rest.status_code == (200 if ok else 401), (header, rest.text)
        with pytest.raises(WebSocketDenialResponse) as refused:  # past the token: the store is empty
            with c.websocket_connect("/v1/objects/cookie-box/track", headers={"Authorization": header}):
                pass
        assert refused.value.json()["error"]["code"] == ("unknown_object" if ok else "unauthorized"), header


# --- QUATRACK_ALLOWED_HOSTS ----------------------------------------------------------------------

def test_without_allowed_hosts_any_host_is_answered(client):
    """The default keeps every existing behaviour: whatever the ``Host``."""
    for host in ("testserver", "127.0.0.1:8000", "attacker.example", "[::1]:8000"):
        assert client.get("/v1/objects", headers={"Host": host}).status_code == 200, host


@pytest.mark.parametrize("host, ok", [
    ("localhost", True), ("LOCALHOST:8000", True), ("127.0.0.1:8000", True), ("[::1]:8000", True), ("::1", True),
    ("localhost.", True), ("cam.lab.example.org", True), ("lab.example.org", False),
    ("rebind.attacker.example", False), ("localhost.attacker.example", False), ("", False), ("[::1", False),
])
def test_allowed_hosts_refuse_another_host_with_the_contract_s_error(tmp_path, host, ok):
    """DNS rebinding: a page of ``rebind.attacker.example`` (resolving to 127.0.0.1) reached a
    local server without a token as its own origin. With ``QUATRACK_ALLOWED_HOSTS`` its ``Host``
    is refused; the probes still answer (health checks call them by address)."""
    settings = _settings(tmp_path, allowed_hosts="localhost, 127.0.0.1,[::1],*.lab.example.org")
    with TestClient(create_app(settings)) as c:
        r = c.get("/v1/objects", headers={"Host": host})
        if ok:
            assert r.status_code == 200, (host, r.text)
        else:
            assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_host", (host, r.text)
            assert "QUATRACK_ALLOWED_HOSTS" in r.json()["error"]["message"]
            assert r.headers["x-content-type-options"] == "nosniff"
        for probe, status in (("/healthz", 200), ("/readyz", 503)):  # (answered, not refused: the store is empty)
            assert c.get(probe, headers={"Host": host}).status_code == status, (probe, host)


@pytest.mark.parametrize("hosts", [["rebind.attacker.example", "localhost"], ["localhost", "rebind.attacker.example"],
                                   ["localhost", "localhost"]])
def test_allowed_hosts_refuse_a_request_with_two_host_headers(tmp_path, hosts):
    """Two ``Host`` headers passed the check when the last one was allowed (it read the last,
    Starlette and the origin check the first): which host is meant is the request's to say once."""
    settings = _settings(tmp_path, allowed_hosts="localhost")
    with TestClient(create_app(settings)) as c:
        r = c.get("/v1/objects", headers=[("host", h) for h in hosts])
        assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_host", r.text
        assert "several Host headers" in r.json()["error"]["message"]
        assert c.get("/v1/objects", headers={"Host": "localhost"}).status_code == 200


def test_allowed_hosts_refuse_a_websocket_handshake(tmp_path):
    from starlette.testclient import WebSocketDenialResponse

    settings = _settings(tmp_path, allowed_hosts="localhost")
    with TestClient(create_app(settings)) as c:
        with pytest.raises(WebSocketDenialResponse) as refused:
            with c.websocket_connect("/v1/objects/cookie-box/track", headers={"Host": "rebind.attacker.example"}):
                pass
        assert refused.value.status_code == 400 and refused.value.json()["error"]["code"] == "invalid_host"
        assert 'quatrack_ws_refused_total{code="invalid_host"} 1.0' in c.get("/metrics", headers={"Host": "localhost"}).text


def test_allowed_hosts_over_uvicorn(tmp_path):
    """On the wire (a real WebSocket handshake is answered 400 with the JSON error)."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    with BackgroundServer(_settings(tmp_path, allowed_hosts="127.0.0.1")) as srv:
        ok = _raw(srv.port, b"GET /v1/objects HTTP/1.1\r\nHost: 127.0.0.1:1\r\nConnection: close\r\n\r\n")
        bad = _raw(srv.port, b"GET /v1/objects HTTP/1.1\r\nHost: rebind.attacker.example\r\nConnection: close\r\n\r\n")
        assert ok.startswith(b"HTTP/1.1 200"), ok[:200]
        assert bad.startswith(b"HTTP/1.1 400") and b'"invalid_host"' in bad, bad[:300]
        with pytest.raises(InvalidStatus) as refused:
            with connect(f"{srv.ws_url}/v1/objects/cookie-box/track", open_timeout=30,
                         additional_headers={"Host": "rebind.attacker.example"}):
                pass
        assert refused.value.response.status_code == 400 and b"invalid_host" in refused.value.response.body


@pytest.mark.parametrize("value", ["http://localhost", "localhost:8000", "a,,b/c"])
def test_allowed_hosts_are_names_without_scheme_or_port(monkeypatch, value):
    monkeypatch.setenv("QUATRACK_ALLOWED_HOSTS", value)
    with pytest.raises(ValueError, match="^environment variable QUATRACK_ALLOWED_HOSTS=.*is not a host name"):
        Settings.from_env()


# --- QUATRACK_CORS_ORIGINS as operators write them -----------------------------------------------

@pytest.mark.parametrize("written", ["https://app.example/", "https://App.Example", "https://app.example:443"])
def test_an_origin_written_with_a_slash_case_or_default_port_still_matches(tmp_path, written):
    """``QUATRACK_CORS_ORIGINS=https://app.example/`` (copied from the address bar) was compared
    whole with the browser's ``Origin: https://app.example``: no CORS header, and the page's
    WebSocket refused 403 ``forbidden_origin``, with nothing said at start."""
    origin = {"Origin": "https://app.example"}
    with TestClient(create_app(_settings(tmp_path, cors_origins=written))) as c:
        assert c.get("/healthz", headers=origin).headers.get("access-control-allow-origin") == "https://app.example"
        # past the origin check: the store is empty (a browser's refusal is an error message:
        # test_service_errors_ws_browser.py)
        with c.websocket_connect("/v1/objects/cookie-box/track", headers=origin) as ws:
            assert ws.receive_json()["error"]["code"] == "unknown_object"


@pytest.mark.parametrize("value", ["app.example", "https://app.example/page", "localhost:8080"])
def test_an_entry_that_is_no_origin_is_refused(monkeypatch, value):
    monkeypatch.setenv("QUATRACK_CORS_ORIGINS", value)
    with pytest.raises(ValueError, match="^environment variable QUATRACK_CORS_ORIGINS=.*is not an origin"):
        Settings.from_env()


def test_a_request_id_is_echoed_only_when_it_is_ascii(tmp_path):
    """``X-Request-ID: ²³`` (bytes B2 B3) passed the check (``str.isalnum``) and came back as
    C2 B2 C2 B3: another id than the client's, in its answer and the log."""
    with BackgroundServer(_settings(tmp_path)) as srv:
        def rid(value: bytes) -> bytes:
            answer = _raw(srv.port, b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n"
                                    b"X-Request-ID: " + value + b"\r\n\r\n")
            return next(line.split(b": ", 1)[1] for line in answer.split(b"\r\n") if line.lower().startswith(b"x-request-id:"))

        assert rid(b"abc-123") == b"abc-123"
        fresh = rid(b"\xb2\xb3")
        assert fresh.isascii() and fresh.isalnum() and len(fresh) == 16, fresh


# --- a page of another site calling the REST API of a server without a token ----------------------

@pytest.mark.parametrize("path", ["/v1/objects/cookie-box/pose", "/v1/objects/cookie-box/reload", "/v1/pose"])
def test_a_foreign_pages_post_is_refused_without_a_token(tmp_path, path):
    """A multipart POST is a "simple" request: a browser sends it from any page without a
    preflight, and it returned 200 (the page cannot read it, but the server did the work). Like
    the WebSocket's handshake, a foreign Origin is refused (403 forbidden_origin) on a server
    without a token; the server's own pages, listed origins and clients without Origin are not."""
    with TestClient(create_app(_settings(tmp_path))) as c:
        r = c.post(path, headers={"Origin": "https://evil.example"}, files={"image": ("x.png", b"not an image")})
        assert r.status_code == 403 and r.json()["error"]["code"] == "forbidden_origin", r.text
        for headers in ({"Origin": "http://testserver"}, {}):  # its own page; no browser
            r = c.post(path, headers=headers, files={"image": ("x.png", b"not an image")})
            assert r.status_code != 403, (headers, r.text)
    with TestClient(create_app(_settings(tmp_path, cors_origins="https://app.example"))) as c:
        r = c.post(path, headers={"Origin": "https://app.example"}, files={"image": ("x.png", b"not an image")})
        assert r.status_code != 403, r.text
    with TestClient(create_app(_settings(tmp_path, api_token="t0ken-for-tests"))) as c:  # the token decides
        r = c.post(path, headers={"Origin": "https://evil.example", "Authorization": "Bearer t0ken-for-tests"},
                   files={"image": ("x.png", b"not an image")})
        assert r.status_code != 403, r.text

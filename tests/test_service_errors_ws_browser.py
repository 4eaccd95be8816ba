"""A refused WebSocket handshake as a browser meets it. Browsers hide a refused handshake's HTTP
answer (the page sees a bare 1006, whatever the cause), so a handshake with an ``Origin`` header
(every browser sends one) is accepted, gets the contract's error message and is closed with 1008
(policy), 1011 (server error) or 1013 (try again later) and the reason ``code: message``. A client
that is no browser (no ``Origin``) still gets the HTTP refusal, as docs/contract.md says, and so
does a handshake refused as a foreign origin or host (``forbidden_origin``, ``invalid_host``: the
attack those checks stop is told nothing more; the contract's 403 / 400).
"""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse
from starlette.websockets import WebSocketDisconnect

from quatrack.service.app import create_app
from quatrack.service.routes import close_reason
from quatrack.service.settings import Settings
from quatrack.viewsets.store import MANIFEST

TOKEN = "ws-browser-token"
PAGE = {"origin": "http://testserver"}  # the viewer's own page


def _client(tmp_path, **kw) -> TestClient:
    (tmp_path / "broken").mkdir(exist_ok=True)  # a model the store lists but nobody can load
    (tmp_path / "broken" / MANIFEST).write_text("{not json")
    settings = Settings(store=tmp_path, preload=False, workers=1, threads=1, model_poll_s=0, max_sessions=1, **kw)
    return TestClient(create_app(settings))


def _browser_refusal(c: TestClient, path: str, headers: dict) -> tuple[dict, int, str]:
    """The error message, the close code and the close reason a browser's handshake gets."""
    with c.websocket_connect(path, headers=headers) as ws:
        msg = ws.receive_json()
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_text()
    return msg, closed.value.code, closed.value.reason


@pytest.mark.parametrize("case, settings, path, headers, status, code, close", [
    ("unauthorized", {"api_token": TOKEN}, "/v1/objects/broken/track", PAGE, 401, "unauthorized", 1008),
    ("unknown_object", {}, "/v1/objects/nothing/track", PAGE, 404, "unknown_object", 1008),
    ("no route", {}, "/v1/nothing", PAGE, 404, "not_found", 1008),
    ("model_unavailable", {}, "/v1/objects/broken/track", PAGE, 503, "model_unavailable", 1011),
])
def test_a_browsers_refused_handshake_is_an_error_message_and_a_close_code(tmp_path, case, settings, path, headers,
                                                                             status, code, close):
    with _client(tmp_path, **settings) as c:
        msg, got_close, reason = _browser_refusal(c, path, headers)
        assert msg["type"] == "error" and msg["error"]["code"] == code, msg
        assert (got_close, reason) == (close, close_reason(code, msg["error"]["message"]))
        assert reason.startswith(code + ": ")
        # the same handshake without Origin (no browser): the HTTP refusal, as before
        with pytest.raises(WebSocketDenialResponse) as denied:
            with c.websocket_connect(path, headers={k: v for k, v in headers.items() if k != "origin"}):
                pass
        assert denied.value.status_code == status and denied.value.json()["error"]["code"] == code


@pytest.mark.parametrize("settings, headers, status, code", [
    ({}, {"origin": "https://evil.example"}, 403, "forbidden_origin"),
    ({"allowed_hosts": ("localhost",)}, PAGE, 400, "invalid_host"),
])
def test_a_foreign_origin_or_host_is_refused_in_http_even_to_a_browser(tmp_path, settings, headers, status, code):
    """The page of another site (cross-site WebSocket hijacking) or one reached under a host
    name the server does not serve (DNS rebinding) gets the documented HTTP refusal: no socket is
    opened for it, and it is told nothing."""
    with _client(tmp_path, **settings) as c:
        with pytest.raises(WebSocketDenialResponse) as denied:
            with c.websocket_connect("/v1/objects/broken/track", headers=headers):
                pass
        assert denied.value.status_code == status and denied.value.json()["error"]["code"] == code


def test_too_many_sessions_closes_with_try_again_later(tmp_path):
    with _client(tmp_path) as c:
        assert c.app.state.quatrack.sessions.try_open() is not None  # the one session allowed is taken
        msg, close, reason = _browser_refusal(c, "/v1/objects/broken/track", PAGE)
        assert msg["error"]["code"] == "too_many_sessions" and close == 1013 and reason.startswith("too_many_sessions: ")
        with pytest.raises(WebSocketDenialResponse) as denied:
            with c.websocket_connect("/v1/objects/broken/track"):
                pass
        assert denied.value.status_code == 503 and denied.value.headers["retry-after"]


def test_the_close_reason_fits_a_close_frame():
    reason = close_reason("forbidden_origin", "é" * 200)
    assert len(reason.encode()) <= 123 and reason.startswith("forbidden_origin: é")

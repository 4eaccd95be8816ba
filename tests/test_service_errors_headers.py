"""Error answers carry the headers every answer carries. A 500 (an exception nothing handled) was
made by Starlette's outermost middleware, outside CORS, the security headers and the request id:
a browser page allowed by ``QUATRACK_CORS_ORIGINS`` saw a network error instead of the JSON body,
and the answer had no ``X-Request-ID`` to find its log line by, no ``nosniff``. And a page could
not read a 503's ``Retry-After`` (not in ``Access-Control-Expose-Headers``).
"""

from __future__ import annotations

import logging

import pytest
from fastapi.testclient import TestClient

from quatrack.service.app import create_app
from quatrack.service.routes import get_state
from quatrack.service.settings import Settings
from quatrack.viewsets.store import MANIFEST

PAGE = "https://app.example"


@pytest.fixture
def client(tmp_path):
    (tmp_path / "box").mkdir()
    (tmp_path / "box" / MANIFEST).write_text("{}")  # a name the store knows (nothing here is loaded)
    settings = Settings(store=tmp_path, preload=False, workers=1, threads=1, model_poll_s=0, cors_origins=(PAGE,))
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        yield c


def test_an_unexpected_error_is_the_json_500_with_every_answers_headers(client, caplog):
    def broken():
        raise RuntimeError("a bug")

    client.app.dependency_overrides[get_state] = broken
    with caplog.at_level(logging.ERROR, logger="quatrack.service"):
        r = client.get("/v1/objects", headers={"Origin": PAGE, "X-Request-ID": "trace-500"})
    assert r.status_code == 500 and r.json() == {"error": {"code": "internal", "message": "internal error (logged on the server)"}}
    assert r.headers["access-control-allow-origin"] == PAGE
    assert r.headers["x-request-id"] == "trace-500"
    assert r.headers["x-content-type-options"] == "nosniff"
    assert any("unexpected error on GET /v1/objects" in rec.getMessage() and rec.exc_info for rec in caplog.records)


def test_a_page_may_read_retry_after(client):
    state = client.app.state.quatrack
    state.pending = state.settings.max_pending_requests  # the pose requests in progress: the next is busy
    r = client.post("/v1/objects/box/pose?fx=500&fy=500&cx=320&cy=240", content=b"\xff\xd8",
                    headers={"Origin": PAGE, "Content-Type": "image/jpeg"})
    assert r.status_code == 503 and r.json()["error"]["code"] == "busy" and r.headers["retry-after"]
    exposed = {h.strip().lower() for h in r.headers["access-control-expose-headers"].split(",")}
    assert {"retry-after", "x-request-id"} <= exposed

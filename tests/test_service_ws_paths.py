"""WebSocket handshakes on paths no route serves get the service's JSON refusal (404
``not_found``; Starlette's was a bare 403 with an empty body), and the tracking path with a final
slash, which ``deploy/nginx.conf``'s ``track/?$`` passes on, is served as the path without it."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

CAMERA = json.loads((Path(__file__).resolve().parent.parent / "examples" / "cookie-box" / "camera.json").read_text())


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store())) as srv:
        yield srv


@pytest.mark.parametrize("path", ["/v1/objects/cookie-box/trak", "/v1/nothing",
                                  "/v1/objects/cookie-box/track//"])
def test_an_unmatched_websocket_path_is_a_json_404(server, path):
    with pytest.raises(InvalidStatus) as err:
        connect(server.ws_url + path, open_timeout=20)
    response = err.value.response
    assert response.status_code == 404, (response.status_code, response.body)
    body = json.loads(response.body)
    assert body["error"]["code"] == "not_found" and "/v1/objects/NAME/track" in body["error"]["message"], body


def test_the_track_path_with_a_final_slash_is_served(server):
    nginx = (Path(__file__).resolve().parent.parent / "deploy" / "nginx.conf").read_text()
    assert re.search(r"location ~ \^/v1/objects/\[\^/\]\+/track/\?\$", nginx)  # what the balancer passes on
    with connect(server.ws_url + "/v1/objects/cookie-box/track/", open_timeout=20) as ws:
        ws.send(json.dumps({**CAMERA, "ack": True}))
        assert json.loads(ws.recv(timeout=60))["type"] == "ready"

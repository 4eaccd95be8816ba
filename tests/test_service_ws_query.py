"""The track WebSocket's handshake refuses a query parameter it does not read, 422 as the pose
endpoints refuse theirs: it opened the session and ignored it, so a camera given in the URL
(``?fx=…``, ``?dist_coeffs=…``, as the pose endpoints take it) was dropped without a word."""

from __future__ import annotations

import json

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

CAMERA = {"width": 640, "height": 480, "fx": 669.7, "fy": 667.8, "cx": 320.0, "cy": 240.0, "ack": True}


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store())) as srv:
        yield srv


def refusal(srv, query: str) -> tuple[int, dict]:
    with pytest.raises(InvalidStatus) as err:
        connect(f"{srv.ws_url}/v1/objects/cookie-box/track?{query}", open_timeout=20)
    return err.value.response.status_code, json.loads(err.value.response.body)["error"]


@pytest.mark.parametrize("query", ["dist_coeffs=0,0,0,0", "fx=600", "dist=0,0,0,0,0", "K=1,0,0"])
def test_a_camera_in_the_query_is_refused_pointing_to_the_first_message(server, query):
    status, error = refusal(server, query)
    assert status == 422 and error["code"] == "bad_camera", error
    assert "first message" in error["message"] and repr(query.split("=")[0]) in error["message"], error


@pytest.mark.parametrize("query, meant", [("foo=1", None), ("formt=ros", "format"), ("mesh_units=cm", "mesh_unit"),
                                          ("access_token=x", "token")])
def test_another_unknown_parameter_is_refused_with_the_nearest_name(server, query, meant):
    status, error = refusal(server, query)
    assert status == 422 and error["code"] == "invalid_input", error
    assert "token, format, mesh_unit" in error["message"], error
    assert (f"did you mean {meant!r}?" in error["message"]) if meant else "did you mean" not in error["message"]


def test_the_parameters_it_reads_still_open_a_session(server):
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track?format=ros&mesh_unit=cm", open_timeout=20) as ws:
        ws.send(json.dumps(CAMERA))
        assert json.loads(ws.recv(timeout=60))["type"] == "ready"

"""The camera's refusals say what is wrong with the name the user wrote: a NaN focal length is
not finite (it was told "greater than 0"), ``dist`` is named ``dist`` with its 4, 5 or 8 numbers
(the message named ``dist_coeffs``, the name the query refuses), a parameter given twice is
refused (the last one was used in silence), a camera parameter that is not a number is named
``fx``, not ``query.fx``, and on the WebSocket ``{}`` as the first message is a camera with its
fields missing (it was ``camera_required``)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from quatrack.service.app import create_app
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

Q = "fx=669.7&fy=667.8&cx=320&cy=240"


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(Settings(store=example_store(), workers=1, threads=1, model_poll_s=0))) as c:
        yield c


def pose(client, query: str):
    img = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
    r = client.post(f"/v1/objects/cookie-box/pose?{query}", content=img, headers={"content-type": "image/jpeg"})
    return r.status_code, r.json()["error"]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_focal_length_that_is_not_finite_is_said_so(client, value):
    status, error = pose(client, Q.replace("fx=669.7", f"fx={value}"))
    assert status == 422 and error == {"code": "bad_camera", "message": error["message"]}
    assert error["message"].startswith("fx: must be finite"), error


@pytest.mark.parametrize("dist", ["0,0,0,0,0,0", "0,0,0", "a,b"])
def test_dist_is_named_dist_with_its_counts(client, dist):
    status, error = pose(client, f"{Q}&dist={dist}")
    assert status == 422 and error["code"] == "bad_camera"
    msg = error["message"]
    assert msg.startswith("dist: 4, 5 or 8 comma-separated numbers") and "k1,k2,p1,p2[,k3[,k4,k5,k6]]" in msg, msg
    assert "dist_coeffs" not in msg


def test_eight_coefficients_are_taken(client):
    img = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
    r = client.post(f"/v1/objects/cookie-box/pose?{Q}&dist=0,0,0,0,0,0,0,0", content=img,
                    headers={"content-type": "image/jpeg"})
    assert r.status_code == 200 and r.json()["found"] is False, r.text


@pytest.mark.parametrize("query, name", [(f"{Q}&fx=100", "fx"), (f"format=json&{Q}&format=ros", "format")])
def test_a_parameter_given_twice_is_refused_naming_it(client, query, name):
    status, error = pose(client, query)
    assert status == 422 and error["message"] == f"query parameter {name!r} is given 2 times: give it once", error


def test_a_camera_parameter_that_is_not_a_number_is_named_as_written(client):
    status, error = pose(client, Q.replace("fx=669.7", "fx=abc"))
    assert status == 422 and error["code"] == "bad_camera" and error["message"].startswith("fx: "), error


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store())) as srv:
        yield srv


def test_an_empty_object_first_on_the_websocket_is_a_camera_missing_its_fields(server):
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
        ws.send("{}")
        m = json.loads(ws.recv(timeout=60))
        assert m["error"] == {"code": "bad_camera", "message": "camera: fields fx, fy, cx, cy are required"}, m
        ws.send(json.dumps({"fx": 600.0}))
        m = json.loads(ws.recv(timeout=60))
        assert m["error"] == {"code": "bad_camera", "message": "camera: fields fy, cx, cy are required"}, m


def test_a_websocket_parameter_given_twice_is_refused(server):
    with pytest.raises(InvalidStatus) as err:
        connect(f"{server.ws_url}/v1/objects/cookie-box/track?format=ros&mesh_unit=cm&mesh_unit=m", open_timeout=20)
    assert err.value.response.status_code == 422
    assert "'mesh_unit' is given 2 times" in json.loads(err.value.response.body)["error"]["message"]

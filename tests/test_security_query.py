"""The pose endpoints refuse query parameters they do not read: ``?dist_coeffs=…`` (the camera
JSON's name; the query's is ``dist``) was ignored, and the pose came without the lens's
distortion, in silence. Other programs' names for a camera field are pointed to the query's, as
camera JSON refuses them (``viewsets.camera.FIELD_ALIASES``)."""

from __future__ import annotations

import httpx
import pytest
from conftest import box_frames_jpeg

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

CAMERA = {"fx": 669.7, "fy": 667.8, "cx": 320.0, "cy": 240.0}
PATHS = ("/v1/objects/cookie-box/pose", "/v1/pose")


@pytest.fixture(scope="module")
def client():
    with BackgroundServer(Settings(store=example_store(), model_poll_s=0)) as srv, \
            httpx.Client(base_url=srv.url, timeout=120) as c:
        yield c


@pytest.fixture(scope="module")
def image():
    return box_frames_jpeg(1)[0]


def post(client, path, image, **extra):
    return client.post(path, content=image, params={**CAMERA, **extra}, headers={"content-type": "image/jpeg"})


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("key, meant, code", [
    ("dist_coeffs", "'dist'", "bad_camera"),
    ("D", "'dist'", "bad_camera"),
    ("k1", "'dist'", "bad_camera"),
    ("distortion", "'dist'", "bad_camera"),
    ("image_width", "'width'", "bad_camera"),
    ("K", "'fx', 'fy', 'cx', 'cy'", "bad_camera"),
    ("fxx", "'fx'", "bad_camera"),
    ("fromat", "'format'", "invalid_input"),
    ("focal", None, "bad_camera"),
])
def test_an_unknown_query_parameter_is_refused(client, image, path, key, meant, code):
    r = post(client, path, image, **{key: "0.1,0,0,0"})
    body = r.json()
    assert r.status_code == 422 and body["error"]["code"] == code, r.text
    msg = body["error"]["message"]
    assert msg.startswith(f"unknown query parameter {key!r}"), msg
    assert (f"(did you mean {meant}?)" in msg) if meant else "did you mean" not in msg, msg
    known = "fx, fy, cx, cy, width, height, dist, format, mesh_unit" + (", objects" if path == "/v1/pose" else "")
    assert msg.endswith(f"the pose endpoints take {known}"), msg


def test_a_token_in_a_rest_query_is_said_to_be_unread(client, image):
    r = post(client, PATHS[0], image, token="s3cret")
    assert r.status_code == 422 and "Authorization: Bearer" in r.json()["error"]["message"], r.text
    assert "s3cret" not in r.text


def test_the_known_parameters_are_still_served(client, image):
    r = post(client, PATHS[0], image, dist="0,0,0,0", format="ros", mesh_unit="cm", width=640, height=480)
    assert r.status_code == 200 and r.json()["found"] is True, r.text

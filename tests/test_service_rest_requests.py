"""REST pose requests' refusals in a REST client's terms: a camera size mismatch names the
intrinsics to send (not ``camera.scaled(...)``, Python); ``width`` without ``height`` is refused
as a camera file with one of them is; a camera in both the query and the multipart body is
ambiguous; a duplicated multipart field is named."""

from __future__ import annotations

import json

import cv2
import httpx
import pytest

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store
from test_service_http import CAMERA, assert_error, jpeg, video_frames

POSE = "/v1/objects/cookie-box/pose"
INTRINSICS = {k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}


@pytest.fixture(scope="module")
def client():
    with BackgroundServer(Settings(store=example_store())) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        yield c


@pytest.fixture(scope="module")
def frame():
    return video_frames(1, start=10)[0]


def test_a_camera_for_the_full_size_names_the_intrinsics_for_the_half_size(client, frame):
    h, w = frame.shape[:2]
    half = jpeg(cv2.resize(frame, (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    for path in (POSE, "/v1/pose"):
        r = client.post(path, files={"image": ("f.jpg", half, "image/jpeg")}, data={"camera": json.dumps(CAMERA)})
        msg = assert_error(r, 422, "bad_image")["error"]["message"]
        assert msg.startswith(f"the camera is for {w}×{h} px images but the image is {w // 2}×{h // 2} px"), msg
        assert "scaled(" not in msg and f"width={w // 2}, height={h // 2}" in msg, msg
        assert f"fx={(CAMERA['fx'] * 0.5):.6g}" in msg, msg


@pytest.mark.parametrize("params, files_camera, says", [
    ({**INTRINSICS, "width": 640}, False, "query parameters width and height go together"),
    ({"width": 640, "height": 480}, True, "query parameters width, height and dist go with fx, fy, cx and cy"),
    (INTRINSICS, True, "the camera is given twice"),
    ({}, {k: v for k, v in CAMERA.items() if k != "height"}, "camera: width and height go together"),
])
def test_a_half_given_or_twice_given_camera_is_refused(client, frame, params, files_camera, says):
    data = {} if files_camera is False else {"camera": json.dumps(CAMERA if files_camera is True else files_camera)}
    r = client.post(POSE, params=params, files={"image": ("f.jpg", jpeg(frame), "image/jpeg")}, data=data)
    assert says in assert_error(r, 422, "bad_camera")["error"]["message"]


def test_a_duplicated_multipart_field_is_named(client, frame):
    img = ("f.jpg", jpeg(frame), "image/jpeg")
    cam = ("camera.json", json.dumps(CAMERA).encode(), "application/json")
    for files, field in (([("image", img), ("image", img), ("camera", cam)], "image"),
                         ([("image", img), ("camera", cam), ("camera", cam)], "camera")):
        r = client.post(POSE, files=files)
        assert f"multipart field '{field}' is given 2 times" in assert_error(r, 400, "bad_request")["error"]["message"]
    r = client.post(POSE, files=[("image", img)] * 5)
    assert "a pose request has one field 'image'" in assert_error(r, 400, "bad_request")["error"]["message"]


def test_a_camera_stating_the_wrong_size_is_not_told_to_scale(client, frame):
    """User report (session 73): the intrinsics of this image under another size's width and
    height were answered "send fx=…/2": followed, the object was found 47 % off in depth."""
    h, w = frame.shape[:2]
    wrong = CAMERA | {"width": 2 * w, "height": 2 * h}
    for path in (POSE, "/v1/pose"):
        r = client.post(path, files={"image": ("f.jpg", jpeg(frame), "image/jpeg")}, data={"camera": json.dumps(wrong)})
        msg = assert_error(r, 422, "bad_image")["error"]["message"]
        assert "are its width and height wrong?" in msg and "send the camera" not in msg, msg

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

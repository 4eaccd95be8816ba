"""A multipart ``camera`` field in OpenCV YAML (the camera files ``quatrack locate --camera`` and
the Python client accept) is told that the field is JSON and how to convert it: it was
``camera: Invalid JSON: expected value at line 1 column 1``."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from quatrack.client import camera_json
from quatrack.service.app import create_app
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

YAML = """%YAML:1.0
---
image_width: 640
image_height: 480
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 669.7, 0., 320., 0., 667.8, 240., 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ 0., 0., 0., 0., 0. ]
"""


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(Settings(store=example_store(), workers=1, threads=1, model_poll_s=0))) as c:
        yield c


def post(client, camera: str):
    img = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
    return client.post("/v1/objects/cookie-box/pose",
                       files={"image": ("f.jpg", img, "image/jpeg"), "camera": ("cam.yaml", camera.encode())})


def test_an_opencv_yaml_camera_field_is_told_the_field_is_json_and_how_to_convert(client, tmp_path):
    r = post(client, YAML)
    assert r.status_code == 422 and r.json()["error"]["code"] == "bad_camera", r.text
    msg = r.json()["error"]["message"]
    assert "not OpenCV YAML" in msg and "camera_json" in msg and "Invalid JSON" not in msg, msg
    (tmp_path / "cam.yaml").write_text(YAML)  # what the message says works
    assert post(client, json.dumps(camera_json(str(tmp_path / "cam.yaml")))).status_code == 200


def test_other_bad_json_keeps_its_message(client):
    msg = post(client, "{oops").json()["error"]["message"]
    assert "Invalid JSON" in msg and "YAML" not in msg, msg
    msg = post(client, json.dumps({"camera_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]})).json()["error"]["message"]
    assert "YAML" not in msg, msg

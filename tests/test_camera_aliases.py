"""Other programs' names for the camera's fields (OpenCV's ``dist``/``D``/``k1``…, ROS's
``K``/``D``, ``camera_matrix``) are refused with the contract's name wherever a camera is read
(camera files, REST ``camera``, the WebSocket's camera message): they were ignored, and with
them the lens's distortion (the pose 5 % off in depth without a word)."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from quatrack.service.schemas import CameraIn, CameraMessage
from quatrack.viewsets.camera import camera_from_dict, load_camera
from quatrack.viewsets.errors import SpecError

CAM = {"width": 640, "height": 480, "fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0}
DIST = [0.1, -0.05, 0.0, 0.0, 0.0]


@pytest.mark.parametrize("alias, value, meant", [
    ("dist", DIST, "'dist_coeffs'"), ("D", DIST, "'dist_coeffs'"), ("d", DIST, "'dist_coeffs'"),
    ("distortion", DIST, "'dist_coeffs'"), ("distortion_coefficients", DIST, "'dist_coeffs'"),
    ("k1", 0.1, "'dist_coeffs'"), ("p2", 0.0, "'dist_coeffs'"),
    ("K", [600, 0, 320, 0, 600, 240, 0, 0, 1], "'fx', 'fy', 'cx', 'cy'"),
    ("camera_matrix", [[600, 0, 320], [0, 600, 240], [0, 0, 1]], "'fx', 'fy', 'cx', 'cy'"),
    ("image_width", 640, "'width'")])
def test_an_alias_is_refused_naming_the_field_meant_everywhere(alias, value, meant, tmp_path):
    data = {**CAM, alias: value}
    if alias == "image_width":
        data.pop("width")
    if meant.startswith("'fx'"):
        data.pop("fx")
    expected = f"unknown field '{alias}' (did you mean {meant}?)"
    with pytest.raises(SpecError) as exc:
        camera_from_dict(data)
    assert str(exc.value) == f"camera: {expected}"
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(data))
    with pytest.raises(SpecError, match="^" + __import__("re").escape(f"{path}: {expected}") + "$"):
        load_camera(path)
    for model in (CameraIn, CameraMessage):  # (REST's camera, the WebSocket's camera message)
        with pytest.raises(ValidationError) as vexc:
            model.model_validate(data)
        assert CameraIn.error_message(vexc.value).endswith(expected), CameraIn.error_message(vexc.value)


def test_an_alias_beside_the_contract_field_is_a_note_and_ignored():
    """A file carrying both (``dist_coeffs`` and OpenCV's ``D``) keeps working: the contract's field is read."""
    cam = camera_from_dict({**CAM, "dist_coeffs": DIST, "D": [9, 9, 9, 9, 9], "K": [1] * 9})
    assert list(cam.dist_coeffs) == DIST

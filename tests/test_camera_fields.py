"""A misspelt camera field is refused with a suggestion wherever a camera is read (files, specs,
REST, WebSocket); other unknown fields are still ignored (a file may carry its own notes)."""

from __future__ import annotations

import json

import pytest

from quatrack.viewsets.camera import camera_from_dict, load_camera, misspelt_field
from quatrack.viewsets.errors import SpecError

CAM = {"width": 640, "height": 480, "fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0}


@pytest.mark.parametrize("typo, meant", [("dist_coeff", "dist_coeffs"), ("distcoeffs", "dist_coeffs"),
                                         ("fxx", "fx"), ("widht", "width"), ("Height", "height")])
def test_a_misspelt_field_is_named_with_the_field_meant(typo, meant, tmp_path):
    data = {**CAM, typo: [0.1, 0.0, 0.0, 0.0] if "dist" in typo else 600}
    data.pop(meant, None)
    with pytest.raises(SpecError, match=rf"unknown field '{typo}' \(did you mean '{meant}'\?\)"):
        camera_from_dict(data)
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(data))
    with pytest.raises(SpecError, match=rf"{path}: unknown field '{typo}'"):
        load_camera(path)


def test_other_fields_are_still_ignored():
    cam = camera_from_dict({**CAM, "model": "pinhole", "serial": "A12", "notes": "left camera"})
    assert cam.fx == 600.0
    assert misspelt_field({**CAM, "dist_coeffs": [0, 0, 0, 0], "dist_coeff": 1}) is None  # (the real one is there)

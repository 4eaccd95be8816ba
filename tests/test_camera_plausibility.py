"""Camera plausibility: one check (viewsets/camera.py) behind the CLI's files and the service's JSON."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from quatrack.cli import main
from quatrack.viewsets.camera import camera_from_dict, load_camera
from quatrack.viewsets.errors import SpecError

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cookie-box"
CAMERA = json.loads((EXAMPLE / "camera.json").read_text())


@pytest.mark.parametrize("change", [
    {}, {"fx": 14.0, "fy": 14.0}, {"fx": 600_000.0, "fy": 600_000.0}, {"cx": -300.0}, {"cy": 700.0},
    {"fx": 1200.0, "fy": 600.0},  # an anamorphic lens (2:1)
    {"width": 4000, "height": 3000, "fx": 3000.0, "fy": 3000.0, "cx": 2000.0, "cy": 1500.0},
])
def test_real_cameras_pass(change):
    cam = camera_from_dict({**CAMERA, **change})
    assert cam.fx == {**CAMERA, **change}["fx"]


@pytest.mark.parametrize("change, field", [
    ({"fx": 1e308}, "fx"), ({"fy": 1e308}, "fy"), ({"fx": 12.0}, "fx"), ({"fx": 700_000.0}, "fx"),
    ({"fx": True}, "fx"), ({"cx": 1e9}, "cx"), ({"cy": -250.0}, "cy"), ({"cx": float("nan")}, "cx"),
    ({"fx": 669.7, "fy": 60.0}, "fy"), ({"width": True}, "width"), ({"height": 10**6}, "height"),
    ({"fx": 6000.0, "fy": 669.7}, "fx/fy"),
])
def test_implausible_cameras_are_refused_naming_the_field(change, field):
    with pytest.raises(SpecError) as err:
        camera_from_dict({**CAMERA, **change}, "cam.json")
    msg = str(err.value)
    assert msg.startswith("cam.json:") and field in msg and "\n" not in msg, msg


def test_yaml_calibrations_are_checked_too(tmp_path):
    fs_path = tmp_path / "cam.yml"
    fs = cv2.FileStorage(str(fs_path), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[1e12, 0, 320], [0, 1e12, 240], [0, 0, 1]], float))
    fs.write("distortion_coefficients", np.zeros((1, 5)))
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    with pytest.raises(SpecError, match="fx"):
        load_camera(fs_path)


def test_cli_says_it_in_one_line(tmp_path, capsys):
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({**CAMERA, "fx": 1e308}))
    img = tmp_path / "x.png"
    cv2.imwrite(str(img), np.zeros((480, 640, 3), np.uint8))
    assert main(["locate", "--object", "cookie-box", "--camera", str(cam), "--store", str(tmp_path / "s"), str(img)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "fx" in err and "Traceback" not in err, err


@pytest.mark.parametrize("text, detail", [
    ("%YAML:1.0\ncamera_matrix: 5\n", "must be a 3×3 matrix"),  # valid YAML, wrong shape (cv2.error)
    ("hello world\n", "not a valid OpenCV YAML/XML camera file (line 1: Only collections"),  # not YAML (SystemError)
    ("%YAML:1.0\nfoo: [1,2\n", "not a valid OpenCV YAML/XML camera file (line "),  # unclosed
])
def test_malformed_yaml_calibrations_are_one_line_errors(tmp_path, text, detail):
    path = tmp_path / "cam.yml"
    path.write_text(text)
    with pytest.raises(SpecError) as err:
        load_camera(path)
    msg = str(err.value)
    assert msg.startswith(str(path)) and detail in msg and "\n" not in msg and "persistence" not in msg, msg


def test_deeply_nested_json_is_not_valid_json(tmp_path):
    path = tmp_path / "cam.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(SpecError, match="nested too deeply"):
        load_camera(path)


@pytest.mark.parametrize("change, message", [
    ({"dist_coeffs": [0.0, 0.0, 0.0]}, "4, 5 or 8"),  # (passed on to OpenCV, misread: the object "not found")
    ({"dist_coeffs": [0.1]}, "4, 5 or 8"),
    ({"dist_coeffs": [np.nan] * 5}, "finite"),
    ({"cx": np.inf}, "principal point"),
    ({"width": -640}, "width"),
    ({"fx": "600"}, "fx must be a number"),
])
def test_a_camera_built_in_python_is_checked_as_a_camera_file_is(change, message):
    from quatrack.tracking.camera import PinholeCamera

    kw = {"fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480, **change}
    with pytest.raises(ValueError, match=message):
        PinholeCamera(**kw)


def test_a_camera_dict_built_from_numpy_values_is_read():
    # numpy's numbers (K from cv2.calibrateCamera, a width from an array) were refused: an int64
    # width "must be a positive integer, got np.int64(640)", a float32 focal length "must be a
    # finite number", the (1, 5) distortion array "must be a list of numbers"
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    data = {"fx": np.float32(K[0, 0]), "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": np.int64(640),
            "height": np.int32(480), "dist_coeffs": np.array([[-0.1, 0.01, 0.0, 0.0, 0.0]])}
    cam = camera_from_dict(data)
    assert cam == camera_from_dict({**CAMERA, "fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0, "width": 640,
                                    "height": 480, "dist_coeffs": [-0.1, 0.01, 0.0, 0.0, 0.0]})
    with pytest.raises(SpecError, match="dist_coeffs"):
        camera_from_dict({**data, "dist_coeffs": np.zeros((2, 5))})
    with pytest.raises(SpecError, match="fx"):
        camera_from_dict({**data, "fx": np.bool_(True)})

"""`locate` with a camera file that states another image size than the image's (user report F1,
F2): images resized from the camera's are searched with its intrinsics scaled (the contract's
"Resized images"), but a camera whose principal point is the centre of the image as it is — the
intrinsics of this image under another resolution's width and height — is refused for that
image, on its own line, instead of being searched at half its focal length ("not found")."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import EXAMPLE, box_frames_jpeg
from quatrack.cli import main
from quatrack.testing.scenes import example_store


@pytest.fixture(scope="module")
def store():
    return example_store()


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    root = tmp_path_factory.mktemp("frame")
    img = cv2.imdecode(np.frombuffer(box_frames_jpeg(1)[0], np.uint8), cv2.IMREAD_COLOR)
    cv2.imwrite(str(root / "f0.png"), img)
    return root / "f0.png"


def test_a_camera_stating_a_wrong_size_is_refused_not_scaled(store, frame, tmp_path, capsys):
    cam = json.loads((EXAMPLE / "camera.json").read_text()) | {"width": 1280, "height": 960}  # (the 640×480 numbers)
    path = tmp_path / "cam_big.json"
    path.write_text(json.dumps(cam))
    args = ["locate", "--object", "cookie-box", "--camera", str(path), "--store", str(store), str(frame)]
    assert main(args) == 1
    out, err = capsys.readouterr()
    assert "cam_big.json" in err and "states 1280×960 px images" in err and "width and height wrong" in err
    assert "scaled by" not in err and "not found" not in out
    assert main([*args, "--json"]) == 1
    line = json.loads(capsys.readouterr().out)
    assert line["found"] is False and "width and height wrong" in line["error"]


def test_a_resized_image_is_still_scaled_said_without_a_video(store, frame, tmp_path, capsys):
    big = tmp_path / "big.png"
    cv2.imwrite(str(big), cv2.resize(cv2.imread(str(frame)), (1280, 960), interpolation=cv2.INTER_LINEAR))
    assert main(["locate", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"), "--store", str(store),
                 str(big)]) == 0
    out, err = capsys.readouterr()
    assert ": found" in out and "its intrinsics scaled by 2 (resized images)" in err and "video" not in err


def test_exit_statuses(store, frame, tmp_path, capsys):
    """Per image (unreadable, missing, another aspect ratio than the camera): a line each, the
    others still searched, exit 1 (the contract's); a bad camera file: exit 2 before any image."""
    cam = json.loads((EXAMPLE / "camera.json").read_text()) | {"height": 360}
    other = tmp_path / "cam_wide.json"
    other.write_text(json.dumps(cam))
    (tmp_path / "not.png").write_bytes(b"not an image")
    base = ["locate", "--object", "cookie-box", "--store", str(store)]
    assert main([*base, "--camera", str(EXAMPLE / "camera.json"), str(tmp_path / "not.png"),
                 str(tmp_path / "missing.png"), str(frame)]) == 1
    out, err = capsys.readouterr()
    assert ": found" in out and err.count(": error: ") == 2
    assert main([*base, "--camera", str(other), str(frame)]) == 1
    assert "640×360" in capsys.readouterr().err
    assert main([*base, "--camera", str(tmp_path / "not.png"), str(frame)]) == 2

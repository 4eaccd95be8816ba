"""A camera calibrated at full size used with its images resized (a shared, downscaled video):
`track` and `locate` scale its intrinsics, say so once, and give the full-size answer (÷ nothing:
poses are in the mesh's units); another aspect ratio is refused as before."""

from __future__ import annotations

import csv

import cv2
import numpy as np
import pytest

from conftest import EXAMPLE, box_frames_jpeg
from quatrack.cli import main
from quatrack.testing.scenes import example_store


@pytest.fixture(scope="module")
def base_store():
    """The example trained with the default options (its 0.6× views find the box at 3/4 size)."""
    return example_store()


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """The first 6 frames of box.mp4 at full size, halved (320 × 240) and squeezed to 640 × 360, as PNG files."""
    root = tmp_path_factory.mktemp("frames")
    for k, data in enumerate(box_frames_jpeg(6)):
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        (root / "full").mkdir(exist_ok=True)
        (root / "half").mkdir(exist_ok=True)
        (root / "wide").mkdir(exist_ok=True)
        cv2.imwrite(str(root / "full" / f"f{k}.png"), img)
        cv2.imwrite(str(root / "half" / f"f{k}.png"), cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA))
        cv2.imwrite(str(root / "wide" / f"f{k}.png"), cv2.resize(img, (640, 360), interpolation=cv2.INTER_AREA))
    return root


def _rows(path):
    return list(csv.DictReader(open(path)))


def test_track_scales_the_camera_to_resized_frames(base_store, frames, tmp_path, capsys):
    camera = str(EXAMPLE / "camera.json")
    for size in ("full", "half"):
        assert main(["track", "--object", "cookie-box", "--camera", camera, "--images", str(frames / size / "f*.png"),
                     "--out", str(tmp_path / f"{size}.csv"), "--store", str(base_store), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert err.count("the camera is for 640×480 px images and these are 320×240 px: its intrinsics scaled by 0.5") == 1
    full, half = _rows(tmp_path / "full.csv"), _rows(tmp_path / "half.csv")
    assert all(r["status"] != "lost" for r in half)
    t_full = np.array([[float(r[k]) for k in ("tx", "ty", "tz")] for r in full])
    t_half = np.array([[float(r[k]) for k in ("tx", "ty", "tz")] for r in half])
    assert np.median(np.linalg.norm(t_full - t_half, axis=1)) < 1.0  # cm: the same box, fewer pixels


def test_locate_scales_it_and_says_so_once(base_store, frames, capsys):
    camera = str(EXAMPLE / "camera.json")
    paths = [str(frames / "half" / f"f{k}.png") for k in range(3)]
    assert main(["locate", "--object", "cookie-box", "--camera", camera, "--store", str(base_store), *paths]) == 0
    out, err = capsys.readouterr()
    assert out.count(": found") == 3 and err.count("its intrinsics scaled by 0.5") == 1


def test_another_aspect_ratio_is_still_refused(base_store, frames, tmp_path, capsys):
    camera = str(EXAMPLE / "camera.json")
    assert main(["track", "--object", "cookie-box", "--camera", camera, "--images", str(frames / "wide" / "f*.png"),
                 "--out", str(tmp_path / "w.csv"), "--store", str(base_store), "--quiet"]) == 2
    assert "the camera is for 640×480 px images but the frame is 640×360 px" in capsys.readouterr().err

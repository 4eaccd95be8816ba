"""The speed measures of ``locate`` (issue 13) keep the geometry: SIFT on a shrunk crop reports
keypoints in the full image's pixels, and the shrink factor follows the window's size."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from quatrack.recognition.locate import sift_scale
from quatrack.recognition.match import ModelIndex
from quatrack.viewsets.viewset import ViewsetParams


def _blobs(rng):
    """A 480×640 image of dark discs (radius 7 px), centres (x, y) on a jittered grid 80 px apart."""
    img = np.full((480, 640, 3), 230, np.uint8)
    gx, gy = np.meshgrid(np.arange(140, 520, 80), np.arange(120, 380, 80))
    centres = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-10, 10, (gx.size, 2))
    for x, y in centres:
        cv2.circle(img, (int(round(x * 16)), int(round(y * 16))), 7 * 16, (30, 30, 30), -1, cv2.LINE_AA, shift=4)
    return cv2.GaussianBlur(img, (0, 0), 1.0), centres


@pytest.mark.parametrize("scale", [1.0, 0.5, 0.35])
def test_shrunk_crop_keypoints_land_on_the_blobs(scale):
    img, centres = _blobs(np.random.default_rng(7))
    index = SimpleNamespace(viewset_params=ViewsetParams())  # describe() needs only the SIFT parameters
    box = (90, 70, 560, 410)  # x0, y0, x1, y1: an off-origin crop, so the offset matters too
    f = ModelIndex.describe(index, img, box, scale=scale)
    big = f.sizes > 8.0  # blob-sized keypoints (the disc's edges give small ones too)
    assert big.sum() >= 10
    d = np.linalg.norm(f.keypoints[big, None, :] - centres[None], axis=2).min(axis=1)
    # at the blob centres, in the full image's pixels, to within a pixel of the shrunk crop
    assert np.median(d) < 0.6 / scale and np.mean(d < 1.5 / scale) >= 0.9
    assert f.keypoints[:, 0].min() >= box[0] - 1 and f.keypoints[:, 0].max() <= box[2]
    # SIFT's scale is reported in full-image pixels too: a disc of radius 7 px whatever the shrink
    assert 8.0 < np.median(f.sizes[big]) < 12.0  # 9.6 at full resolution


def test_sift_scale_follows_the_window():
    assert sift_scale((0, 0, 400, 300), 200.0) == pytest.approx(0.5)
    assert sift_scale((5, 5, 300, 600), 200.0) == pytest.approx(1 / 3)  # the longer side counts
    assert sift_scale((0, 0, 120, 180), 200.0) == 1.0  # never enlarged
    assert sift_scale((0, 0, 4000, 3000), None) == 1.0

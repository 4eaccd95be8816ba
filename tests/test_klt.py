"""recognition/klt.py: the forward–backward check at fewer pyramid levels than the forward pass."""

from __future__ import annotations

import cv2
import numpy as np

from quatrack.recognition.klt import KLTParams, make_frame, track_points
from quatrack.testing.sequences import clutter_background


def _pair(shift, seed=1):
    img = cv2.cvtColor(clutter_background(seed), cv2.COLOR_BGR2GRAY)
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    moved = cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    pts = cv2.goodFeaturesToTrack(img, 200, 0.01, 8).reshape(-1, 2).astype(float)
    pts = pts[(pts[:, 0] > 40) & (pts[:, 0] < img.shape[1] - 40) & (pts[:, 1] > 40) & (pts[:, 1] < img.shape[0] - 40)]
    return img, moved, pts


def test_a_single_level_backward_pass_keeps_the_forward_tracks_and_their_verdicts():
    """The backward pass starts where each point came from: on a correct forward track it has
    nothing to search, so level 0 alone accepts what the full pyramid accepts; the forward
    tracks are the same (the forward pass is unchanged)."""
    shift = np.array([9.4, -7.2])  # beyond a 21-px window without the pyramid
    img, moved, pts = _pair(shift)
    a, b = make_frame(img), make_frame(moved)
    full = track_points(a, b, pts, params=KLTParams(fb_levels=None))
    one = track_points(a, b, pts, params=KLTParams(fb_levels=0))
    np.testing.assert_array_equal(full[0], one[0])
    assert full[1].mean() > 0.9 and np.mean(full[1] == one[1]) > 0.97
    err = np.linalg.norm(one[0][one[1]] - (pts[one[1]] + shift), axis=1)
    assert np.median(err) < 0.1 and np.percentile(err, 90) < 0.3


def test_a_single_level_backward_pass_still_refuses_tracks_into_another_image():
    img, _, pts = _pair(np.zeros(2))
    other = cv2.cvtColor(clutter_background(7), cv2.COLOR_BGR2GRAY)
    for p in (KLTParams(fb_levels=None), KLTParams(fb_levels=0)):
        _, ok, _ = track_points(make_frame(img), make_frame(other), pts, params=p)
        assert ok.mean() < 0.3, p

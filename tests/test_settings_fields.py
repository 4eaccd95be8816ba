"""Recognition's settings objects refuse a field of the wrong kind at construction, naming it
(recognition/fields.py), as TrackerParams does."""

from __future__ import annotations

import numpy as np
import pytest

from quatrack.recognition.locate import LocateParams
from quatrack.recognition.pose import PoseParams
from quatrack.recognition.video import TrackerParams
from quatrack.recognition.window_search import WindowSearchParams


@pytest.mark.parametrize("make, message", [
    (lambda: PoseParams(ransac_px="6"), "ransac_px must be a finite number"),
    (lambda: PoseParams(ransac_iterations=2.5), "ransac_iterations must be a whole number"),
    (lambda: PoseParams(min_edge_agreement=float("nan")), "min_edge_agreement must be a finite number"),
    (lambda: WindowSearchParams(cell=-8), "cell must be a whole number >= 0"),
    (lambda: WindowSearchParams(aspects=("wide",)), "aspects must be a tuple of numbers"),
    (lambda: LocateParams(margin=None), "margin must be a finite number"),
    (lambda: TrackerParams(min_points="5"), "min_points must be a whole number"),
])
def test_a_field_of_the_wrong_kind_is_named(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_nested_settings_must_be_settings_objects():
    with pytest.raises(TypeError, match="pose: a PoseParams, got dict"):
        LocateParams(pose={"ransac_px": 4.0})
    with pytest.raises(TypeError, match="window: a WindowSearchParams"):
        LocateParams(window=None)


def test_whole_floats_and_numpy_numbers_are_taken_as_python_numbers():
    p = PoseParams(ransac_iterations=np.int64(200), ransac_px=np.float32(5.0))
    assert type(p.ransac_iterations) is int and p.ransac_iterations == 200
    assert WindowSearchParams(cell=8.0).cell == 8 and type(WindowSearchParams(cell=8.0).cell) is int
    assert PoseParams() == PoseParams() and LocateParams().pose == PoseParams()  # (defaults unchanged)


@pytest.mark.parametrize("kwargs, message", [
    ({"learn": "yes"}, "learn must be True or False"),
    ({"max_gap_s": 0}, "max_gap_s must be None or a number of seconds above 0"),
    ({"max_gap_s": -1.0}, "max_gap_s must be None or a number of seconds above 0"),
    ({"sources": ()}, "sources: none given"),
])
def test_tracker_params_a_library_user_got_wrong(kwargs, message):
    """(The library trial: learn="yes" was taken as true, max_gap_s=0 ended the track at every
    frame, sources=() said "unknown measurement source(s) []".)"""
    with pytest.raises(ValueError, match=message):
        TrackerParams(**kwargs)
    assert TrackerParams(learn=np.bool_(True)).learn is True and TrackerParams(max_gap_s=None).max_gap_s is None


def test_pose_from_matrix_takes_a_4x4_and_a_size_mismatch_says_how_to_scale():
    from quatrack.recognition.images import ImageError, prepare_image
    from quatrack.tracking.camera import PinholeCamera
    from quatrack.tracking.pose import Pose

    p = Pose([0.5, 0.5, 0.5, 0.5], [1.0, 2.0, 3.0])
    assert Pose.from_matrix(p.as_matrix()) == p  # (as_matrix's own output was "missing 't'")
    with pytest.raises(TypeError, match="give t with a 3×3 R"):
        Pose.from_matrix(np.eye(3))
    cam = PinholeCamera(600.0, 600.0, 319.5, 239.5, width=640, height=480)
    with pytest.raises(ImageError, match=r"resized by 2\? pass camera.scaled\(2, 1280, 960\)"):
        prepare_image(np.zeros((960, 1280, 3), np.uint8), cam)
    with pytest.raises(ImageError, match=r"the image is 640×360 px$"):  # (another aspect ratio: no hint)
        prepare_image(np.zeros((360, 640, 3), np.uint8), cam)

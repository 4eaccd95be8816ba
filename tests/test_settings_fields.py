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

"""``Tracker.init_pose(t, q, time_s=…)`` sets a time the next frames may not go back before, as
the track's latest frame does: a frame at 3 s after a pose given at 5 s was started from that
pose all the same (put at 3 s), where every other step back in time is refused."""

from __future__ import annotations

import numpy as np
import pytest

from quatrack.recognition.video import Tracker
from quatrack.testing.scenes import EXAMPLE, example_model
from quatrack.viewsets.camera import load_camera

BEHIND = ([0.0, 0.0, -1.0], [1.0, 0.0, 0.0, 0.0])  # refused when used: a reason without any vision run


@pytest.fixture(scope="module")
def tracker_and_frame():
    camera = load_camera(EXAMPLE / "camera.json")
    return Tracker(example_model(), camera), np.full((camera.height, camera.width, 3), 128, np.uint8)


def test_a_frame_before_the_given_pose_s_time_is_refused_and_the_pose_kept(tracker_and_frame):
    tracker, blank = tracker_and_frame
    tracker.init_pose(*BEHIND, time_s=5.0)
    with pytest.raises(ValueError, match=r"time goes backwards \(3\.0 s before the pose given at 5\.0 s by init_pose"):
        tracker.step(blank, 3.0)
    with pytest.raises(ValueError, match="time goes backwards"):
        tracker.skip(4.0, "unreadable")
    step = tracker.step(blank, 5.0)  # (the pose was not used up by the refused frame)
    assert step.status == "lost" and step.reason.startswith("given pose refused"), step.reason


def test_a_pose_given_without_a_time_takes_the_next_frame_s(tracker_and_frame):
    tracker, blank = tracker_and_frame
    tracker.step(blank, 10.0)
    tracker.init_pose(*BEHIND)  # (a new start: the clock may start again, as after reset)
    step = tracker.step(blank, 1.0)
    assert step.status == "lost" and step.reason.startswith("given pose refused"), step.reason

"""Recognition while lost, at most once per ``TrackerParams.relocate_interval_s`` of frame time.

A failed recognition costs a hundred milliseconds or more, so a stream whose object has left the
view holds its worker's core; with the interval set, the frames between two searches are answered
``lost`` at once. The first frame of a new loss searches without waiting: the interval counts
from the latest search of the *same* loss."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from quatrack.recognition.tracker import machine
from quatrack.recognition.video import Tracker, TrackerParams
from quatrack.testing.scenes import EXAMPLE, example_model
from quatrack.viewsets.camera import load_camera

INTERVAL = 0.25
_LOCATE = machine.locate  # (wrapped afresh by each run, never a wrapper of a wrapper)
DT = 0.0625  # frame times k/16: exact in binary, so "at least 0.25 s later" is never a rounding question


def _frames():
    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    box = [cap.read()[1] for _ in range(5)]
    cap.release()
    blank = np.full_like(box[0], 128)
    # nothing; the box (found after the interval, then tracked); nothing again, the second loss
    # starting less than the interval after the search that found the box
    return [blank] + box + [blank] * 8


def _run(monkeypatch, params):
    searched = []

    def counted(*args, **kwargs):
        searched[-1] = True
        return _LOCATE(*args, **kwargs)

    monkeypatch.setattr(machine, "locate", counted)
    tracker = Tracker(example_model(), load_camera(EXAMPLE / "camera.json"), params)
    steps = []
    for k, f in enumerate(_frames()):
        searched.append(False)
        steps.append(tracker.step(f, k * DT))
    return steps, searched


def test_lost_frames_search_at_most_once_per_interval(monkeypatch):
    steps, searched = _run(monkeypatch, replace(TrackerParams(), relocate_interval_s=INTERVAL))
    statuses = [s.status for s in steps]
    assert "tracking" in statuses, statuses  # (the box was found and tracked between the two losses)
    skipped = [k for k, s in enumerate(steps) if s.reason and "relocate_interval_s" in s.reason]
    assert skipped and all(statuses[k] == "lost" and not searched[k] for k in skipped)
    times = [k * DT for k, s in enumerate(searched) if s]
    runs = [k for k, s in enumerate(searched) if s]
    for a, b in zip(runs, runs[1:]):
        if "tracking" not in statuses[a + 1:b]:  # (within one loss)
            assert (b - a) * DT >= INTERVAL, (times, statuses)
    # the first frame of the second loss that reaches recognition searches at once
    last_tracked = max(k for k, s in enumerate(statuses) if s == "tracking")
    first = min(k for k in runs if k > last_tracked)
    assert not any(k in skipped for k in range(last_tracked + 1, first)), (first, skipped)


def test_every_lost_frame_searches_by_default(monkeypatch):
    assert TrackerParams().relocate_interval_s is None
    steps, searched = _run(monkeypatch, TrackerParams())
    _, throttled = _run(monkeypatch, replace(TrackerParams(), relocate_interval_s=INTERVAL))
    assert not any(s.reason and "relocate_interval_s" in s.reason for s in steps)
    assert sum(searched) > sum(throttled)


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf")])
def test_a_negative_or_non_finite_interval_is_refused(bad):
    with pytest.raises(ValueError, match="relocate_interval_s"):
        TrackerParams(relocate_interval_s=bad)


def test_reset_restarts_the_interval_and_time_may_not_go_back_while_lost(monkeypatch):
    searched = []

    def counted(*args, **kwargs):
        searched.append(True)
        return _LOCATE(*args, **kwargs)

    monkeypatch.setattr(machine, "locate", counted)
    blank = _frames()[0]
    tracker = Tracker(example_model(), load_camera(EXAMPLE / "camera.json"),
                      replace(TrackerParams(), relocate_interval_s=INTERVAL))
    assert tracker.step(blank, 100.0).status == "lost" and len(searched) == 1
    with pytest.raises(ValueError, match="time goes backwards"):  # (lost: no state, a clock all the same)
        tracker.step(blank, 99.0)
    tracker.reset()  # a new stream: its clock starts again, and the next frame searches at once
    step = tracker.step(blank, 0.0)
    assert len(searched) == 2 and "relocate_interval_s" not in (step.reason or ""), step.reason


def test_init_pose_checks_what_it_is_given():
    from quatrack.tracking.pose import Pose

    tracker = Tracker(example_model(), load_camera(EXAMPLE / "camera.json"))
    with pytest.raises(ValueError, match="time_s must be finite"):
        tracker.init_pose([0.0, 0.0, 60.0], [1.0, 0.0, 0.0, 0.0], time_s=float("nan"))
    with pytest.raises(ValueError, match="q_wxyz must be 4 numbers, got shape"):
        tracker.init_pose([0.0, 0.0, 60.0], [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="t must be 3 numbers"):
        tracker.init_pose([0.0, 60.0], [1.0, 0.0, 0.0, 0.0])
    tracker.init_pose(Pose([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 60.0]))  # the one pose type, as such
    assert tracker._pending[0].t.tolist() == [0.0, 0.0, 60.0]

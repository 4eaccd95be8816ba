"""Geometrically extreme but legitimate inputs to the tracker: nothing crashes, nothing wrong
is reported as tracked, and a refusal says why.

- frames smaller than recognition takes (1 × N) are refused by ``Tracker.step`` whatever the
  tracker's state (they went through KLT and the sources after ``init_pose``);
- a given pose with the object at or behind the camera (``t = 0``, a mirrored ``t``) is refused
  naming that, and the next frame is searched by recognition;
- a clock jumping by hours ends the track, and that frame is searched afresh (the velocities
  were extrapolated over the gap: the prediction left the object metres away, behind the camera).

One small cube (centimetres) trained from one rendered photo at 320 × 240, no synthetic views.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from quatrack.recognition.images import ImageError
from quatrack.recognition.match import index_for
from quatrack.recognition.video import Tracker, TrackerParams
from quatrack.testing import scenes as S
from quatrack.testing import zoo as Z
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.train import TrainParams, train_object

CAM = Z.zoo_camera(320, 240)
NAME = "small-cube-cm"


def _background(seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320, 3)).astype(np.float32), (0, 0), 2.0)
    return cv2.normalize(img, None, 40, 210, cv2.NORM_MINMAX).astype(np.uint8)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    cv2.setRNGSeed(0)
    path = Z.write_spec(NAME, tmp_path_factory.mktemp("cube"), 1, camera=CAM, backgrounds=(_background(),))
    spec = load_spec(path)
    model = train_object(spec, TrainParams(novel=None))
    return model, index_for(model), spec.views[0].pose


def _moved(pose: Pose, k: int, speed: float = 0.004) -> Pose:
    """``pose`` slid sideways by ``speed`` × its depth per frame and turned 0.5° per frame."""
    obj = Z.textured(NAME)
    c = pose.R @ obj.mesh.centre + pose.t
    R = cv2.Rodrigues(np.array([0.0, np.radians(0.5) * k, 0.0]))[0] @ pose.R
    return Pose.from_matrix(R, c + np.array([speed * k * c[2], 0.0, 0.0]) - R @ obj.mesh.centre)


def _frame(pose: Pose, seed: int) -> np.ndarray:
    img, sil = Z.textured(NAME).render(CAM, pose)
    return Z.degrade(Z.compose(img, sil, _background()), np.random.default_rng(seed))


def _close(step, truth: Pose, mesh) -> bool:
    dt, dr = S.pose_errors(step.t, step.q_wxyz, truth, mesh)
    return dt <= 0.05 * mesh.extent and dr <= 5.0


def test_frames_too_small_to_search_are_refused_after_a_given_pose_too(trained):
    model, index, pose = trained
    for w, h in ((320, 1), (1, 240), (320, 16)):
        cam = PinholeCamera(CAM.fx, CAM.fy, (w - 1) / 2, (h - 1) / 2, np.zeros(5), width=w, height=h)
        tracker = Tracker(model, cam, index=index)
        tracker.init_pose(pose)
        with pytest.raises(ImageError, match=rf"the image is too small \({w}×{h} px; at least 32 px a side\)"):
            tracker.step(np.full((h, w, 3), 128, np.uint8), 0.0)
        # as recognition refused it (no given pose): the same error
        with pytest.raises(ImageError, match="too small"):
            Tracker(model, cam, index=index).step(np.full((h, w), 128, np.uint8), 0.0)


@pytest.mark.parametrize("given", ["t=0", "mirrored", "straddling"])
def test_a_given_pose_at_or_behind_the_camera_is_refused_saying_so(trained, given):
    model, index, pose = trained
    centre = pose.R @ model.mesh.centre + pose.t
    bad = {"t=0": Pose(pose.q_wxyz, np.zeros(3)),
           "mirrored": Pose(pose.q_wxyz, pose.t * np.array([1.0, 1.0, -1.0])),
           "straddling": Pose(pose.q_wxyz, pose.t - centre)}[given]  # the object's centre at the camera's
    assert bad.apply(model.mesh.vertices)[:, 2].min() <= 0
    tracker = Tracker(model, CAM, index=index)
    tracker.init_pose(bad)
    first = tracker.step(_frame(pose, 0), 0.0)
    assert first.status == "lost" and first.pose is None
    assert first.reason.startswith("given pose refused: the object would be (partly) behind the camera"), first.reason
    second = tracker.step(_frame(pose, 1), 1 / 30)  # recognition takes over
    assert second.status == "init" and second.reason == "recognition" and _close(second, pose, model.mesh)


def test_a_clock_jumping_by_hours_restarts_the_track_by_recognition(trained):
    model, index, pose = trained
    tracker = Tracker(model, CAM, TrackerParams(motion_model="ude"), index=index)
    steps = [tracker.step(_frame(_moved(pose, k), k), k / 30) for k in range(6)]
    assert [s.status for s in steps] == ["init"] + ["tracking"] * 5
    # the object stopped where it was; the clock jumped by three hours (a paused stream, a
    # timestamp glitch): the frame is a new start, found where the object is
    truth = _moved(pose, 5)
    after = tracker.step(_frame(truth, 6), 3 * 3600.0)
    assert after.status == "init" and after.reason == "recognition" and _close(after, truth, model.mesh)
    nxt = tracker.step(_frame(truth, 7), 3 * 3600.0 + 1 / 30)
    assert nxt.status == "tracking" and _close(nxt, truth, model.mesh)
    # a jump to where the object is gone: lost, saying the track was dropped for the gap
    gone = tracker.step(_background(5), 6 * 3600.0)
    assert gone.status == "lost" and gone.reason.startswith("the track was dropped after 1.08e+04 s without a frame")


def test_max_gap_s_none_predicts_across_any_gap(trained):
    model, index, pose = trained
    tracker = Tracker(model, CAM, TrackerParams(motion_model="ude", max_gap_s=None), index=index)
    for k in range(3):
        tracker.step(_frame(pose, k), k / 30)
    assert tracker.step(_frame(pose, 3), 5.0).status != "init"


def test_a_time_lapse_gap_under_a_minute_keeps_the_track(trained):
    # the default max_gap_s is a minute: a slow camera or a time-lapse (a frame every 30 s of a
    # still object) is tracked on, not restarted by recognition at every frame
    model, index, pose = trained
    tracker = Tracker(model, CAM, TrackerParams(motion_model="ude"), index=index)
    assert TrackerParams().max_gap_s == 60.0
    steps = [tracker.step(_frame(pose, k), 30.0 * k) for k in range(4)]
    assert [s.status for s in steps] == ["init"] + ["tracking"] * 3, [s.reason for s in steps]

"""A given pose the tracker refuses (``init_pose``, ``--init-pose``) leaves its frame to
recognition at once: the frame was answered ``lost`` and recognition started only at the next
one, though it finds the object in that frame on its own (user report: a pose given camera →
object cost frame 0 of box.mp4)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from quatrack.cli import main
from quatrack.recognition.tracker.machine import GIVEN_REFUSED, THEN
from quatrack.recognition.video import Tracker
from quatrack.testing.scenes import EXAMPLE, example_model, example_store
from quatrack.viewsets.camera import load_camera

BEHIND = ([0.0, 0.0, -1.0], [1.0, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def box_frames():
    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    frames = [cap.read()[1] for _ in range(2)]
    cap.release()
    return frames


def test_recognition_tries_the_frame_whose_given_pose_is_refused(box_frames):
    camera = load_camera(EXAMPLE / "camera.json")
    tracker = Tracker(example_model(), camera)
    tracker.init_pose(*BEHIND)
    first = tracker.step(box_frames[0], 0.0)
    assert first.frame == 0 and first.status == "init" and first.pose is not None, first.reason
    assert first.reason == (f"{GIVEN_REFUSED}the object would be (partly) behind the camera (its nearest vertex "
                            f"at z = -1 mesh units){THEN}recognition"), first.reason
    assert tracker.step(box_frames[1], 1 / 30).status == "tracking"


def test_a_refused_init_pose_leaves_frame_0_to_recognition_and_says_so(box_frames, tmp_path, capsys):
    """The inverse pose (camera → object): row 0 is an init found by recognition, and the warning
    says recognition found the object in that frame."""
    from quatrack.tracking.pose import Pose

    camera = load_camera(EXAMPLE / "camera.json")
    right = Tracker(example_model(), camera).step(box_frames[0], 0.0)
    assert right.status == "init"
    R, t = Pose(right.q_wxyz, right.t).R, right.t
    pose_file = tmp_path / "inverse.json"
    pose_file.write_text(json.dumps({"R": R.T.tolist(), "t": (-R.T @ t).tolist()}))
    out = tmp_path / "poses.jsonl"
    assert main(["track", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"),
                 "--store", str(example_store()), "--video", str(EXAMPLE / "box.mp4"), "--max-frames", "2",
                 "--init-pose", str(pose_file), "--format", "jsonl", "--out", str(out), "--quiet"]) == 0
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["status"] for r in rows] == ["init", "tracking"]
    assert rows[0]["reason"].startswith(GIVEN_REFUSED) and rows[0]["reason"].endswith(f"{THEN}recognition")
    assert np.allclose(rows[0]["pose"]["t"], right.t, atol=0.5)
    err = [x for x in capsys.readouterr().err.splitlines() if "--init-pose" in x]
    assert len(err) == 1 and "the pose was refused at frame 0 (" in err[0], err
    assert err[0].endswith("; recognition found it in that same frame") and THEN not in err[0], err

"""A refused ``track --init-pose`` names both causes (trial report, item 4).

The warning asked "(is the pose object → camera, in the mesh's units?)" of a pose that was merely
off — a trial's pose 10° from the frame's on a side no photo shows — sending the user after a
convention error they had not made. It now names both: too far from where the frame shows the
object (with how close it must be), or another convention.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import test_cli_reports
from quatrack.tracking.pose import Pose
from test_cli_reports import _track


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """test_cli_reports' frames: three rendered frames of the box and their true poses."""
    return test_cli_reports.frames.__wrapped__(tmp_path_factory)


def _turned(pose: Pose, centre: np.ndarray, deg: float) -> Pose:
    """``pose`` with the object turned ``deg`` about its centre's vertical axis (object frame)."""
    R = cv2.Rodrigues(np.array([0.0, np.radians(deg), 0.0]))[0]
    return Pose.from_matrix(pose.R @ R, pose.R @ (centre - R @ centre) + pose.t)


def _warning(store, frames, tmp_path, capsys, pose: Pose) -> str:
    root, _ = frames
    pose_file = tmp_path / "pose.json"
    pose_file.write_text(json.dumps({"R": pose.R.tolist(), "t": pose.t.tolist()}))
    capsys.readouterr()
    assert _track(store, root, pose_file, tmp_path / "poses.csv") == 0
    lines = [x for x in capsys.readouterr().err.splitlines() if "--init-pose" in x]
    assert len(lines) == 1, lines
    return lines[0]


def _both_causes(line: str) -> None:
    assert "recognition instead (either the pose is too far from where the frame shows the object (it must be within about 5° and " \
           "a few % of the object's size, on a side no photo shows)" in line, line
    assert "or it is in another convention (camera → object instead of object → camera, or not in the mesh's " \
           "units))" in line, line


def test_a_pose_far_off_is_told_it_may_be_too_far(base_store, frames, tmp_path, capsys):
    from quatrack.viewsets.store import load_model

    centre = load_model(base_store, "cookie-box").mesh.centre
    _both_causes(_warning(base_store, frames, tmp_path, capsys, _turned(frames[1][0], centre, 40.0)))


def test_a_pose_given_camera_to_object_names_the_convention_too(base_store, frames, tmp_path, capsys):
    p = frames[1][0]
    _both_causes(_warning(base_store, frames, tmp_path, capsys, Pose.from_matrix(p.R.T, -p.R.T @ p.t)))

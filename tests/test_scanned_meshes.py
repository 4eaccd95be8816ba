"""Meshes of many faces (scans, fine CAD exports): trained on in full, run on their decimation.

A scanned object's mesh has 10⁴–10⁶ triangles where a CAD box has 12. Training lifts keypoints
onto the full mesh (ray casting through a grid: viewsets/render.py); recognition and tracking,
whose geometry costs in proportion to the faces every frame, work on its quadric decimation
(``Mesh.run_time``). A finely subdivided cookie box must then give the plain box's poses.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from quatrack.recognition.locate import locate
from quatrack.recognition.match import index_for
from quatrack.recognition.video import Tracker, TrackerParams
from quatrack.tracking import quaternion as quat
from quatrack.viewsets.camera import load_camera
from quatrack.testing.scans import scanned
from quatrack.viewsets.mesh import RUN_TIME_MAX_FACES, load_mesh
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.train import train_object

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cookie-box"


def test_a_mesh_of_many_faces_runs_on_a_decimation_that_keeps_its_shape():
    plain = load_mesh(EXAMPLE / "box.ply")
    fine = scanned(plain, 5)
    assert len(fine.faces) > RUN_TIME_MAX_FACES and plain.run_time is plain
    run = fine.run_time
    assert run is fine.run_time  # (computed once per mesh)
    assert len(run.faces) <= RUN_TIME_MAX_FACES
    # every vertex of the decimation lies on the box's surface: on one of its six planes, inside it
    lo, hi = plain.vertices.min(axis=0), plain.vertices.max(axis=0)
    tol = 1e-4 * plain.extent
    on_a_face = np.any((np.abs(run.vertices - lo) < tol) | (np.abs(run.vertices - hi) < tol), axis=1)
    assert on_a_face.all() and np.all(run.vertices >= lo - tol) and np.all(run.vertices <= hi + tol)
    assert abs(run.extent - plain.extent) < tol and np.allclose(run.centre, plain.centre, atol=tol)
    assert run.closed_outward


@pytest.fixture(scope="module")
def two_boxes(tmp_path_factory):
    """The cookie box trained from its photo on its own mesh and on the same box subdivided into
    12 288 triangles."""
    d = tmp_path_factory.mktemp("fine")
    spec = json.loads((EXAMPLE / "object.json").read_text())
    for v in spec["views"]:
        v["image"] = str(EXAMPLE / v["image"])
    fine = scanned(load_mesh(EXAMPLE / "box.ply"), 5)
    import trimesh

    trimesh.Trimesh(fine.vertices, fine.faces, process=False).export(d / "fine.ply")
    spec.update(name="fine-box", mesh="fine.ply")
    (d / "fine.json").write_text(json.dumps(spec))
    return train_object(load_spec(EXAMPLE / "object.json")), train_object(load_spec(d / "fine.json"))


def test_a_finely_meshed_box_is_found_and_tracked_as_the_plain_one(two_boxes):
    camera = load_camera(EXAMPLE / "camera.json")
    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    frames = [cap.read()[1] for _ in range(12)]
    poses = {}
    for model in two_boxes:
        found = locate(frames[0], camera, model, index=index_for(model))
        assert found.found
        tracker = Tracker(model, camera, TrackerParams(), index=index_for(model))
        assert len(tracker.model.mesh.faces) <= RUN_TIME_MAX_FACES  # (the fine box: its decimation)
        steps = [tracker.step(f, k / 30.0) for k, f in enumerate(frames)]
        assert all(s.has_pose for s in steps), [(s.status, s.reason) for s in steps]
        poses[model.name] = [(found.t, found.q_wxyz)] + [(s.t, s.q_wxyz) for s in steps]
    dt = [np.linalg.norm(np.asarray(ta) - np.asarray(tb)) for (ta, _), (tb, _) in zip(poses["cookie-box"], poses["fine-box"])]
    dr = [np.degrees(quat.angle_between(np.asarray(qa), np.asarray(qb)))
          for (_, qa), (_, qb) in zip(poses["cookie-box"], poses["fine-box"])]
    # (the same poses as long as the same measurements come in; a facet of the decimation that
    # borders another place than the box's triangle did moves a sample, and a pose by a little)
    assert max(dt) < 0.02 * two_boxes[0].mesh.extent and max(dr) < 1.0
    assert np.median(dt) < 0.002 * two_boxes[0].mesh.extent

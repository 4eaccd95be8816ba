"""Equality of the answers holding arrays: TrackStep and Located compare by value (arrays number
for number, the stage times left out) and are not hashable; Pose (by value, hashable) for
comparison."""

import copy
import pickle

import numpy as np
import pytest

from quatrack.recognition.locate import Located
from quatrack.recognition.tracker.params import TrackStep
from quatrack.tracking.pose import Pose


def _step(**changes) -> TrackStep:
    rng = np.random.default_rng(5)
    a = rng.normal(size=(6, 6))
    fields = dict(frame=3, time_s=0.1, status="tracking", t=np.array([0.1, -0.2, 5.0]),
                  q_wxyz=np.array([0.9, 0.1, 0.3, np.sqrt(1 - 0.81 - 0.01 - 0.09)]), v=np.zeros(3),
                  omega=np.array([0.0, 0.01, 0.0]), covariance=a @ a.T, inliers=40, timings_ms={"total": 12.5},
                  reason=None)
    fields.update(changes)
    return TrackStep(**fields)


def _located(**changes) -> Located:
    fields = dict(found=True, bbox=(10.0, 20.0, 100.0, 80.0), chi2=3.5, viewset="front", matches=50, inliers=30,
                  reprojection_rms_px=0.8, t=np.array([0.0, 0.1, 4.0]), q_wxyz=np.array([1.0, 0.0, 0.0, 0.0]),
                  covariance=np.eye(6) * 1e-4, time_ms={"total": 40.0}, verification={"confidence": 0.97},
                  object="box")
    fields.update(changes)
    return Located(**fields)


@pytest.mark.parametrize("make, times", [(_step, "timings_ms"), (_located, "time_ms")])
def test_answers_with_arrays_compare_by_value_not_raising(make, times):
    # was ValueError "The truth value of an array with more than one element is ambiguous"
    a, b = make(), make()
    assert a == b and not (a != b) and a == a
    assert b in [make(covariance=np.eye(6)), a]  # (list membership asks ==)
    assert a == make(**{times: {"total": 99.0, "other": 1.0}})  # the machine's times are not the answer
    assert a == make(t=list(a.t)) and a == make(t=a.t.copy())
    assert a != make(t=a.t.astype(np.float32).astype(float))  # exact: not within rounding
    assert a == copy.deepcopy(a) and a == pickle.loads(pickle.dumps(a))
    assert a != make(t=a.t + [0.0, 0.0, 1e-12])
    assert a != make(covariance=a.covariance[:5, :5])  # another shape, the same leading numbers
    assert a != make(covariance=None) and a != make(inliers=a.inliers + 1)
    assert a != "a string" and a != Pose(np.array(a.q_wxyz), a.t)


def test_lost_steps_and_not_found_answers_compare_by_their_fields():
    assert TrackStep(1, 0.0, "lost", reason="x") == TrackStep(1, 0.0, "lost", reason="x", timings_ms={"total": 2.0})
    assert TrackStep(1, 0.0, "lost", reason="x") != TrackStep(1, 0.0, "lost", reason="y")
    assert Located(False, reason="no match") == Located(False, reason="no match", time_ms={"total": 3.0})
    assert Located(False, reason="no match") != _located()
    assert _step() != _located()


@pytest.mark.parametrize("answer", [_step(), _located(), TrackStep(1, 0.0, "lost")])
def test_answers_are_not_hashable_they_change_after_they_are_made(answer):
    # value equality on a mutable object: a hash would change under the dict holding it
    # (locate_all marks an answer not found; Pose, frozen with read-only arrays, is hashable)
    with pytest.raises(TypeError, match="unhashable"):
        hash(answer)
    assert len({_step().pose, _step().pose}) == 1


def test_meshes_compare_by_value_and_hash_alike_when_equal():
    # (the frozen dataclass's == raised "the truth value of an array ... is ambiguous", hash()
    # "unhashable type: 'numpy.ndarray'")
    from quatrack.examples import example_dir
    from quatrack.viewsets.mesh import load_mesh, make_mesh

    box = load_mesh(example_dir() / "box.ply")
    same = make_mesh(box.vertices.copy(), box.faces.astype(np.int64))
    assert box == same and hash(box) == hash(same) and len({box, same}) == 1 and box == box
    assert box != make_mesh(box.vertices + [0.0, 0.0, 1e-9], box.faces)
    assert box != make_mesh(box.vertices, box.faces[::-1]) and box != make_mesh(box.vertices, box.faces[:11])
    assert box != "box" and box != None  # noqa: E711
    assert {box: "model"}[same] == "model"


def test_pnp_solutions_compare_by_value_and_hash_by_their_pose():
    # (solve_pnp's result: the frozen dataclass's == raised, its hash was "unhashable type")
    from quatrack.recognition.pose import PnPSolution

    pose = Pose.from_rvec([0.1, 0.2, 0.3], [0.0, 0.0, 5.0])
    a = PnPSolution(pose, np.eye(6) * 1e-4, np.arange(12), 0.7)
    b = PnPSolution(Pose.from_rvec([0.1, 0.2, 0.3], [0.0, 0.0, 5.0]), np.eye(6) * 1e-4, np.arange(12), 0.7,
                    ties=(pose,))  # (ties do not compare)
    assert a == b and hash(a) == hash(b) and len({a, b}) == 1
    assert a != PnPSolution(pose, np.eye(6) * 2e-4, np.arange(12), 0.7)
    assert a != PnPSolution(pose, np.eye(6) * 1e-4, np.arange(11), 0.7) and a != pose

"""Reasons recognition gives for a pose it refuses, read by users in ``locate``'s "not found (...)".
A user saw "its inliers would be seen at a transition tilt of inf from its matched viewset's view":
inf is where a view sees the points' faces edge-on or from behind, and it now says so."""

from __future__ import annotations

import numpy as np

from quatrack.recognition.pose import PnPSolution, PoseParams, _basic_checks
from quatrack.tracking.pose import Pose


def _face(n: int = 20):
    """``n`` points on the plane z = 0 facing −z, and a pose 5 units in front of them (camera on −z)."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    normals = np.tile([0.0, 0.0, -1.0], (n, 1))
    est = PnPSolution(Pose(np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 0.0, 5.0])), np.eye(6), np.arange(n), 0.1)
    return X, normals, est


def test_a_view_that_sees_the_inliers_from_behind_is_named_not_inf():
    X, normals, est = _face()
    behind = (Pose(np.array([0.0, 0.0, 1.0, 0.0]), np.array([0.0, 0.0, 5.0])).R, np.array([0.0, 0.0, 5.0]))  # (turned 180°)
    why = _basic_checks(est, len(X), PoseParams(), X, normals, behind)
    assert why == ("most of its inliers would lie on faces its matched viewset's view sees edge-on or from behind: "
                   "no match across that (transition tilt at most 2.5)"), why
    assert "inf" not in why


def test_a_finite_tilt_keeps_its_number():
    X, normals, est = _face()
    a = np.radians(75.0)  # the reference sees the face ~75° from its normal: a tilt of ~3.9 (3.7 over the points)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    why = _basic_checks(est, len(X), PoseParams(), X, normals, (R, np.array([0.0, 0.0, 5.0])))
    assert why.startswith("its inliers would be seen at a transition tilt of 3.7 from its matched viewset's view"), why

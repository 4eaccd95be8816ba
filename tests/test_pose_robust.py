"""A verified pose is reported as a robust fit of its inliers, not least squares (issue 13, session 25).

In zoo seed 0 the two poses reported found but wrong were least-squares fits in which a few
inliers 3–6 px off (of 12 and of 27; the rest within 0.5–1 px at the true pose) moved the pose
along the line of sight by 5–6 % of the object's diameter. These tests build that at a known
pose — matches on a slab's face seen from 45 units, exact projections plus 0.5 px noise, five of
27 pushed 3.5 px outwards (a nearer-looking object) — and check that :func:`solve_pnp` stays
near the truth once polished (:func:`polish`, as ``locate`` reports a verified pose), and that on
clean matches the robust fit costs no accuracy.
"""

import numpy as np
import pytest

from quatrack.recognition.pose import PoseParams, deleted_errors, polish, robust_refit, solve_pnp
from quatrack.tracking import quaternion as quat
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose

CAM = PinholeCamera(600.0, 600.0, 319.5, 239.5, width=640, height=480)
SIZE = np.array([16.0, 11.0, 3.0])  # a slab; the centre at the origin
DIAMETER = float(np.linalg.norm(SIZE))


def _slab_scene(seed: int, off: int = 5, push_px: float = 3.5, n: int = 27, noise_px: float = 0.5):
    """Matches on the slab's top face (z = −1.5) seen 20–35° from its normal at 45 units (the
    face ~200 px wide); the first ``off`` pushed ``push_px`` away from the projected centre."""
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-8, 8, n), rng.uniform(-5.5, 5.5, n), np.full(n, -1.5)])
    R = quat.to_matrix(quat.from_rotvec(np.array([np.radians(rng.uniform(20, 35)), 0.0, 0.0]) + rng.normal(0, 0.1, 3)))
    truth = Pose(quat.from_matrix(R), np.array([rng.uniform(-3, 3), rng.uniform(-2, 2), 45.0]))
    uv = CAM.project(truth.apply(X)) + rng.normal(0, noise_px, (n, 2))
    c = CAM.project(truth.apply(np.zeros((1, 3))))[0]
    d = uv[:off] - c
    uv[:off] += push_px * d / np.linalg.norm(d, axis=1, keepdims=True)
    return X, uv, truth


def _criterion(est, truth) -> float:
    """The error against the criterion of a right pose: max(centre / 5 % of the diameter, rotation / 5°)."""
    dc = np.linalg.norm(est.t - truth.t)  # the centre is the origin
    return max(dc / (0.05 * DIAMETER), np.degrees(quat.angle_between(est.q, truth.q_wxyz)) / 5.0)


def _errors(params: PoseParams, **scene) -> np.ndarray:
    out = []
    for seed in range(10):
        X, uv, truth = _slab_scene(seed, **scene)
        est = solve_pnp(CAM, X, uv, params)
        assert est is not None and len(est.inliers) == len(X)  # every match is within the 4-px inlier threshold
        est = polish(est, CAM, X, uv, params)  # as locate reports a verified pose
        out.append(_criterion(est, truth))
    return np.array(out)


def test_a_few_inliers_a_few_pixels_off_do_not_move_the_pose():
    robust = _errors(PoseParams())
    least_squares = _errors(PoseParams(robust_scale=None, drop_pulled_inliers=False))
    # least squares: 0.13–0.78 of the criterion, mean 0.45; the robust fit 0.05–0.21, mean 0.15
    assert robust.max() < 0.3, robust.round(2)
    assert robust.mean() < 0.5 * least_squares.mean(), (robust.round(2), least_squares.round(2))


def test_on_clean_matches_the_robust_fit_is_as_accurate():
    robust = _errors(PoseParams(), off=0)
    least_squares = _errors(PoseParams(robust_scale=None, drop_pulled_inliers=False), off=0)
    assert robust.mean() < 1.2 * least_squares.mean(), (robust.round(3), least_squares.round(3))
    assert robust.max() < 0.2


@pytest.mark.parametrize("n", [3, 5])
def test_too_few_matches_leave_the_pose(n):
    X = np.zeros((n, 3))
    t, q = robust_refit(CAM, X, np.zeros((n, 2)), np.array([0.0, 0.0, 10.0]), np.array([1.0, 0.0, 0.0, 0.0]))
    assert np.allclose(t, [0, 0, 10]) and np.allclose(q, [1, 0, 0, 0])


def _leveraged_scene(seed: int, push_px: float = 8.0, n: int = 23):
    """23 right matches on the left third of the slab's face and 2 wrong ones at its far corners,
    both pushed ``push_px`` sideways (as zoo seed 0's wide box, 60 % out of the frame: 2 wrong of
    25 inliers on one face held the pose 6.8 %/3.1° off, 1.6 and 3.7 px from it)."""
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-8, -3, n), rng.uniform(-5.5, 5.5, n), np.full(n, -1.5)])
    X = np.vstack([X, [[7.8, 5.2, -1.5], [7.6, -5.0, -1.5]]])
    R = quat.to_matrix(quat.from_rotvec(np.array([np.radians(rng.uniform(20, 35)), 0.0, 0.0]) + rng.normal(0, 0.1, 3)))
    truth = Pose(quat.from_matrix(R), np.array([rng.uniform(-3, 3), rng.uniform(-2, 2), 45.0]))
    uv = CAM.project(truth.apply(X)) + rng.normal(0, 0.4, (len(X), 2))
    uv[n:, 0] += push_px
    return X, uv, truth


def test_inliers_that_pull_the_fit_onto_themselves_are_dropped():
    """Wrong matches with leverage pull the least-squares pose onto themselves: they stay within
    the 4-px inlier threshold of it, and the Cauchy refit, which starts there, keeps them. Their
    deleted residuals (the error at the pose fitted without each) give them away."""
    kept, dropped = [], []
    for seed in range(10):
        X, uv, truth = _leveraged_scene(seed)
        est = solve_pnp(CAM, X, uv, PoseParams())
        assert est is not None
        kept.append(_criterion(polish(est, CAM, X, uv, PoseParams(drop_pulled_inliers=False)), truth))
        dropped.append(_criterion(polish(est, CAM, X, uv, PoseParams()), truth))
    kept, dropped = np.array(kept), np.array(dropped)
    # kept: 5 of 10 beyond the criterion (1.2-1.5); dropped: 2 (two wrong matches hiding each other)
    assert (kept > 1.0).sum() >= 4 and (dropped > 1.0).sum() <= 2, (kept.round(2), dropped.round(2))
    assert np.median(dropped) < 0.5 * np.median(kept)


def test_deleted_residuals_of_right_matches_stay_small():
    """On right matches (0.5 px noise) no deleted residual reaches the inlier threshold: nothing
    is dropped, and the polished pose is as before."""
    for seed in range(10):
        X, uv, truth = _slab_scene(seed, off=0)
        est = solve_pnp(CAM, X, uv, PoseParams())
        d = deleted_errors(CAM, X[est.inliers], uv[est.inliers], est.t, est.q)
        assert d.max() < PoseParams().inlier_px
        a = polish(est, CAM, X, uv, PoseParams())
        b = polish(est, CAM, X, uv, PoseParams(drop_pulled_inliers=False))
        assert np.allclose(a.t, b.t) and np.allclose(a.q, b.q)

"""The systematic floor of the reported covariance (quatrack.tracking.systematic).

The floor is stated as an error of the object's centre (across / along the line of sight) and a
rotation error; the state's coordinates are the origin ``p`` and ``δθ``. The transform between
them is checked against the exact perturbation of a pose, by Monte Carlo: draw the centre's
shift and the rotation, move the pose exactly, and compare the sample covariance of ``[Δp, δθ]``
with the floor.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from quatrack.tracking.rotation import rodrigues as exp_so3
from quatrack.tracking.systematic import systematic_floor

vec = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).map(np.array)


@settings(max_examples=12)
@given(rv=vec, centre=vec, lateral=st.floats(0.001, 0.02), ratio=st.floats(1.0, 5.0), angle=st.floats(0.0005, 0.01))
def test_the_floor_is_the_covariance_of_the_exactly_perturbed_pose(rv, centre, lateral, ratio, angle):
    rng = np.random.default_rng(0)
    R = exp_so3(rv)
    d = 0.3
    p = np.array([0.1, -0.05, 1.5]) - R @ centre  # the centre 1.5 in front of the camera
    F = systematic_floor(R, p, centre, d, lateral, ratio, angle)
    c_cam = R @ centre + p
    z = c_cam / np.linalg.norm(c_cam)
    Sc = (lateral * d) ** 2 * (np.eye(3) + (ratio**2 - 1) * np.outer(z, z))
    n = 20000
    dc = rng.multivariate_normal(np.zeros(3), Sc, n)
    dth = rng.normal(0.0, angle, (n, 3))
    R2 = exp_so3(dth) @ R  # the exact pose: turned by exp(dθ) about the camera axes, centre moved by dc
    dp = (c_cam + dc - R2 @ centre) - p
    emp = np.cov(np.column_stack([dp, dth]).T)
    scale = np.sqrt(np.outer(np.diag(F), np.diag(F)))
    assert np.all(np.abs(emp - F) <= 0.05 * scale + 1e-12)


def test_zero_floor_and_units():
    R, p, c = np.eye(3), np.array([0.0, 0.0, 2.0]), np.array([0.1, 0.0, 0.0])
    assert not np.any(systematic_floor(R, p, c, 1.0, 0.0, 1.0, 0.0))
    # lengths in another unit: the position block scales with its square, the rotation block not
    a = systematic_floor(R, p, c, 1.0, 0.004, 4.0, 0.001)
    b = systematic_floor(R, 10 * p, 10 * c, 10.0, 0.004, 4.0, 0.001)
    assert np.allclose(b[:3, :3], 100 * a[:3, :3]) and np.allclose(b[3:, 3:], a[3:, 3:])
    assert np.allclose(b[:3, 3:], 10 * a[:3, 3:])

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
from quatrack.tracking.systematic import image_floor, systematic_floor

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


def _camera():
    from quatrack.tracking.camera import PinholeCamera

    return PinholeCamera(600.0, 580.0, 320.0, 240.0, np.zeros(5), width=640, height=480)


def _box(a, b, c):
    return np.array([[x, y, z] for x in (-a, a) for y in (-b, b) for z in (-c, c)], float) / 2


@settings(max_examples=10, deadline=None)
@given(rv=vec, shift=vec, s=st.floats(0.1, 1.0))
def test_the_image_floor_is_the_shared_pixel_error_through_numerical_jacobians(rv, shift, s):
    """s² (1/n Σ JᵢᵀJᵢ)⁻¹ with every Jᵢ taken by central differences of the projection under the
    state's own perturbation (``p + δp``, ``R → exp(δθ) R``), not from project_model_points."""
    cam = _camera()
    X = _box(0.2, 0.1, 0.35)
    R, p = exp_so3(rv), np.array([0.0, 0.0, 1.5]) + 0.1 * shift

    def pixels(delta):
        R2 = exp_so3(delta[3:]) @ R
        return cam.project(X @ R2.T + p + delta[:3])

    h = 1e-6
    J = np.stack([(pixels(h * e) - pixels(-h * e)) / (2 * h) for e in np.eye(6)], axis=-1)  # (n, 2, 6)
    expected = s**2 * np.linalg.inv(np.einsum("nki,nkj->ij", J, J) / len(X))
    F = image_floor(cam, R, p, X, s)
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    assert np.all(np.abs(F - expected) <= 1e-5 * scale)


def test_the_image_floor_follows_the_shape_the_distance_and_not_the_units():
    cam = _camera()
    tall = _box(0.1, 0.1, 0.4)  # a tall box standing along the camera's y axis, seen from the side
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # object z → camera y
    p = np.array([0.0, 0.0, 1.5])
    F = image_floor(cam, R, p, tall, 0.3)
    sd = np.sqrt(np.diag(F))
    # its turn about its long axis (camera y) moves its points only across its narrow width: far
    # less known than its turn in the image (about the line of sight), and than a cube's as wide
    # as the tall box is long
    assert sd[4] > 3.0 * sd[5]
    cube = np.sqrt(np.diag(image_floor(cam, R, p, _box(0.4, 0.4, 0.4), 0.3)))
    assert sd[4] > 3.0 * cube[4]
    # twice as far: across the line of sight ×2, along it ×4 (depth shows as size), turns ×2
    G = np.sqrt(np.diag(image_floor(cam, R, 2 * p, tall, 0.3)))
    assert np.isclose(G[0] / sd[0], 2.0, rtol=0.05) and np.isclose(G[2] / sd[2], 4.0, rtol=0.05)
    assert np.allclose(G[3:] / sd[3:], 2.0, rtol=0.05)
    # the object and its pose in millimetres instead of metres: the same floor in those units
    M = image_floor(cam, R, 1000 * p, 1000 * tall, 0.3)
    assert np.allclose(M[:3, :3], 1e6 * F[:3, :3]) and np.allclose(M[3:, 3:], F[3:, 3:])
    assert np.allclose(M[:3, 3:], 1e3 * F[:3, 3:])
    # no shared error, or no pose the points determine: no floor
    assert not np.any(image_floor(cam, R, p, tall, 0.0))
    assert not np.any(image_floor(cam, R, p, tall[:2], 0.3))

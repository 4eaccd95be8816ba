"""Camera projection and measurement blocks: values against OpenCV, Jacobians against finite
differences of the left perturbation, the Deriche–Faugeras covariance against sampling."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from quatrack.tracking import quaternion as quat
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.measurements import (
    PointMeasurements,
    SegmentMeasurements,
    project_model_points,
    reduced_midpoint,
    segment_covariance,
    wrap_half_turn,
)
from quatrack.tracking.rotation import rodrigues

DIST = {
    "none": np.zeros(5),
    "radial-tangential": np.array([-0.21, 0.08, 0.0012, -0.0009, -0.015]),
    "rational": np.array([0.1, -0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005]),
}


def random_pose(rng):
    return rng.normal(0, 30, size=3) + np.array([0, 0, 900.0]), quat.from_rotvec(rng.normal(0, 1, size=3))


def numeric_pose_jacobian(f, p, R, h=1e-6):
    """∂f/∂[δp, δθ] by central differences of p + δp, Exp(δθ) R."""
    cols = []
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        plus = f(p + d[:3], rodrigues(d[3:]) @ R)
        minus = f(p - d[:3], rodrigues(-d[3:]) @ R)
        cols.append((plus - minus) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("kind", list(DIST))
def test_projection_matches_opencv(kind):
    rng = np.random.default_rng(3)
    cam = PinholeCamera(712.0, 705.0, 318.0, 241.0, DIST[kind])
    X = rng.uniform(-100, 100, size=(50, 3))
    p, q = random_pose(rng)
    uv = cam.project(X @ quat.to_matrix(q).T + p)
    ref, _ = cv2.projectPoints(X, quat.to_rotvec(q), p, cam.matrix, cam.dist_coeffs)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)


@pytest.mark.parametrize("kind", list(DIST))
def test_projection_jacobian(kind):
    rng = np.random.default_rng(4)
    cam = PinholeCamera(712.0, 705.0, 318.0, 241.0, DIST[kind])
    X = rng.uniform(-150, 150, size=(20, 3)) + np.array([0, 0, 800])
    _, J = cam.project_with_jacobian(X)
    h = 1e-5
    num = np.stack([(cam.project(X + h * e) - cam.project(X - h * e)) / (2 * h) for e in np.eye(3)], -1)
    np.testing.assert_allclose(J, num, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("kind", list(DIST))
@given(s=st.floats(0.1, 3.0), pad=st.integers(0, 5))
@settings(max_examples=25)
def test_a_scaled_camera_sees_each_point_where_the_resized_image_shows_it(kind, s, pad):
    """PinholeCamera.scaled: the pixel u of the image is s(u + ½) − ½ (+ pad) of the image resized
    by s (pixel centres preserved, as cv2.resize maps them), lens distortion included."""
    cam = PinholeCamera(712.0, 705.0, 318.0, 241.0, DIST[kind], width=640, height=480)
    X = np.random.default_rng(5).uniform(-100, 100, size=(30, 3)) + np.array([0, 0, 900.0])
    small = cam.scaled(s, pad=pad)
    np.testing.assert_allclose(small.project(X), s * (cam.project(X) + 0.5) - 0.5 + pad, atol=1e-9)
    assert (small.width, small.height) == (round(640 * s) + 2 * pad, round(480 * s) + 2 * pad)
    assert cam.scaled(s, 100, 70).width == 100 and cam.scaled(s, 100, 70).height == 70


def test_camera_rejects_bad_intrinsics():
    with pytest.raises(ValueError, match="focal"):
        PinholeCamera(0.0, 500.0, 320, 240)
    with pytest.raises(ValueError, match="distortion"):
        PinholeCamera(500.0, 500.0, 320, 240, np.r_[np.zeros(8), 0.1])


@pytest.mark.parametrize("kwargs, match", [
    ({"width": "640"}, "width must be a whole number"),  # (TypeError '<=' not supported)
    ({"height": 480.5}, "height must be a whole number"),
    ({"width": True}, "width must be a whole number"),
    ({"t_rig": [1.0, 2.0]}, "t_rig must be 3 numbers"),  # (numpy's "cannot reshape array of size 2")
    ({"R_rig": np.eye(2)}, "R_rig must be a 3×3 matrix"),
    ({"R_rig": "identity"}, "R_rig must be numbers"),
    ({"R_rig": 2.0 * np.eye(3)}, "R_rig is not a rotation"),  # (accepted: every projection scaled)
    ({"R_rig": np.diag([1.0, 1.0, -1.0])}, "R_rig is not a rotation"),  # (a mirror, accepted)
    ({"t_rig": [np.nan, 0.0, 0.0]}, "t_rig must be finite"),  # (accepted: every projection NaN)
])
def test_camera_names_what_is_wrong_with_its_size_and_rig(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PinholeCamera(800.0, 800.0, 320.0, 240.0, **{"width": 640, "height": 480, **kwargs})


def test_a_camera_size_given_as_whole_floats_is_kept_as_ints():
    # width=640.0 (a size read from YAML or computed) stayed a float: np.zeros((height, width))
    # and range(width) refused it, and JSON wrote 640.0
    cam = PinholeCamera(800.0, 800.0, 320.0, 240.0, width=640.0, height=np.float32(480.0))
    assert (cam.width, cam.height) == (640, 480) and type(cam.width) is int and type(cam.height) is int
    assert cam == PinholeCamera(800.0, 800.0, 320.0, 240.0, width=640, height=480)
    assert np.zeros((cam.height, cam.width)).shape == (480, 640)


def test_cameras_compare_by_value_and_hash():
    # the dataclass's __eq__ compared the numpy fields as a tuple: two equal cameras (a camera
    # file loaded twice, a pickled copy) raised ValueError ("truth value ... ambiguous") and
    # hash() TypeError
    import copy
    import pickle

    a = PinholeCamera(800.0, 800.0, 320.0, 240.0, [0.1, 0.0, 0.0, 0.0, 0.0], width=640, height=480)
    b = PinholeCamera(800, 800, 320, 240, np.array([0.1, -0.0, 0, 0, 0]), width=640, height=480)
    assert a == b and a == pickle.loads(pickle.dumps(a)) and a == copy.deepcopy(a) and hash(a) == hash(b)
    assert a != PinholeCamera(800.0, 800.0, 320.0, 240.0, [0.2, 0.0, 0.0, 0.0, 0.0], width=640, height=480)
    assert a != a.scaled(0.5) and a != "camera" and len({a, b, a.scaled(0.5)}) == 2
    assert a.cropped(0, 0, 640, 480) == a  # (crop_of is not compared)


rig = PinholeCamera(650.0, 650.0, 320.0, 240.0, DIST["radial-tangential"], R_rig=rodrigues(np.array([0.02, -0.3, 0.01])), t_rig=np.array([-120.0, 3.0, 10.0]))


@pytest.mark.parametrize("cam", [PinholeCamera(700.0, 690.0, 320.0, 240.0, DIST["rational"]), rig], ids=["reference", "rig"])
@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_point_block_jacobian(cam, seed):
    rng = np.random.default_rng(seed)
    p, q = random_pose(rng)
    R = quat.to_matrix(q)
    X = rng.uniform(-80, 80, size=(6, 3))
    cov = np.array([[2.0, 0.3], [0.3, 1.0]])
    block = PointMeasurements.create(cam, X, rng.uniform(0, 600, size=(6, 2)), cov)
    lin = block.linearize(p, R)
    num = numeric_pose_jacobian(lambda pp, RR: block.linearize(pp, RR, False).residual, p, R)
    np.testing.assert_allclose(lin.jacobian, num, rtol=1e-5, atol=1e-6)
    # whitening: ½‖e‖² is the Mahalanobis form of eq. 24
    raw = cam.project((X @ R.T + p) @ cam.R_rig.T + cam.t_rig) - block.image_points
    maha = np.einsum("ni,ij,nj->n", raw, np.linalg.inv(cov), raw)
    np.testing.assert_allclose(np.sum(lin.residual**2, axis=1), maha, rtol=1e-10)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_segment_block_jacobian(seed):
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(700.0, 690.0, 320.0, 240.0, DIST["radial-tangential"])
    p, q = random_pose(rng)
    R = quat.to_matrix(q)
    segs = rng.uniform(-80, 80, size=(5, 2, 3))
    true_uv = cam.project((segs.reshape(-1, 3) @ R.T) + p).reshape(-1, 2, 2)
    block = SegmentMeasurements.from_endpoints(cam, segs, true_uv + rng.normal(0, 2, size=true_uv.shape), 5.0, 1.0)
    lin = block.linearize(p, R)
    num = numeric_pose_jacobian(lambda pp, RR: block.linearize(pp, RR, False).residual, p, R)
    np.testing.assert_allclose(lin.jacobian, num, rtol=1e-5, atol=1e-6)


def test_segment_residual_is_zero_at_the_true_pose_and_ignores_direction():
    rng = np.random.default_rng(0)
    cam = PinholeCamera(700.0, 700.0, 320.0, 240.0)
    p, q = random_pose(rng)
    R = quat.to_matrix(q)
    segs = rng.uniform(-80, 80, size=(4, 2, 3))
    uv = cam.project(segs.reshape(-1, 3) @ R.T + p).reshape(-1, 2, 2)
    block = SegmentMeasurements.from_endpoints(cam, segs, uv[:, ::-1], 7.0, 1.0)  # end points swapped
    np.testing.assert_allclose(block.linearize(p, R, False).residual, 0.0, atol=1e-9)


def test_deriche_faugeras_covariance_matches_sampling():
    rng = np.random.default_rng(7)
    # 300 px long: the first-order formula leaves out a relative 3·2σ∥²/l² (0.3 % here) from the
    # along-noise changing the length
    seg = np.array([[[100.0, 50.0], [340.0, 230.0]]])
    d = (seg[0, 1] - seg[0, 0]) / 300.0
    n = np.array([-d[1], d[0]])
    N = 200_000
    s_al, s_ac = 7.0, 1.0
    noise = rng.normal(0, s_al, size=(N, 2, 1)) * d + rng.normal(0, s_ac, size=(N, 2, 1)) * n
    samples = reduced_midpoint(seg + noise)
    samples[:, 2] = wrap_half_turn(samples[:, 2] - samples[:, 2].mean()) + samples[:, 2].mean()
    emp = np.cov(samples.T)
    model = segment_covariance(seg, s_al, s_ac)[0]
    np.testing.assert_allclose(emp[:2, :2], model[:2, :2], rtol=0.02, atol=0.02)
    assert emp[2, 2] == pytest.approx(model[2, 2], rel=0.015)  # 2σ⊥²/l²
    assert abs(emp[0, 2]) < 1e-4 and abs(emp[1, 2]) < 1e-4  # angle ⟂ mid-point


def test_wrap_half_turn():
    np.testing.assert_allclose(wrap_half_turn(np.array([0.1, np.pi - 0.1, -np.pi + 0.2, 3 * np.pi / 2])), [0.1, -0.1, 0.2, -np.pi / 2])


def test_blocks_reject_mismatched_inputs():
    cam = PinholeCamera(700.0, 700.0, 320.0, 240.0)
    with pytest.raises(ValueError, match="model points"):
        PointMeasurements.create(cam, np.zeros((3, 3)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="positive"):
        PointMeasurements.create(cam, np.zeros((3, 3)), np.zeros((3, 2)), 0.0)
    with pytest.raises(ValueError, match="degenerate"):
        segment_covariance(np.zeros((1, 2, 2)), 1.0, 1.0)


def test_sqrt_information_of_2x2_covariances_whitens_exactly():
    """The closed form for 2×2 blocks: ``WᵀW = Σ⁻¹``, ``W`` upper-triangular with a positive
    diagonal (the Cholesky factor, unique), equal to the general route's; non-SPD input raises."""
    from quatrack.tracking.measurements import sqrt_information

    rng = np.random.default_rng(4)
    A = rng.normal(size=(200, 2, 2))
    C = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(2)  # SPD, some nearly singular
    C[:50] *= 1e4  # and a wide range of scales
    W = sqrt_information(C)
    np.testing.assert_allclose(np.swapaxes(W, 1, 2) @ W @ C, np.broadcast_to(np.eye(2), C.shape), atol=1e-8)
    assert np.all(W[:, 1, 0] == 0) and np.all(W[:, 0, 0] > 0) and np.all(W[:, 1, 1] > 0)
    general = np.swapaxes(np.linalg.cholesky(np.linalg.inv(C)), 1, 2)
    np.testing.assert_allclose(W, general, rtol=1e-9, atol=1e-12 * np.abs(general).max())
    for bad in (np.array([[1.0, 2.0], [2.0, 1.0]]), np.array([[-1.0, 0.0], [0.0, 1.0]]), np.zeros((2, 2))):
        with pytest.raises(np.linalg.LinAlgError):
            sqrt_information(np.stack([np.eye(2), bad]))


@given(seed=st.integers(0, 10_000))
def test_undistorted_projection_equals_the_general_path(seed):
    """``project_model_points`` for a reference camera without distortion is written out (the
    adjustment calls it at every iteration); it equals the general path — the camera's
    projection and Jacobian, with ``∂uv/∂δθ = RX × row`` — value for value."""
    from quatrack.tracking.rotation import cross

    rng = np.random.default_rng(seed)
    cam = PinholeCamera(700.0 + rng.uniform(0, 200), 650.0 + rng.uniform(0, 200), 320.0, 240.0, width=640, height=480)
    assert cam.is_reference and not cam.has_distortion
    X = rng.uniform(-50, 50, (int(rng.integers(1, 40)), 3))
    R = rodrigues(rng.normal(0, 1, 3))
    p = np.array([rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(300, 900)])
    uv, J = project_model_points(cam, X, p, R, True)
    RX = X @ R.T
    uv_ref, Jx = cam.project_with_jacobian(RX + p, True)
    J_ref = np.concatenate([Jx, cross(RX[:, None, :], Jx)], axis=-1)
    np.testing.assert_array_equal(uv, uv_ref)
    np.testing.assert_array_equal(J, J_ref)
    uv2, none = project_model_points(cam, X, p, R, False)
    np.testing.assert_array_equal(uv2, uv_ref)
    assert none is None


@given(seed=st.integers(0, 10_000))
def test_the_compiled_point_block_equals_the_numpy_one(seed):
    """A point block of a reference camera without distortion linearises in one compiled pass
    (the adjustment's inner loop); it gives the numpy path's whitened residuals and Jacobian
    (:func:`project_model_points` then the 2×2 whitening) bit for bit, signed zeros included,
    with per-point covariances and with a point straight ahead of the camera (x = y = 0)."""
    from quatrack.tracking.measurements import _whiten

    rng = np.random.default_rng(seed)
    cam = PinholeCamera(700.0 + rng.uniform(0, 200), 650.0 + rng.uniform(0, 200), 320.0, 240.0, width=640, height=480)
    n = int(rng.integers(1, 60))
    X = rng.uniform(-50, 50, (n, 3))
    p, q = random_pose(rng)
    R = quat.to_matrix(q)
    X[0] = R.T @ (np.array([0.0, 0.0, 500.0]) - p)  # on the optical axis
    A = rng.normal(0, 1, (n, 2, 2))
    C = A @ np.swapaxes(A, 1, 2) + 0.05 * np.eye(2)
    block = PointMeasurements.create(cam, X, rng.uniform(0, 640, (n, 2)), C)
    uv, J = project_model_points(cam, X, p, R, True)
    ref = _whiten(block.sqrt_info, uv - block.image_points, J)
    lin = block.linearize(p, R)
    np.testing.assert_array_equal(lin.residual, ref.residual)
    np.testing.assert_array_equal(lin.jacobian, ref.jacobian)
    np.testing.assert_array_equal(np.signbit(lin.jacobian), np.signbit(ref.jacobian))
    plain = block.linearize(p, R, jacobian=False)
    np.testing.assert_array_equal(plain.residual, ref.residual)
    assert plain.jacobian is None


@pytest.mark.parametrize("kind", ["radial-tangential", "rational"])
@given(seed=st.integers(0, 10_000))
@settings(max_examples=25)
def test_the_compiled_distorted_projection_equals_the_numpy_one(kind, seed):
    """A distorted camera projects in one compiled pass (PinholeCamera._project_distorted): the
    numpy original's pixels and Jacobian bit for bit, signed zeros included, a point on the
    optical axis and one far off it among them; without the Jacobian, the same pixels."""
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(712.0, 705.0, 318.3, 241.7, DIST[kind] * rng.uniform(0.2, 2.0), width=640, height=480)
    n = int(rng.integers(1, 80))
    X = rng.uniform(-300, 300, (n, 3)) + np.array([0.0, 0.0, 900.0])
    X[0, :2] = 0.0
    iz = 1.0 / X[:, 2]
    x, y = X[:, 0] * iz, X[:, 1] * iz
    uv, J = cam._project_distorted(x, y, iz, True)
    uv_ref, J_ref = cam._project_distorted_numpy(x, y, iz, True)
    np.testing.assert_array_equal(uv, uv_ref)
    np.testing.assert_array_equal(J, J_ref)
    np.testing.assert_array_equal(np.signbit(J), np.signbit(J_ref))
    uv2, none = cam._project_distorted(x, y, iz, False)
    np.testing.assert_array_equal(uv2, uv_ref)
    assert none is None

"""Property tests of the quaternion and rotation algebra (Ude 1999, eqs. 3–10, 18–21, A.1–A.2)."""

import cv2
import numpy as np
import pytest
from scipy.integrate import simpson
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from quatrack.tracking import quaternion as quat
from quatrack.tracking.rotation import left_jacobian, left_jacobian_inv, rodrigues, skew

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
vec3 = arrays(np.float64, 3, elements=finite)


@st.composite
def unit_quaternions(draw):
    v = draw(arrays(np.float64, 4, elements=finite))
    n = np.linalg.norm(v)
    if n < 1e-3:
        v, n = np.array([1.0, 0.0, 0.0, 0.0]), 1.0
    return v / n


@st.composite
def tangent_vectors(draw, max_norm=np.pi - 1e-3):
    """Vectors of norm < max_norm, including tiny ones (small-angle branches)."""
    direction = draw(vec3)
    n = np.linalg.norm(direction)
    if n < 1e-6:
        direction, n = np.array([1.0, 0.0, 0.0]), 1.0
    scale = draw(st.one_of(st.floats(0.0, max_norm), st.floats(0.0, 1e-7)))
    return direction / n * scale


@given(tangent_vectors())
def test_log_inverts_exp_inside_pi(r):
    np.testing.assert_allclose(quat.log(quat.exp(r)), r, atol=1e-12)


@given(tangent_vectors())
def test_exp_is_unit_and_rotates_by_twice_the_norm(r):
    q = quat.exp(r)
    assert abs(quat.norm(q) - 1.0) < 1e-15
    # eq. 7: exp(θ/2 n) is the rotation by θ about n
    np.testing.assert_allclose(quat.to_matrix(q), rodrigues(2.0 * r), atol=1e-12)


@given(unit_quaternions())
def test_exp_inverts_log(q):
    if q[0] < -1 + 1e-6:  # log is undefined at -1
        return
    np.testing.assert_allclose(quat.exp(quat.log(q)), q, atol=1e-12)


@given(unit_quaternions(), unit_quaternions(), unit_quaternions())
def test_product_is_associative_and_matches_matrices(a, b, c):
    np.testing.assert_allclose(quat.multiply(quat.multiply(a, b), c), quat.multiply(a, quat.multiply(b, c)), atol=1e-14)
    np.testing.assert_allclose(quat.to_matrix(quat.multiply(a, b)), quat.to_matrix(a) @ quat.to_matrix(b), atol=1e-13)
    np.testing.assert_allclose(quat.multiply(a, quat.conjugate(a)), quat.IDENTITY, atol=1e-15)


@given(unit_quaternions(), vec3)
def test_rotate_is_q_v_qbar_and_the_matrix(q, v):
    pure = np.concatenate([[0.0], v])
    sandwich = quat.multiply(quat.multiply(q, pure), quat.conjugate(q))  # eq. 5
    np.testing.assert_allclose(quat.rotate(q, v), sandwich[1:], atol=1e-14)
    np.testing.assert_allclose(quat.rotate(q, v), quat.to_matrix(q) @ v, atol=1e-14)
    assert abs(sandwich[0]) < 1e-14


@given(unit_quaternions())
def test_matrix_round_trip_is_canonical(q):
    R = quat.to_matrix(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(R) == pytest.approx(1.0)
    back = quat.from_matrix(R)
    assert back[0] >= 0.0
    if abs(q[0]) > 1e-9:
        np.testing.assert_allclose(back, quat.canonical(q), atol=1e-12)
    else:  # a half-turn: w is 0 up to rounding, so only the rotation is defined
        assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-12


@given(tangent_vectors())
def test_rotvec_matches_opencv_rodrigues(phi):
    phi = 2.0 * phi  # full rotation vectors up to 2π
    R_cv, _ = cv2.Rodrigues(phi)
    np.testing.assert_allclose(quat.to_matrix(quat.from_rotvec(phi)), R_cv, atol=1e-12)
    np.testing.assert_allclose(rodrigues(phi), R_cv, atol=1e-12)
    # to_rotvec returns the shortest equivalent rotation vector
    np.testing.assert_allclose(rodrigues(quat.to_rotvec(quat.from_rotvec(phi))), R_cv, atol=1e-12)
    assert np.linalg.norm(quat.to_rotvec(quat.from_rotvec(phi))) <= np.pi + 1e-12


@given(unit_quaternions(), vec3)
def test_exp_q_moves_along_the_tangent_space(q, r):
    # r * q is a tangent vector at q (orthogonal to q), and eq. 8 maps it to exp(r) * q
    r_q = quat.multiply(np.concatenate([[0.0], r]), q)
    assert abs(np.dot(r_q, q)) < 1e-14
    np.testing.assert_allclose(quat.exp_q(q, r_q), quat.multiply(quat.exp(r), q), atol=1e-14)
    # the geodesic starts at q with velocity r_q
    h = 1e-7
    velocity = (quat.exp_q(q, h * r_q) - quat.exp_q(q, -h * r_q)) / (2 * h)
    np.testing.assert_allclose(velocity, r_q, atol=1e-7)


@given(unit_quaternions(), unit_quaternions(), unit_quaternions())
def test_angular_metric(a, b, c):
    assert quat.distance(a, a) == pytest.approx(0.0, abs=1e-7)
    assert quat.distance(a, b) == pytest.approx(quat.distance(b, a), abs=1e-12)
    assert quat.distance(a, c) <= quat.distance(a, b) + quat.distance(b, c) + 1e-9
    assert quat.distance(a, -a) == pytest.approx(2 * np.pi)  # eq. 10, antipodal
    assert quat.angle_between(a, -a) == pytest.approx(0.0, abs=1e-7)  # one rotation
    # angle_between is the angle of the relative rotation matrix
    Rrel = quat.to_matrix(a) @ quat.to_matrix(b).T
    cos = np.clip((np.trace(Rrel) - 1) / 2, -1, 1)
    assert quat.angle_between(a, b) == pytest.approx(np.arccos(cos), abs=1e-6)


def test_log_next_to_minus_one_has_norm_pi():
    """Found by the ``explore`` profile: the small-‖u‖ branch ``u/w`` of log was also taken
    next to ``-1``, where it gives ~0 instead of ~π, so ``distance(-1 + ε, 1)`` came out ~0."""
    for eps in (1e-12, 1e-9, 3e-8):
        q = np.array([-np.sqrt(1 - eps**2), eps, 0.0, 0.0])
        assert np.linalg.norm(quat.log(q)) == pytest.approx(np.pi - eps, abs=1e-15)
        assert quat.distance(q, quat.IDENTITY) == pytest.approx(2 * np.pi, abs=1e-7)
        np.testing.assert_allclose(quat.exp(quat.log(q)), q, atol=1e-15)


def test_distance_of_a_known_rotation():
    q = quat.from_rotvec([0.0, 0.0, np.radians(30)])
    assert np.degrees(quat.distance(q, quat.IDENTITY)) == pytest.approx(30.0)


@given(unit_quaternions())
def test_dlog_matches_finite_differences(q):
    if q[0] < -0.95:  # log's derivative blows up near -1
        return
    h = 1e-7
    num = np.column_stack([(quat.log(q + h * e) - quat.log(q - h * e)) / (2 * h) for e in np.eye(4)])
    np.testing.assert_allclose(quat.dlog(q), num, atol=2e-6)


def test_dlog_at_identity_is_eq_A2():
    np.testing.assert_array_equal(quat.dlog(quat.IDENTITY), np.hstack([np.zeros((3, 1)), np.eye(3)]))
    # and continuous next to it
    near = quat.exp(np.array([1e-9, -2e-9, 0.5e-9]))
    np.testing.assert_allclose(quat.dlog(near), np.hstack([np.zeros((3, 1)), np.eye(3)]), atol=1e-8)


@given(tangent_vectors())
def test_dexp_matches_finite_differences(r):
    h = 1e-7
    num = np.column_stack([(quat.exp(r + h * e) - quat.exp(r - h * e)) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(quat.dexp(r), num, atol=2e-7)


@given(unit_quaternions())
def test_dlog_chain_is_the_inverse_left_jacobian(q):
    """d/dδθ 2 log(exp(δθ/2) * q) through A.1 equals J_l⁻¹(2 log q): the prior term's Jacobian."""
    q = quat.canonical(q)
    via_A1 = quat.dlog(q) @ quat.right_matrix(q)[:, 1:]
    np.testing.assert_allclose(via_A1, left_jacobian_inv(2 * quat.log(q)), atol=1e-9)


@given(tangent_vectors(), vec3)
def test_left_jacobian_linearises_exp(phi, d):
    phi = 2 * phi
    h = 1e-6
    lhs = rodrigues(phi + h * d) @ rodrigues(phi).T  # ≈ Exp(h J_l d)
    rhs = rodrigues(h * left_jacobian(phi) @ d)
    np.testing.assert_allclose(lhs, rhs, atol=1e-10)
    np.testing.assert_allclose(left_jacobian(phi) @ left_jacobian_inv(phi), np.eye(3), atol=1e-9)


@given(vec3, st.floats(1e-3, 0.5))
def test_G_is_the_integral_of_R(omega, dt):
    """Eq. 20–21: G = ∫_0^Δt R(t ω) dt, with Ude's closed form (s, c, n)."""
    omega = 5.0 * omega
    ts = np.linspace(0.0, dt, 2001)
    integral = simpson(rodrigues(ts[:, None] * omega), x=ts, axis=0)
    G = dt * left_jacobian(dt * omega)
    np.testing.assert_allclose(G, integral, atol=1e-8)
    th = dt * np.linalg.norm(omega)
    if th > 1e-6:
        n = omega / np.linalg.norm(omega)
        s = 2.0 / th * np.sin(th / 2) ** 2
        c = 2.0 / th * np.sin(th / 2) * np.cos(th / 2)
        ude = dt * ((1 - c) * np.outer(n, n) + c * np.eye(3) + s * skew(n))
        np.testing.assert_allclose(G, ude, atol=1e-12)


@given(unit_quaternions(), unit_quaternions())
def test_product_matrices(a, b):
    """L(a) b = a * b = R(b) a: the matrices the prior term's Jacobian (A.1 chain) is built from."""
    np.testing.assert_allclose(quat.left_matrix(a) @ b, quat.multiply(a, b), atol=1e-14)
    np.testing.assert_allclose(quat.right_matrix(b) @ a, quat.multiply(a, b), atol=1e-14)


def test_functions_are_vectorised():
    rng = np.random.default_rng(1)
    r = rng.normal(size=(5, 7, 3))
    q = quat.exp(r)
    assert q.shape == (5, 7, 4)
    assert quat.to_matrix(q).shape == (5, 7, 3, 3)
    np.testing.assert_allclose(quat.from_matrix(quat.to_matrix(q)), quat.canonical(q), atol=1e-12)
    assert quat.dlog(q).shape == (5, 7, 3, 4)
    for i in range(5):
        np.testing.assert_allclose(quat.log(q[i]), np.stack([quat.log(x) for x in q[i]]))


def test_angle_coefficients_keep_their_digits_near_zero():
    """sin θ/θ, (1-cos θ)/θ², (θ-sin θ)/θ³ against 40-digit series, across the switch-overs
    (a direct 1-cos θ lost 5 digits at θ = 2.5e-6, which hypothesis found through eq. 21)."""
    from decimal import Decimal, getcontext

    from quatrack.tracking.rotation import _angle_coefficients

    getcontext().prec = 40

    def series(x, k):  # Σ (-1)^i x^(2i+k) / (2i+k)!
        out, term, n = Decimal(0), Decimal(1), 0
        for i in range(k):
            term *= x / (i + 1)
        n = k
        for _ in range(30):
            out += term
            term *= -x * x / ((n + 1) * (n + 2))
            n += 2
        return out

    for th in (1e-9, 1e-7, 9.99e-7, 2.5e-6, 1e-4, 0.0999, 0.1, 0.5, 3.0):
        t = Decimal(th)
        sin, one_minus_cos = series(t, 1), series(t, 2)
        ref = (sin / t, one_minus_cos / t**2, (t - sin) / t**3)
        got = _angle_coefficients(np.array(th))
        for g, r in zip(got, ref):
            assert abs(Decimal(float(g)) - r) <= Decimal(1e-13) * abs(r), (th, float(g), float(r))


def test_pose_constructors_refuse_what_is_not_a_pose():
    from quatrack.tracking.pose import Pose

    assert np.allclose(Pose([1e300, 1e300, 0.0, 0.0], [0.0, 0.0, 1.0]).q_wxyz, [0.5**0.5, 0.5**0.5, 0.0, 0.0])
    with pytest.raises(ValueError, match="R is not a rotation"):
        Pose.from_matrix(np.diag([1.0, 1.0, -1.0]), [0.0, 0.0, 1.0])  # a reflection
    with pytest.raises(ValueError, match="R is not a rotation"):
        Pose.from_matrix(2.0 * np.eye(3), [0.0, 0.0, 1.0])
    T = Pose.from_rvec([0.1, 0.2, 0.3], [1.0, 2.0, 3.0]).as_matrix()
    with pytest.raises(ValueError, match="last row"):
        Pose.from_homogeneous(T.T)
    with pytest.raises(ValueError, match="4×4 or 3×4"):
        Pose.from_homogeneous(np.eye(3))
    with pytest.raises(ValueError, match="q_wxyz must be 4 numbers"):
        Pose([1.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    assert np.allclose(Pose.from_homogeneous(T[:3]).as_matrix(), T)


def test_pose_from_rvec_and_compose_name_what_is_wrong():
    # from_rvec([0, 0], t) said numpy's "cannot reshape array of size 2 into shape (3,)"; a pose
    # composed with a 4×4 array (pose @ T) raised AttributeError 'q_wxyz'
    from quatrack.tracking.pose import Pose

    with pytest.raises(ValueError, match="rvec must be 3 numbers"):
        Pose.from_rvec([0.0, 0.0], [0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="tvec must be 3 numbers"):
        Pose.from_rvec([0.0, 0.0, 0.0], "far")
    p = Pose.from_rvec(np.array([[0.1], [0.2], [0.3]]), np.array([[1.0], [2.0], [3.0]]))  # (OpenCV's (3, 1))
    assert np.array_equal(p.t, [1.0, 2.0, 3.0]) and np.array_equal(p.rvec.round(12), [0.1, 0.2, 0.3])
    with pytest.raises(TypeError, match="composes with a Pose.*from_homogeneous"):
        p @ p.as_matrix()


@st.composite
def rotations_near_half_turns(draw):
    """Unit quaternions anywhere on S³, and ones within 1e-12…1e-2 rad of a half-turn (w ≈ 0),
    where a from_matrix dividing by 4w² loses every digit."""
    axis = draw(vec3)
    n = np.linalg.norm(axis)
    if n < 1e-6:
        axis, n = np.array([0.0, 0.0, 1.0]), 1.0
    axis = axis / n
    near = draw(st.booleans())
    angle = (np.pi - draw(st.one_of(st.just(0.0), st.floats(1e-12, 1e-2)))) if near else draw(st.floats(0.0, np.pi))
    return quat.from_rotvec(angle * axis)


@given(st.one_of(unit_quaternions(), rotations_near_half_turns()))
def test_from_matrix_inverts_to_matrix_for_every_rotation_including_half_turns(q):
    R = quat.to_matrix(q)
    back = quat.from_matrix(R)
    assert back[0] >= 0.0 and abs(quat.norm(back) - 1.0) < 1e-15
    assert float(quat.angle_between(back, q)) < 1e-12  # the same rotation, to double precision
    np.testing.assert_allclose(quat.to_matrix(back), R, atol=1e-14)
    if abs(q[0]) > 1e-12:  # (at w = 0 the sign is canonical's choice, not q's)
        np.testing.assert_allclose(back, quat.canonical(q), atol=1e-14)


@pytest.mark.parametrize("R, q", [(np.diag([1.0, -1.0, -1.0]), [0.0, 1.0, 0.0, 0.0]),
                                  (np.diag([-1.0, 1.0, -1.0]), [0.0, 0.0, 1.0, 0.0]),
                                  (np.diag([-1.0, -1.0, 1.0]), [0.0, 0.0, 0.0, 1.0]),
                                  (np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),  # about x + y
                                   [0.0, np.sqrt(0.5), np.sqrt(0.5), 0.0])])
def test_half_turns_give_their_canonical_quaternion(R, q):
    np.testing.assert_allclose(quat.from_matrix(R), q, atol=1e-15)


@pytest.mark.parametrize("R", [-np.eye(3), np.diag([1.0, 1.0, -1.0]), np.zeros((3, 3)), 2.0 * np.eye(3),
                               np.full((3, 3), np.nan)], ids=["minus-I", "reflection", "zero", "scaled", "nan"])
def test_from_matrix_refuses_what_is_not_a_rotation(R):
    # -I (a reflection through the origin) came back as a half-turn about x, a zero matrix as the
    # identity: a rotation reported for something that is none
    with pytest.raises(ValueError, match="not a rotation matrix"):
        quat.from_matrix(R)
    with pytest.raises(ValueError, match="not a rotation matrix"):  # (in a stack too)
        quat.from_matrix(np.stack([np.eye(3), R]))


def test_poses_compare_by_value_and_hash_alike():
    # Pose was a dataclass with eq=False: two poses made alike were unequal (identity), and an
    # eq=True dataclass would have raised on its arrays ("truth value ... is ambiguous")
    from quatrack.tracking.pose import Pose

    a = Pose.from_rvec([0.1, -0.2, 0.3], [1.0, 2.0, 3.0])
    b = Pose.from_rvec([0.1, -0.2, 0.3], [1.0, 2.0, 3.0])
    assert a is not b and a == b and not (a != b) and hash(a) == hash(b)
    assert Pose(-a.q_wxyz, a.t) == a and hash(Pose(-a.q_wxyz, a.t)) == hash(a)  # q and −q: one rotation
    assert Pose.identity() == Pose([1.0, -0.0, 0.0, -0.0], [0.0, -0.0, 0.0])  # −0.0 == 0.0, and hashes alike
    assert hash(Pose.identity()) == hash(Pose([1.0, -0.0, 0.0, -0.0], [0.0, -0.0, 0.0]))
    c = Pose(a.q_wxyz, a.t + np.array([0.0, 0.0, 1e-12]))  # exact: no tolerance (allclose has one)
    assert c != a and c.allclose(a)
    assert a != a.as_matrix().tolist() and a != "pose"  # (other types: unequal, no error)
    assert len({a, b, Pose.identity()}) == 2 and {a: 1}[b] == 1

"""Prediction and error propagation (Ude eqs. 11–23) and the motion models of Kragic & Kyrki."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.integrate import simpson

from quatrack.tracking import quaternion as quat
from quatrack.tracking.motion import (
    CameraRandomWalk,
    LinearConstantVelocity,
    ObjectRandomWalk,
    UdeConstantVelocity,
    make_motion_model,
)
from quatrack.tracking.propagation import plant_noise, predict_mean, transition_jacobian
from quatrack.tracking.state import FilterState, initial_state


def tangent_error(a: FilterState, b: FilterState) -> np.ndarray:
    """``[p, δθ, v, ω]`` of ``a`` relative to ``b``, with ``q_a = exp(δθ/2) * q_b``."""
    dtheta = quat.to_rotvec(quat.multiply(a.q, quat.conjugate(b.q)))
    return np.concatenate([a.p - b.p, dtheta, a.v - b.v, a.omega - b.omega])


def perturb(s: FilterState, d: np.ndarray) -> FilterState:
    return s.replace(p=s.p + d[:3], q=quat.multiply(quat.from_rotvec(d[3:6]), s.q), v=s.v + d[6:9], omega=s.omega + d[9:])


def random_state(rng, omega_scale=1.0) -> FilterState:
    return FilterState(
        0.0,
        rng.normal(0, 100, 3) + [0, 0, 1000],
        quat.from_rotvec(rng.normal(0, 1, 3)),
        rng.normal(0, 50, 3),
        rng.normal(0, omega_scale, 3),
        np.eye(12),
    )


@given(seed=st.integers(0, 10_000), dt=st.floats(1e-3, 0.3))
def test_transition_jacobian_is_the_derivative_of_the_prediction(seed, dt):
    """Eq. 22 in full rotation-vector units: perturb the state, predict, compare."""
    rng = np.random.default_rng(seed)
    s = random_state(rng, omega_scale=2.0)
    model = UdeConstantVelocity()
    base = model.predict(s, dt)
    J = transition_jacobian(s.omega, dt)
    h = 1e-6
    num = np.column_stack(
        [
            (tangent_error(model.predict(perturb(s, h * e), dt), base) - tangent_error(model.predict(perturb(s, -h * e), dt), base)) / (2 * h)
            for e in np.eye(12)
        ]
    )
    np.testing.assert_allclose(J, num, atol=2e-6)


def test_half_angle_reading_of_G_would_be_wrong():
    """Ude's eq. 16 error u^q is half a rotation vector; the printed G (no ½) fits full ones."""
    s = FilterState(0.0, np.zeros(3), quat.IDENTITY, np.zeros(3), np.array([0.5, -0.2, 0.3]), np.eye(12))
    dt = 0.1
    model = UdeConstantVelocity()
    dw = np.array([0.0, 0.0, 1e-5])
    moved = model.predict(s.replace(omega=s.omega + dw), dt)
    dtheta = tangent_error(moved, model.predict(s, dt))[3:6]
    G = transition_jacobian(s.omega, dt)[3:6, 9:12]
    np.testing.assert_allclose(dtheta, G @ dw, rtol=1e-4)
    assert not np.allclose(0.5 * dtheta, G @ dw, rtol=1e-2)


def test_plant_noise_is_the_integral_of_white_acceleration():
    """Eq. 23: Q = ∫_0^Δt Φ(s) B Bᵀ Φ(s)ᵀ ds for white accelerations of densities a and α."""
    dt, a, alpha = 0.2, 3.0, 0.5
    s = np.linspace(0, dt, 2001)
    Q = np.zeros((12, 12))
    for k, (i, j) in zip((a, alpha), ((0, 6), (3, 9))):
        # a velocity kick at time dt - s moves the position by s·kick at dt
        Phi = np.zeros((len(s), 2, 1))
        Phi[:, 0, 0], Phi[:, 1, 0] = s, 1.0
        M = simpson(Phi @ np.swapaxes(Phi, 1, 2), x=s, axis=0) * k
        for (r, c), idx in zip([(0, 0), (0, 1), (1, 0), (1, 1)], [(i, i), (i, j), (j, i), (j, j)]):
            Q[idx[0] : idx[0] + 3, idx[1] : idx[1] + 3] = M[r, c] * np.eye(3)
    np.testing.assert_allclose(plant_noise(dt, a, alpha), Q, atol=1e-12)


def test_prediction_mean_is_exact_for_constant_velocity():
    rng = np.random.default_rng(2)
    s = random_state(rng)
    p, q, v, w = predict_mean(s.p, s.q, s.v, s.omega, 0.25)
    p2, q2, _, _ = predict_mean(*predict_mean(s.p, s.q, s.v, s.omega, 0.1)[:4], 0.15)
    np.testing.assert_allclose(p, p2, atol=1e-12)
    np.testing.assert_allclose(q, q2, atol=1e-14)  # exp(a ω/2) exp(b ω/2) = exp((a+b) ω/2)
    np.testing.assert_allclose(q, quat.multiply(quat.from_rotvec(0.25 * s.omega), s.q), atol=1e-14)


@pytest.mark.parametrize("name", ["ude", "m1", "m2", "m3"])
def test_models_share_one_interface(name):
    rng = np.random.default_rng(5)
    model = make_motion_model(name)
    s = random_state(rng)
    if not model.estimates_velocity:
        s = s.replace(v=np.zeros(3), omega=np.zeros(3))
    out = model.predict(s, 1 / 30)
    assert out.t == pytest.approx(1 / 30)
    assert abs(quat.norm(out.q) - 1) < 1e-15
    np.testing.assert_allclose(out.covariance, out.covariance.T, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(out.covariance) > -1e-9)
    # the pose covariance grows: in total for every model, and for the zeroth-order models (m1, m2:
    # the mean stays put, so the transition is the identity) by exactly their plant noise Q ⪰ 0
    grown = out.covariance[:6, :6] - s.covariance[:6, :6]
    assert np.trace(grown) > 0
    if not model.estimates_velocity:
        Q = model.process_covariance(1 / 30, s.p) if name == "m2" else model.process_covariance(1 / 30)
        np.testing.assert_allclose(grown, Q, atol=1e-12)
        assert np.linalg.eigvalsh(grown).min() > -1e-12 and np.trace(grown) > 1e-3
    still = model.predict(s, 0.0)
    np.testing.assert_allclose(still.p, s.p)
    np.testing.assert_allclose(still.covariance[:6, :6], s.covariance[:6, :6], atol=1e-12)
    with pytest.raises(ValueError, match="time step"):
        model.predict(s, -0.1)


def test_zeroth_order_models_do_not_move_the_pose():
    s = initial_state(0.0, [1, 2, 3], quat.from_rotvec([0.1, 0.2, 0.3]), np.eye(6))
    for model in (ObjectRandomWalk(), CameraRandomWalk()):
        out = model.predict(s, 0.5)
        np.testing.assert_array_equal(out.p, s.p)
        np.testing.assert_array_equal(out.q, s.q)
        assert not out.v.any() and not out.omega.any()
        assert not out.covariance[6:, :].any() and not out.covariance[:, 6:].any()


def test_model_1_noise_is_eq_5():
    m = ObjectRandomWalk(sigma_p2=4.0, sigma_phi2=0.01)
    s = initial_state(0.0, [0, 0, 100], quat.IDENTITY, np.zeros((6, 6)))
    np.testing.assert_allclose(m.predict(s, 0.5).covariance[:6, :6], np.diag([2.0] * 3 + [0.005] * 3))


def test_model_2_couples_position_to_camera_rotation():
    """A small camera rotation w moves the object to Exp(w) p: δp ≈ w × p (eqs. 6–9)."""
    rng = np.random.default_rng(11)
    p = np.array([100.0, -50.0, 800.0])
    m = CameraRandomWalk(sigma_p2=0.04, sigma_phi2=1e-6)
    dt = 0.5
    n = 200_000
    w = rng.normal(0, np.sqrt(m.sigma_phi2 * dt), size=(n, 3))
    w_p = rng.normal(0, np.sqrt(m.sigma_p2 * dt), size=(n, 3))
    from quatrack.tracking.rotation import rodrigues

    dp = np.einsum("nij,j->ni", rodrigues(w), p) - p + w_p
    emp = np.cov(np.hstack([dp, w]).T)
    # whitened by the model, the sample covariance is the identity up to sampling error (~1/√n)
    L = np.linalg.cholesky(np.linalg.inv(m.process_covariance(dt, p)))
    np.testing.assert_allclose(L.T @ emp @ L, np.eye(6), atol=0.015)
    # and the coupling is really there: without it, the whitened covariance is far from I
    Q_uncoupled = m.process_covariance(dt, p).copy()
    Q_uncoupled[:3, 3:] = Q_uncoupled[3:, :3] = 0.0
    L0 = np.linalg.cholesky(np.linalg.inv(Q_uncoupled))
    assert np.abs(L0.T @ emp @ L0 - np.eye(6)).max() > 0.5


def test_model_3_and_ude_differ_only_in_rotational_linearisation():
    rng = np.random.default_rng(4)
    s = random_state(rng)
    s = s.replace(covariance=np.cov(rng.normal(size=(12, 40))))
    ude, m3 = UdeConstantVelocity(a=1.0, alpha=0.1), LinearConstantVelocity(sigma_p2=1.0, sigma_phi2=0.1)
    a, b = ude.predict(s, 0.1), m3.predict(s, 0.1)
    np.testing.assert_allclose(a.q, b.q)
    np.testing.assert_allclose(a.covariance[:3, :3], b.covariance[:3, :3])
    assert not np.allclose(a.covariance[3:6, 3:6], b.covariance[3:6, 3:6])
    still = s.replace(omega=np.zeros(3))
    np.testing.assert_allclose(ude.predict(still, 0.1).covariance, m3.predict(still, 0.1).covariance, atol=1e-12)


def test_bad_model_names_and_parameters():
    with pytest.raises(ValueError, match="unknown motion model"):
        make_motion_model("m4")
    with pytest.raises(ValueError, match=">= 0"):
        make_motion_model("ude", a=-1.0)
    with pytest.raises(TypeError):
        make_motion_model("m1", a=1.0)

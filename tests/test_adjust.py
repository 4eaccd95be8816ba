"""The adjustment (Ude eqs. 24–30) and the filter: convergence, derivatives, honest covariances."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from quatrack.tracking import quaternion as quat
from quatrack.tracking.adjust import (
    AdjustOptions,
    SingularProblemError,
    _Problem,
    adjust,
    estimate_pose,
)
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.filter import PoseFilter
from quatrack.tracking.measurements import PointMeasurements, SegmentMeasurements
from quatrack.tracking.motion import make_motion_model
from quatrack.tracking.pose import Pose
from quatrack.tracking.rotation import rodrigues
from quatrack.tracking.state import FilterState, initial_state

CAM = PinholeCamera(800.0, 790.0, 320.0, 240.0, np.array([-0.1, 0.02, 0.001, 0.0005, 0.0]), 640, 480)
P_TRUE = np.array([12.0, -8.0, 600.0])
Q_TRUE = quat.from_rotvec([0.4, -0.3, 0.2])


def box_points(n=40, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-60, 60, size=(n, 3))


def observe(X, p=P_TRUE, q=Q_TRUE, cam=CAM, sigma=0.0, rng=None):
    uv = cam.project(X @ quat.to_matrix(q).T + p)
    if sigma:
        uv = uv + rng.normal(0, sigma, size=uv.shape)
    return uv


def pose_error(p, q, p_true=P_TRUE, q_true=Q_TRUE):
    """[δp, δθ] with q_true = exp(δθ/2) * q (the contract's convention)."""
    return np.concatenate([p_true - p, quat.to_rotvec(quat.multiply(q_true, quat.conjugate(q)))])


def prior_around(p, q, spread_p=20.0, spread_theta=0.1, t=0.0):
    S = np.diag([spread_p**2] * 3 + [spread_theta**2] * 3 + [1e4] * 3 + [1.0] * 3)
    return FilterState(t, p, q, np.zeros(3), np.zeros(3), S)


def stop_rule_tolerance(covariance: np.ndarray, p: np.ndarray, options: AdjustOptions = AdjustOptions()) -> float:
    """How far from the exact minimum the solver may stop, derived from its stop rule.

    Gauss–Newton stops once ``‖∇F‖ = ‖b‖ < ε`` (eq. 29, ``options.gradient_tolerance``). Near a
    zero-residual minimum ``F`` is quadratic with Hessian ``A = DᵀD``, so the remaining error is
    the Newton step ``A⁻¹b`` and ``‖[δp, δθ]‖ ≤ ‖A⁻¹‖₂ ‖b‖ < λ_max(Σ) ε`` with ``Σ = A⁻¹`` the
    returned covariance (eq. 30). A factor 2 covers the model's curvature beyond second order.
    Below that sits floating point: residuals and positions carry a relative error of a few
    ``eps`` of ``|p|``, amplified by at most ~10³ through the conditioning of the pose problem.
    A fixed 1e-7 (the earlier bound) was tighter than ε = 1e-5 guarantees: 7 of seeds 0–999 broke it.
    """
    lam_max = float(np.linalg.eigvalsh(covariance[:6, :6]).max())
    return 2.0 * lam_max * options.gradient_tolerance + 1e3 * np.finfo(float).eps * float(np.linalg.norm(p))


@given(seed=st.integers(0, 10_000))
def test_exact_measurements_converge_to_the_true_pose(seed):
    rng = np.random.default_rng(seed)
    X = box_points(seed=seed)
    block = PointMeasurements.create(CAM, X, observe(X), 1.0)
    p0 = P_TRUE + rng.normal(0, 10, 3)
    q0 = quat.multiply(quat.from_rotvec(rng.normal(0, 0.1, 3)), Q_TRUE)
    # a weak prior (1e8 variances) barely pulls: the measurements decide
    S = np.diag([1e8] * 12)
    res = adjust(FilterState(0.0, p0, q0, np.zeros(3), np.zeros(3), S), [block])
    assert res.converged
    err = np.linalg.norm(pose_error(res.state.p, res.state.q))
    assert err < stop_rule_tolerance(res.state.covariance, P_TRUE), err
    est = estimate_pose([block], p0, q0)
    assert est.converged
    err = np.linalg.norm(pose_error(est.p, est.q))
    assert err < stop_rule_tolerance(est.covariance, P_TRUE), err
    # q moves by exact unit quaternions (eq. 28): its norm drifts by a few eps per iteration
    assert abs(quat.norm(est.q) - 1.0) < 4 * (est.iterations + 1) * np.finfo(float).eps


def test_exact_segments_converge_to_the_true_pose():
    rng = np.random.default_rng(1)
    segs = rng.uniform(-60, 60, size=(8, 2, 3))
    uv = observe(segs.reshape(-1, 3)).reshape(-1, 2, 2)
    block = SegmentMeasurements.from_endpoints(CAM, segs, uv, 5.0, 1.0)
    est = estimate_pose([block], P_TRUE + [5, -5, 20], quat.multiply(quat.from_rotvec([0.05, 0, -0.05]), Q_TRUE))
    np.testing.assert_allclose(pose_error(est.p, est.q), 0.0, atol=1e-7)


@pytest.mark.parametrize("robust", ["none", "huber", "cauchy", "tukey"])
@pytest.mark.parametrize("velocity", [True, False])
def test_gradient_and_normal_matrix_match_finite_differences(robust, velocity):
    """∇F = Dᵀg and DᵀD against finite differences of F along the retraction (eq. 26)."""
    rng = np.random.default_rng(3)
    X = box_points(12)
    blocks = [
        PointMeasurements.create(CAM, X, observe(X, sigma=3.0, rng=rng), 1.5),
        SegmentMeasurements.from_endpoints(
            CAM, X[:6].reshape(3, 2, 3), observe(X[:6], sigma=1.0, rng=rng).reshape(3, 2, 2), 4.0, 1.0
        ),
    ]
    prior = prior_around(P_TRUE + [3, -2, 5], quat.multiply(quat.from_rotvec([0.02, 0.01, -0.03]), Q_TRUE))
    prior = prior.replace(v=np.array([1.0, 2.0, 3.0]), omega=np.array([0.1, -0.2, 0.05]))
    n = 12 if velocity else 6
    problem = _Problem(blocks, AdjustOptions(robust=robust), n, prior)
    x = (P_TRUE, Q_TRUE, np.array([0.5, 1.0, 2.0]), np.array([0.2, -0.1, 0.0]))
    F, A, b, _ = problem.evaluate(x)
    h = 1e-6
    num = np.array(
        [
            (problem.evaluate(problem.retract(x, h * e), False)[0] - problem.evaluate(problem.retract(x, -h * e), False)[0]) / (2 * h)
            for e in np.eye(n)
        ]
    )
    np.testing.assert_allclose(b, num, rtol=1e-5, atol=1e-5)
    if robust == "none":  # Gauss–Newton's DᵀD is the Hessian up to residual-curvature terms
        H = np.array(
            [
                [
                    (problem.evaluate(problem.retract(x, h * (ei + ej)), False)[0] - problem.evaluate(problem.retract(x, h * (ei - ej)), False)[0]
                     - problem.evaluate(problem.retract(x, h * (ej - ei)), False)[0] + problem.evaluate(problem.retract(x, -h * (ei + ej)), False)[0])
                    / (4 * h * h)
                    for ej in np.eye(n)
                ]
                for ei in np.eye(n)
            ]
        )
        assert np.abs(A - H).max() / np.abs(A).max() < 0.05


def test_covariance_is_honest():
    """Eq. 30: over many noise draws the estimates scatter as (DᵀD)⁻¹ says (NEES ≈ 6)."""
    rng = np.random.default_rng(42)
    X = box_points(25)
    sigma = 1.5
    nees, errs, covs = [], [], []
    for _ in range(400):
        block = PointMeasurements.create(CAM, X, observe(X, sigma=sigma, rng=rng), sigma)
        est = estimate_pose([block], P_TRUE, Q_TRUE)
        e = pose_error(est.p, est.q)
        nees.append(e @ np.linalg.solve(est.covariance, e))
        errs.append(e)
        covs.append(est.covariance)
    assert np.mean(nees) == pytest.approx(6.0, rel=0.12)
    emp = np.cov(np.array(errs).T)
    model = np.mean(covs, axis=0)
    # the rotation block is where a factor-2 angle convention slip would show (×4 in variance)
    np.testing.assert_allclose(np.diag(emp)[3:], np.diag(model)[3:], rtol=0.2)
    np.testing.assert_allclose(np.diag(emp)[:3], np.diag(model)[:3], rtol=0.2)


def test_prior_alone_returns_the_prior():
    prior = prior_around(P_TRUE, Q_TRUE)
    res = adjust(prior, [])
    np.testing.assert_allclose(res.state.p, prior.p)
    np.testing.assert_allclose(res.state.q, prior.q)
    np.testing.assert_allclose(res.state.covariance, prior.covariance, rtol=1e-9)
    assert res.iterations == 0


def test_posterior_combines_prior_and_measurements():
    """The linear-Gaussian case: information adds (eq. 30 with the prior rows of D)."""
    X = box_points(30)
    block = PointMeasurements.create(CAM, X, observe(X), 2.0)
    prior = prior_around(P_TRUE, Q_TRUE, spread_p=1.0, spread_theta=0.002)
    res = adjust(prior, [block], estimate_velocity=False)
    lin = block.linearize(P_TRUE, quat.to_matrix(Q_TRUE))
    J = lin.jacobian.reshape(-1, 6)
    expected = np.linalg.inv(J.T @ J + np.linalg.inv(prior.covariance[:6, :6]))
    np.testing.assert_allclose(res.state.covariance[:6, :6], expected, rtol=1e-6)
    assert not res.state.covariance[6:].any()


@pytest.mark.parametrize("loss", ["huber", "cauchy", "tukey"])
def test_robust_losses_resist_outliers(loss):
    rng = np.random.default_rng(8)
    X = box_points(60)
    uv = observe(X, sigma=1.0, rng=rng)
    bad = rng.choice(60, 12, replace=False)
    uv[bad] += rng.uniform(-80, 80, size=(12, 2))
    block = PointMeasurements.create(CAM, X, uv, 1.0)
    start = (P_TRUE + [2, -2, 5], quat.multiply(quat.from_rotvec([0.01, 0.02, 0.0]), Q_TRUE))
    good = np.setdiff1d(np.arange(60), bad)
    oracle = estimate_pose([PointMeasurements.create(CAM, X[good], uv[good], 1.0)], *start)
    plain = estimate_pose([block], *start)
    robust = estimate_pose([block], *start, AdjustOptions(robust=loss, max_iterations=50))

    def distance_to_oracle(est):
        """Mahalanobis distance² to the inlier-only estimate, in its covariance."""
        d = pose_error(est.p, est.q) - pose_error(oracle.p, oracle.q)
        return d @ np.linalg.solve(oracle.covariance, d)

    limit = 22.46  # χ²(6) at 99.9 %
    assert distance_to_oracle(plain) > limit  # the outliers do hurt a plain least-squares fit
    assert distance_to_oracle(robust) < limit
    w = robust.weights[0]
    assert w[bad].mean() < 0.3 * w[good].mean()


def test_levenberg_marquardt_converges_where_gauss_newton_is_fragile():
    rng = np.random.default_rng(5)
    X = box_points(30)
    block = PointMeasurements.create(CAM, X, observe(X, sigma=0.5, rng=rng), 0.5)
    far = (P_TRUE + [80, -60, 250], quat.multiply(quat.from_rotvec([0.5, -0.4, 0.3]), Q_TRUE))
    opts = AdjustOptions(method="levenberg-marquardt", max_iterations=100, record=True)
    prior = FilterState(0.0, far[0], far[1], np.zeros(3), np.zeros(3), np.diag([1e8] * 12))
    res = adjust(prior, [block], opts)
    assert res.converged
    costs = [r.cost for r in res.history] + [res.cost]
    assert all(b <= a + 1e-9 for a, b in zip(costs, costs[1:]))  # LM never goes uphill
    ref = estimate_pose([block], P_TRUE, Q_TRUE)
    np.testing.assert_allclose(res.state.p, ref.p, atol=1e-3)


def test_two_cameras_sum_their_information():
    X = box_points(20)
    right = PinholeCamera(800.0, 790.0, 320.0, 240.0, R_rig=rodrigues(np.array([0.0, -0.15, 0.0])), t_rig=np.array([-100.0, 0.0, 0.0]))
    X_ref = X @ quat.to_matrix(Q_TRUE).T + P_TRUE
    uv_r = right.project(X_ref @ right.R_rig.T + right.t_rig)
    left_block = PointMeasurements.create(CAM, X, observe(X), 1.0)
    right_block = PointMeasurements.create(right, X, uv_r, 1.0)
    start = (P_TRUE + [5, 5, 10], quat.multiply(quat.from_rotvec([0.03, 0, 0]), Q_TRUE))
    both = estimate_pose([left_block, right_block], *start)
    one = estimate_pose([left_block], *start)
    np.testing.assert_allclose(pose_error(both.p, both.q), 0.0, atol=1e-8)
    assert np.trace(both.covariance) < np.trace(one.covariance)
    # depth is what the second view adds most
    assert both.covariance[2, 2] < 0.5 * one.covariance[2, 2]


def test_underdetermined_problems_are_refused():
    with pytest.raises(SingularProblemError):
        estimate_pose([], P_TRUE, Q_TRUE)
    X = box_points(2)
    with pytest.raises(SingularProblemError):
        estimate_pose([PointMeasurements.create(CAM, X, observe(X), 1.0)], P_TRUE, Q_TRUE)


def test_estimate_pose_checks_its_starting_guess():
    # q0 = 0 came back as the answer (q = [0, 0, 0, 0]); q0 of norm 2 kept that norm through the
    # geodesic steps and ended ~7 diameters away; p0 of 2 numbers was a broadcasting error
    X = box_points(seed=1)
    block = PointMeasurements.create(CAM, X, observe(X), 1.0)
    unit = estimate_pose([block], P_TRUE + 5.0, Q_TRUE)
    twice = estimate_pose([block], P_TRUE + 5.0, 2.0 * Q_TRUE)
    assert twice.converged and np.allclose(twice.p, unit.p, atol=1e-9) and np.allclose(twice.q, unit.q, atol=1e-12)
    with pytest.raises(ValueError, match="q0 must be a non-zero quaternion"):
        estimate_pose([block], P_TRUE, [0.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="q0 must be"):
        estimate_pose([block], P_TRUE, Q_TRUE[:3])
    with pytest.raises(ValueError, match="p0 must be 3 finite numbers"):
        estimate_pose([block], P_TRUE[:2], Q_TRUE)
    with pytest.raises(ValueError, match="model points: .*3 columns"):  # (X and uv swapped: was read as other points)
        PointMeasurements.create(CAM, observe(X), X, 1.0)


def test_options_are_validated():
    with pytest.raises(ValueError, match="method"):
        AdjustOptions(method="newton")
    with pytest.raises(ValueError, match="robust"):
        AdjustOptions(robust="l1")


def simulate_motion(model_name, n=90, dt=1 / 30, sigma=0.5, seed=0):
    """Points on an object moving with constant v and ω, tracked by a filter."""
    rng = np.random.default_rng(seed)
    X = box_points(30, seed=seed)
    v_true, w_true = np.array([30.0, -20.0, 40.0]), np.array([0.3, -0.2, 0.4])
    params = {"ude": dict(a=10.0, alpha=0.01), "m3": dict(sigma_p2=10.0, sigma_phi2=0.01),
              "m1": dict(sigma_p2=400.0, sigma_phi2=0.05), "m2": dict(sigma_p2=400.0, sigma_phi2=0.05)}[model_name]
    f = PoseFilter(make_motion_model(model_name, **params))
    first = PointMeasurements.create(CAM, X, observe(X, sigma=sigma, rng=rng), sigma)
    est = estimate_pose([first], P_TRUE, Q_TRUE)
    f.initialize(0.0, est.pose, est.covariance)
    errs = []
    for k in range(1, n):
        t = k * dt
        p_t = P_TRUE + t * v_true
        q_t = quat.multiply(quat.from_rotvec(t * w_true), Q_TRUE)
        f.predict(t)
        block = PointMeasurements.create(CAM, X, observe(X, p_t, q_t, sigma=sigma, rng=rng), sigma)
        res = f.update([block])
        assert res.converged
        assert abs(quat.norm(res.state.q) - 1) < 1e-13
        errs.append((np.linalg.norm(res.state.p - p_t), np.degrees(quat.angle_between(res.state.q, q_t)),
                     np.linalg.norm(res.state.v - v_true), np.linalg.norm(res.state.omega - w_true)))
    return np.array(errs)


@pytest.mark.parametrize("name", ["ude", "m1", "m2", "m3"])
def test_every_motion_model_tracks(name):
    X = box_points(30)
    single = estimate_pose([PointMeasurements.create(CAM, X, observe(X), 0.5)], P_TRUE, Q_TRUE)
    sd_p = np.sqrt(np.trace(single.covariance[:3, :3]))  # one frame's RMS error (mm)
    sd_r = np.degrees(np.sqrt(np.trace(single.covariance[3:, 3:])))  # (deg)
    late = simulate_motion(name)[-30:].mean(axis=0)
    if name in ("ude", "m3"):  # constant velocity: filtering beats a single frame, velocities found
        assert late[0] < sd_p and late[1] < sd_r
        assert late[2] < 5.0  # mm/s, of 54 mm/s
        assert late[3] < 0.05  # rad/s, of 0.54 rad/s
    else:  # zeroth order: no worse than a single frame, with a margin for the lag
        assert late[0] < 1.5 * sd_p and late[1] < 1.5 * sd_r


def test_unit_norm_survives_without_renormalisation():
    """1000 predictions and geodesic updates: the quaternion stays on S³ to rounding."""
    X = box_points(10)
    f = PoseFilter(make_motion_model("ude", a=1.0, alpha=0.01))
    f.initialize(0.0, Pose(Q_TRUE, P_TRUE), np.diag([1.0] * 3 + [1e-4] * 3), velocity_variance=1.0)
    f.state = f.state.replace(omega=np.array([0.7, -0.4, 0.9]))
    rng = np.random.default_rng(0)
    for k in range(1, 1001):
        s = f.predict(k / 30)
        block = PointMeasurements.create(CAM, X, observe(X, s.p, s.q, sigma=0.3, rng=rng), 0.3)
        f.update([block])
    assert abs(quat.norm(f.state.q) - 1.0) < 1e-12


def test_filter_api_guards():
    f = PoseFilter(make_motion_model("ude"))
    with pytest.raises(RuntimeError, match="initialize"):
        f.predict(0.1)
    f.initialize(0.0, Pose(Q_TRUE, P_TRUE), np.eye(6))
    with pytest.raises(RuntimeError, match="predict"):
        f.update([])
    state = initial_state(0.0, P_TRUE, Q_TRUE, np.eye(6))
    assert state.covariance[6, 6] == 1e8 and state.pose_covariance.shape == (6, 6)
    # the estimate itself for its pose was AttributeError 't'; a 3×3 covariance numpy's broadcast error
    X = box_points(seed=2)
    est = estimate_pose([PointMeasurements.create(CAM, X, observe(X), 1.0)], P_TRUE, Q_TRUE)
    with pytest.raises(TypeError, match=r"pose: a Pose \(estimate_pose's result gives it as .pose\)"):
        f.initialize(0.0, est, est.covariance)
    with pytest.raises(ValueError, match="pose_covariance: 6×6"):
        f.initialize(0.0, est.pose, np.eye(3))
    f.initialize(0.0, est.pose, est.covariance)  # (an estimate's own: finite, symmetric, positive definite)


@pytest.mark.parametrize("bad, match", [
    (np.diag([1.0, 1.0, -1.0, 1.0, 1.0, 1.0]), "positive semi-definite"),  # a negative variance
    (np.eye(6) + np.triu(np.full((6, 6), 0.1), 1), "symmetric"),  # one triangle only
    (np.diag([1.0, 1.0, np.nan, 1.0, 1.0, 1.0]), "finite"),
    (np.full((6, 6), 1.0) - 2.0 * np.eye(6), "positive semi-definite"),  # symmetric, indefinite
])
def test_filter_refuses_a_pose_covariance_that_is_none(bad, match):
    # filtered on without a word before: its (DᵀD)⁻¹ and 1σ went NaN or negative later
    f = PoseFilter(make_motion_model("ude"))
    with pytest.raises(ValueError, match=f"pose_covariance must be {match}"):
        f.initialize(0.0, Pose(Q_TRUE, P_TRUE), bad)
    with pytest.raises(ValueError, match="velocity_variance"):
        f.initialize(0.0, Pose(Q_TRUE, P_TRUE), np.eye(6), velocity_variance=-1.0)
    f.initialize(0.0, Pose(Q_TRUE, P_TRUE), np.eye(6) + 1e-19 * np.triu(np.ones((6, 6)), 1))  # (rounding: taken)
    f.initialize(0.0, Pose(Q_TRUE, P_TRUE), np.zeros((6, 6)))  # (a pose taken as exact: allowed)


_unit_q = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 1e-3).map(
    lambda v: np.asarray(v) / np.linalg.norm(v))


@given(q=_unit_q, q_prior=_unit_q, tiny=st.sampled_from([0.0, 1e-12, 1e-9, 1e-6]))
def test_prior_rotation_matches_the_quaternion_functions(q, q_prior, tiny):
    """The prior's orientation residual and its Jacobian, written out on floats for speed
    (``_prior_rotation``), equal the vectorised quaternion functions' ``2 log(qc)`` and
    ``dlog(qc) R(qc)[:, 1:]`` with ``qc = canonical(q * conj(q̂))`` — also for ``q`` next to the
    prior (the small-angle limits) and on the other hemisphere."""
    from quatrack.tracking.adjust import _prior_rotation

    if tiny:  # q within a tiny rotation of the prior (and its antipode)
        q = quat.multiply(quat.exp(np.array([tiny, -0.5 * tiny, 0.3 * tiny])), q_prior) * (1 if tiny > 1e-9 else -1)
    qc = quat.canonical(quat.multiply(q, quat.conjugate(q_prior)))
    e, M = _prior_rotation(q, q_prior)
    np.testing.assert_allclose(e, 2.0 * quat.log(qc), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(M, quat.dlog(qc) @ quat.right_matrix(qc)[:, 1:], rtol=1e-12, atol=1e-15)
    assert _prior_rotation(q, q_prior, jacobian=False)[1] is None


@given(q=_unit_q, r=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3), scale=st.sampled_from([1.0, 1e-5, 1e-12, 0.0]))
def test_geodesic_step_matches_exp_times_q(q, r, scale):
    """Eq. 28's ``exp(Δθ/2) * q`` written out on floats (``_rotate_left``) equals the quaternion
    functions, down to a zero step."""
    from quatrack.tracking.adjust import _rotate_left

    d = np.asarray(r) * scale
    np.testing.assert_allclose(_rotate_left(d, q), quat.multiply(quat.exp(0.5 * d), q), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("robust", ["none", "huber"])
def test_gauss_newton_reports_the_cost_at_its_solution(robust):
    """Gauss–Newton computes the cost only once, at the end: it is eq. 24 at the returned state."""
    X = box_points(30, 4)
    rng = np.random.default_rng(4)
    blocks = [PointMeasurements.create(CAM, X, observe(X, sigma=0.8, rng=rng), 0.8)]
    prior = prior_around(P_TRUE + [3.0, -2.0, 10.0], quat.multiply(quat.from_rotvec([0.02, 0.0, -0.03]), Q_TRUE))
    options = AdjustOptions(robust=robust, max_iterations=3)
    result = adjust(prior, blocks, options)
    s = result.state
    F, _, _, _ = _Problem(blocks, options, 12, prior).evaluate((s.p, s.q, s.v, s.omega), False)
    assert result.cost == pytest.approx(F, rel=1e-12)
    recorded = adjust(prior, blocks, AdjustOptions(robust=robust, max_iterations=3, record=True))
    assert recorded.cost == pytest.approx(F, rel=1e-12)
    assert [r.cost for r in recorded.history][0] > F


def test_decrement_tolerance_is_validated():
    with pytest.raises(ValueError, match="decrement_tolerance"):
        AdjustOptions(decrement_tolerance=0.0)
    assert AdjustOptions(decrement_tolerance=1e-3).decrement_tolerance == 1e-3


@given(seed=st.integers(0, 10_000), robust=st.sampled_from(["none", "huber", "cauchy"]),
       tol=st.sampled_from([1e-1, 1e-2, 1e-3]))
def test_newton_decrement_stops_within_its_tolerance_of_the_minimum(seed, robust, tol):
    """The rule stops when the next step Δ has ΔᵀAΔ < tol. For least squares Δ is the Newton
    step, so the state returned lies within that squared Mahalanobis distance of the minimum
    (in the metric of the covariance it returns; 1.5·tol leaves room for the curvature beyond
    second order). With a robust loss, Gauss–Newton on the reweighted problem ignores how the
    weights change and converges only linearly, so the distance left can be a few times the
    last step (up to 2.3·tol over seeds 0–299 with Cauchy weights): 4·tol there."""
    rng = np.random.default_rng(seed)
    X = box_points(30, seed)
    sigma = 0.8
    blocks = [PointMeasurements.create(CAM, X, observe(X, sigma=sigma, rng=rng), sigma)]
    prior = prior_around(P_TRUE + rng.normal(0, 5, 3), quat.multiply(quat.from_rotvec(rng.normal(0, 0.03, 3)), Q_TRUE))
    exact = adjust(prior, blocks, AdjustOptions(robust=robust, max_iterations=50, gradient_tolerance=1e-12))
    early = adjust(prior, blocks, AdjustOptions(robust=robust, max_iterations=50, gradient_tolerance=1e-12,
                                                decrement_tolerance=tol))
    assert early.converged and early.iterations <= exact.iterations
    d = np.concatenate([pose_error(early.state.p, early.state.q, exact.state.p, exact.state.q),
                        exact.state.v - early.state.v, exact.state.omega - early.state.omega])
    m2 = float(d @ np.linalg.solve(early.state.covariance, d))
    assert m2 < (1.5 if robust == "none" else 4.0) * tol, (m2, tol)


def test_estimate_pose_names_a_measurement_that_is_not_finite():
    # a NaN image point (a lost track's, a failed undistortion) was "the measurements do not
    # constrain every estimated parameter": it names the block, the array and the row now, and is
    # still a SingularProblemError for callers that catch that
    from quatrack.tracking.adjust import NonFiniteMeasurementError

    X = box_points(seed=2)
    uv = observe(X)
    uv[3, 0] = np.nan
    with pytest.raises(NonFiniteMeasurementError, match=r"block 0 \(PointMeasurements\): its image_points .* \(row 3\)"):
        estimate_pose([PointMeasurements.create(CAM, X, uv, 1.0)], P_TRUE, Q_TRUE)
    X[5, 2] = np.inf
    with pytest.raises(SingularProblemError, match="model_points"):
        estimate_pose([PointMeasurements.create(CAM, X, observe(box_points(seed=2)), 1.0)], P_TRUE, Q_TRUE)

"""Adjustment of a predicted state to measurements (Ude 1999, Section 4, eqs. 24–30).

Minimises eq. 24 — the measurement terms plus the prior ``½ eᵀ Ŝ⁻¹ e`` with
``e = [p - p̂, δθ(q, q̂), v - v̂, ω - ω̂]`` — by Gauss–Newton directly on R³×S³×R³×R³: each
step solves for ``Δ = [Δp, Δθ, Δv, Δω]`` in the tangent space and moves the orientation along
the geodesic, ``q ← exp(Δθ/2) * q`` (eq. 28, with Ude's ``Δr = Δθ/2``). ``q`` stays on the unit
sphere by construction: it is never renormalised.

Ude writes the step with the stacked whitened residual ``g`` and its Jacobian ``D``:
``Δ = -(DᵀD)⁻¹ Dᵀ g`` (eq. 27). We accumulate ``DᵀD`` and ``Dᵀg`` block by block, which is the
same arithmetic without building ``D``. The iteration stops when ``‖∇F‖ = ‖Dᵀg‖ < ε``
(eq. 29), and the new covariance is ``(DᵀD)⁻¹`` at that point (eq. 30).

Options beyond the paper: Levenberg–Marquardt damping (his closing remark, for large
measurement noise), M-estimator weights (IRLS) against outliers, and a stop rule without units:
the Newton decrement ``λ² = ΔᵀAΔ`` of the next step (``AdjustOptions.decrement_tolerance``).
``‖∇F‖`` adds a gradient per unit of length to one per radian, so its ε means something
different for a mesh in mm and one in m; ``λ²`` measures the step in standard deviations of
the estimate itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np

from . import quaternion as quat
from . import robust
from .measurements import MeasurementBlock
from .pose import Pose
from .state import POSE_DIM, STATE_DIM, FilterState


@dataclass(frozen=True)
class AdjustOptions:
    """How to minimise eq. 24.

    ``gradient_tolerance`` is Ude's ε (eq. 29) on ``‖∇F‖``; ``robust_scale`` is in Mahalanobis
    units (``None``: a χ² quantile per block, see :mod:`tracking.robust`).
    """

    method: Literal["gauss-newton", "levenberg-marquardt"] = "gauss-newton"
    gradient_tolerance: float = 1e-5
    max_iterations: int = 20
    robust: robust.RobustLoss = "none"
    robust_scale: float | None = None
    damping: float = 1e-3  # Levenberg–Marquardt's initial λ (relative to diag(DᵀD))
    record: bool = False  # keep a per-iteration history (Ude's Table 1)
    # Gauss–Newton also stops, without taking it, when the next step's Newton decrement
    # λ² = −bᵀΔ = ΔᵀAΔ (the step's length in the metric of the current information, where 1 is
    # one standard deviation; Boyd & Vandenberghe, Convex Optimization, §9.5.1) is below this:
    # unlike ‖∇F‖ it has no unit (None: Ude's rule alone)
    decrement_tolerance: float | None = None

    def __post_init__(self) -> None:
        if self.method not in ("gauss-newton", "levenberg-marquardt"):
            raise ValueError(f"unknown method {self.method!r}")
        if self.robust not in robust.LOSSES:
            raise ValueError(f"unknown robust loss {self.robust!r}; expected one of {robust.LOSSES}")
        if self.max_iterations < 1 or not self.gradient_tolerance > 0:
            raise ValueError("max_iterations must be >= 1 and gradient_tolerance > 0")
        if self.decrement_tolerance is not None and not self.decrement_tolerance > 0:
            raise ValueError("decrement_tolerance must be > 0 (or None)")


@dataclass(frozen=True)
class IterationRecord:
    """One row of Ude's Table 1: step sizes, then ``‖∇F‖²`` *before* the step."""

    step_p: float
    step_theta: float  # ‖Δθ‖ = 2‖Δr‖ (full rotation angle, rad)
    step_v: float
    step_omega: float
    gradient_norm_sq: float
    cost: float


@dataclass(frozen=True)
class AdjustResult:
    state: FilterState
    iterations: int  # Gauss–Newton steps taken
    converged: bool  # ‖∇F‖ < ε reached
    gradient_norm: float
    cost: float  # F at the solution (eq. 24)
    weights: tuple[np.ndarray, ...]  # per block, per measurement (all 1 without a robust loss)
    history: tuple[IterationRecord, ...]
    final_gradient_norm_sq: float  # the last row of Table 1


@dataclass(frozen=True)
class PoseEstimate:
    """A pose from measurements alone: ``p``, ``q`` and the 6×6 covariance over ``[p, δθ]``."""

    p: np.ndarray
    q: np.ndarray
    covariance: np.ndarray
    iterations: int
    converged: bool
    gradient_norm: float
    cost: float
    weights: tuple[np.ndarray, ...]

    @property
    def pose(self) -> Pose:
        """``(q, p)`` as a :class:`~tracking.pose.Pose`."""
        return Pose(self.q, self.p)


class SingularProblemError(ValueError):
    """The measurements (and prior) do not constrain every estimated parameter."""


class NonFiniteMeasurementError(SingularProblemError):
    """A measurement holds a NaN or an infinity: nothing can be estimated from it. (A
    :class:`SingularProblemError`, which it was reported as — "the measurements do not constrain
    every estimated parameter" — so that callers catching that see no change.)"""


def _check_finite(blocks: Sequence[MeasurementBlock]) -> None:
    """:class:`NonFiniteMeasurementError` naming the first block and field (its arrays: points,
    segments, weights) holding a NaN or an infinity."""
    for i, block in enumerate(blocks):
        for name, value in getattr(block, "__dict__", {}).items():
            if isinstance(value, np.ndarray) and value.dtype.kind == "f" and not np.all(np.isfinite(value)):
                rows = np.flatnonzero(~np.isfinite(value.reshape(len(value), -1)).all(axis=1)) if value.ndim else []
                where = f" (row {int(rows[0])}{f' and {len(rows) - 1} more' if len(rows) > 1 else ''})" if len(rows) else ""
                raise NonFiniteMeasurementError(f"measurement block {i} ({type(block).__name__}): its {name} hold a NaN "
                                                f"or an infinity{where}")


def _scaled(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobi scaling ``A = D⁻¹ C D⁻¹``: pose variances (~1e-6) and velocity variances (~1e8)
    differ by 14 orders, far beyond what an unscaled solve keeps exact."""
    d = np.sqrt(np.diagonal(A))
    if not np.all(d > 0) or not np.all(np.isfinite(d)):
        raise SingularProblemError("the measurements do not constrain every estimated parameter")
    s = 1.0 / d
    return s, A * s[:, None] * s[None, :]


_MIN_PIVOT = 1e-12  # smallest Cholesky pivot² of the scaled matrix still called full rank


def _factor(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scaling and scaled matrix of an SPD ``A``, after checking it has full rank."""
    s, C = _scaled(A)
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError as exc:
        raise SingularProblemError("the measurements do not constrain every estimated parameter") from exc
    if np.min(np.diagonal(L)) ** 2 < _MIN_PIVOT:
        raise SingularProblemError("the measurements do not constrain every estimated parameter")
    return s, C


def spd_inverse(A: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive-definite matrix, solved in Jacobi-scaled form."""
    s, C = _factor(A)
    out = np.linalg.inv(C) * s[:, None] * s[None, :]
    return 0.5 * (out + out.T)


def _spd_solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    s, C = _factor(A)
    return s * np.linalg.solve(C, s * b)


def _prior_rotation(q: np.ndarray, q_prior: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """The prior's orientation residual ``e_θ = 2 log(qc)``, ``qc = canonical(q * conj(q̂))``, and
    its derivative ``∂e_θ/∂Δθ = dlog(qc) · R(qc)[:, 1:]`` (eq. A.1; equals ``J_l⁻¹``) for ONE pair
    of quaternions: :func:`quaternion.multiply`, :func:`~quaternion.canonical`,
    :func:`~quaternion.log`, :func:`~quaternion.dlog` and :func:`~quaternion.right_matrix` written
    out on Python floats (the adjustment asks for them at every iteration, and the vectorised
    functions' array overhead cost more than the arithmetic; tests/test_adjust.py checks them
    against each other)."""
    w1, x1, y1, z1 = q.tolist()
    w2, x2, y2, z2 = q_prior.tolist()
    # q * conj(q̂), conj(q̂) = (w2, -x2, -y2, -z2)
    w = w1 * w2 + (x1 * x2 + y1 * y2 + z1 * z2)
    x = -w1 * x2 + w2 * x1 + (-y1 * z2 + z1 * y2)
    y = -w1 * y2 + w2 * y1 + (-z1 * x2 + x1 * z2)
    z = -w1 * z2 + w2 * z1 + (-x1 * y2 + y1 * x2)
    lead = w if w != 0.0 else x if x != 0.0 else y if y != 0.0 else z
    if lead < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s2 = x * x + y * y + z * z
    s = math.sqrt(s2)
    small = s < quat._SMALL
    a = 1.0 / w if small and w > 0 else (math.atan2(s, w) / s if s != 0.0 else math.atan2(s, w))
    e = np.array([2.0 * (a * x), 2.0 * (a * y), 2.0 * (a * z)])
    if not jacobian:
        return e, None
    if small:  # dlog's limit (A.2); (w - a)/‖u‖² multiplies u uᵀ = O(‖u‖²)
        a_d, c = 1.0 / w, 0.0
    else:
        a_d, c = a, (w - a) / s2
    D = np.array([[-x, a_d + c * (x * x), c * (x * y), c * (x * z)],
                  [-y, c * (y * x), a_d + c * (y * y), c * (y * z)],
                  [-z, c * (z * x), c * (z * y), a_d + c * (z * z)]])
    Rq = np.array([[-x, -y, -z],
                   [w, z, -y],
                   [-z, w, x],
                   [y, -x, w]])
    return e, D @ Rq


def _rotate_left(dtheta: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``exp(Δθ/2) * q`` (eq. 28) for one rotation vector and quaternion, on Python floats
    (:func:`quaternion.exp` and :func:`~quaternion.multiply` for one pair cost ~25 µs)."""
    rx, ry, rz = (0.5 * dtheta).tolist()
    n = math.sqrt(rx * rx + ry * ry + rz * rz)
    c, k = math.cos(n), (math.sin(n) / n if n > 0.0 else 1.0)
    w1, x1, y1, z1 = c, k * rx, k * ry, k * rz
    w2, x2, y2, z2 = q.tolist()
    return np.array([w1 * w2 - (x1 * x2 + y1 * y2 + z1 * z2),
                     w1 * x2 + w2 * x1 + (y1 * z2 - z1 * y2),
                     w1 * y2 + w2 * y1 + (z1 * x2 - x1 * z2),
                     w1 * z2 + w2 * z1 + (x1 * y2 - y1 * x2)])


class _Problem:
    """Eq. 24 over ``n`` = 6 (pose) or 12 (pose and velocities) tangent coordinates."""

    def __init__(
        self,
        blocks: Sequence[MeasurementBlock],
        options: AdjustOptions,
        n: int,
        prior: FilterState | None,
    ) -> None:
        self.blocks = [b for b in blocks if len(b) > 0]
        self.options = options
        self.n = n
        self.prior = prior
        self.prior_info = None if prior is None else spd_inverse(prior.covariance[:n, :n])
        self.scales = [
            options.robust_scale if options.robust_scale is not None or options.robust == "none"
            else robust.default_scale(options.robust, b.dim)
            for b in self.blocks
        ]

    def evaluate(self, x, jacobian: bool = True, cost: bool = True):
        """Cost ``F``, and if asked ``A = DᵀD``, gradient ``b = Dᵀg`` and the robust weights.
        ``cost=False`` leaves ``F`` (None) for :meth:`last_cost` to compute when it is wanted:
        Gauss–Newton needs only the last one."""
        p, q = x[0], x[1]
        R = quat.to_matrix(q)
        n = self.n
        A = np.zeros((n, n)) if jacobian else None
        b = np.zeros(n) if jacobian else None
        all_w = []
        all_s2 = []
        loss = self.options.robust
        for block, scale in zip(self.blocks, self.scales):
            lin = block.linearize(p, R, jacobian)
            e = lin.residual
            s2 = np.einsum("ij,ij->i", e, e)
            all_s2.append(s2)
            if loss != "none":
                w = robust.weights(s2, loss, scale)
                all_w.append(w)
            else:
                w = None
                all_w.append(np.ones_like(s2))
            if jacobian:
                J = lin.jacobian
                if w is not None:
                    sw = np.sqrt(w)
                    e = e * sw[:, None]
                    J = J * sw[:, None, None]
                Jf = J.reshape(-1, POSE_DIM)
                A[:POSE_DIM, :POSE_DIM] += Jf.T @ Jf
                b[:POSE_DIM] += Jf.T @ e.reshape(-1)
        e_prior = Pe = None
        if self.prior is not None:
            e_prior, M = self._prior_terms(x, jacobian)
            Pe = self.prior_info @ e_prior
            if jacobian:
                # Jpᵀ Ŝ⁻¹ Jp and Jpᵀ Ŝ⁻¹ e with Jp the identity but for its orientation block M
                T = self.prior_info.copy()
                T[3:6, :] = M.T @ T[3:6, :]
                T[:, 3:6] = T[:, 3:6] @ M
                A += T
                g = Pe.copy()
                g[3:6] = M.T @ Pe[3:6]
                b += g
        self._last = (all_s2, e_prior, Pe)
        return (self.last_cost() if cost else None), A, b, tuple(all_w)

    def _prior_terms(self, x, jacobian: bool):
        """``e`` of the prior and the orientation block ``M`` of ``∂e/∂Δ`` (None without ``jacobian``)."""
        p, q, v, w = x
        pr = self.prior
        e = np.empty(self.n)
        e[0:3] = p - pr.p
        e_theta, M = _prior_rotation(q, pr.q, jacobian)
        e[3:6] = e_theta
        if self.n == STATE_DIM:
            e[6:9] = v - pr.v
            e[9:12] = w - pr.omega
        return e, M

    def last_cost(self) -> float:
        """``F`` (eq. 24) at the point of the last :meth:`evaluate`."""
        all_s2, e_prior, Pe = self._last
        loss = self.options.robust
        cost = 0.0
        for s2, scale in zip(all_s2, self.scales):
            cost += 0.5 * float(np.sum(s2 if loss == "none" else robust.rho(s2, loss, scale)))
        if e_prior is not None:
            cost += 0.5 * float(e_prior @ Pe)
        return cost

    def retract(self, x, delta):
        """Eq. 28: linear updates, and the geodesic ``q ← exp(Δθ/2) * q`` on S³."""
        p, q, v, w = x
        q_new = _rotate_left(delta[3:6], q)
        if self.n == STATE_DIM:
            return p + delta[0:3], q_new, v + delta[6:9], w + delta[9:12]
        return p + delta[0:3], q_new, v, w


def _record(delta: np.ndarray, g2: float, cost: float) -> IterationRecord:
    n = lambda s: float(np.linalg.norm(delta[s])) if delta.size > s.start else 0.0  # noqa: E731
    return IterationRecord(n(slice(0, 3)), n(slice(3, 6)), n(slice(6, 9)), n(slice(9, 12)), g2, cost)


def _minimise(problem: _Problem, x, options: AdjustOptions):
    history: list[IterationRecord] = []
    lam = options.damping
    gn = options.method == "gauss-newton"
    need_cost = not gn or options.record  # Gauss–Newton needs only the final cost
    cost, A, b, w = problem.evaluate(x, cost=need_cost)
    iterations = 0
    small_step = False
    while True:
        g2 = float(b @ b)
        if g2 < options.gradient_tolerance**2 or iterations >= options.max_iterations:
            break
        if gn:
            delta = -_spd_solve(A, b)
            if options.decrement_tolerance is not None and -float(b @ delta) < options.decrement_tolerance:
                small_step = True  # x is the minimum to within a small share of a standard deviation
                break
            x_new = problem.retract(x, delta)
            if options.record:
                history.append(_record(delta, g2, cost))
            x = x_new
            cost, A, b, w = problem.evaluate(x, cost=need_cost)
        else:  # Levenberg–Marquardt: damp until the cost goes down
            diag = np.diagonal(A)
            while lam <= 1e12:
                delta = -_spd_solve(A + lam * np.diag(diag), b)
                x_new = problem.retract(x, delta)
                if problem.evaluate(x_new, jacobian=False)[0] <= cost:
                    lam = max(lam / 10.0, 1e-12)
                    break
                lam *= 10.0
            else:  # no step lowers the cost: x is a minimum to working precision
                break
            if options.record:
                history.append(_record(delta, g2, cost))
            x = x_new
            cost, A, b, w = problem.evaluate(x)
        iterations += 1
    converged = small_step or float(b @ b) < options.gradient_tolerance**2
    if cost is None:
        cost = problem.last_cost()
    return x, cost, A, b, w, iterations, converged, tuple(history)


def adjust(
    prior: FilterState,
    blocks: Sequence[MeasurementBlock],
    options: AdjustOptions = AdjustOptions(),
    estimate_velocity: bool = True,
) -> AdjustResult:
    """The state at ``prior.t`` most consistent with the prediction ``prior`` and ``blocks``.

    ``estimate_velocity=False`` (zeroth-order motion models) solves for the pose only and keeps
    ``v = ω = 0``. Raises :class:`SingularProblemError` if the problem is not determined.
    """
    n = STATE_DIM if estimate_velocity else POSE_DIM
    problem = _Problem(blocks, options, n, prior)
    x0 = (prior.p.copy(), prior.q.copy(), prior.v.copy(), prior.omega.copy())
    x, cost, A, b, w, iterations, converged, history = _minimise(problem, x0, options)
    S = np.zeros((STATE_DIM, STATE_DIM))
    S[:n, :n] = spd_inverse(A)  # eq. 30
    state = FilterState(prior.t, x[0], x[1], x[2], x[3], S)
    return AdjustResult(
        state, iterations, converged, float(np.sqrt(b @ b)), cost, w, history, float(b @ b)
    )


def _start(p0, q0) -> tuple[np.ndarray, np.ndarray]:
    """``estimate_pose``'s guess, checked: a zero quaternion came back as the answer (q = 0), one of
    another norm kept it (the geodesic steps preserve the norm) and led the fit astray; p0 of
    another length was a broadcasting error. A unit ``q0`` (to 1e-9) is used as given."""
    p = np.asarray(p0, dtype=float)
    q = np.asarray(q0, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"p0 must be 3 finite numbers, got {np.asarray(p0).tolist()!r}"[:120])
    n = float(np.linalg.norm(q)) if q.shape == (4,) and np.all(np.isfinite(q)) else 0.0
    if not n > 1e-12:
        raise ValueError(f"q0 must be a non-zero quaternion [w, x, y, z], got {np.asarray(q0).tolist()!r}"[:120])
    return p, (q if abs(n - 1.0) <= 1e-9 else q / n)


def estimate_pose(
    blocks: Sequence[MeasurementBlock],
    p0: np.ndarray,
    q0: np.ndarray,
    options: AdjustOptions = AdjustOptions(),
) -> PoseEstimate:
    """The pose minimising the measurement terms of eq. 24 alone, from a starting guess.

    Its covariance ``(DᵀD)⁻¹`` initialises the filter (Ude, Section 5).
    """
    p0, q0 = _start(p0, q0)
    _check_finite(blocks)
    problem = _Problem(blocks, options, POSE_DIM, None)
    x0 = (p0, q0, np.zeros(3), np.zeros(3))
    x, cost, A, b, w, iterations, converged, _ = _minimise(problem, x0, options)
    return PoseEstimate(x[0], x[1], spd_inverse(A), iterations, converged, float(np.sqrt(b @ b)), cost, w)

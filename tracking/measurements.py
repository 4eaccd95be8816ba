"""Measurement models: the ``g_jk(p, q)`` of Ude's eq. 24 as residual blocks with covariances.

A block compares image features to the projection of model features at a pose
``X_cam = R X_obj + p``. It returns *whitened* residuals ``e = W (g(x) - y)`` with
``WᵀW = Σ⁻¹``, so that ``½‖e‖²`` is the block's term of eq. 24, and their Jacobian with respect
to the left pose perturbation ``[δp, δθ]``: ``p ← p + δp``, ``R ← Exp(δθ) R`` (``δθ`` a full
rotation vector, the contract's convention). Blocks are independent of the motion model.

Residual rows are grouped per measurement (a point: 2 rows; a segment: 3), so robust weights
and gating act on whole measurements.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .camera import PinholeCamera
from .jit import lazily_compiled
from .rotation import cross


@dataclass(frozen=True)
class Linearization:
    """Whitened residuals ``(n, d)`` and their Jacobian ``(n, d, 6)`` over ``[δp, δθ]``."""

    residual: np.ndarray
    jacobian: np.ndarray | None


class MeasurementBlock(Protocol):
    """What the adjustment needs from a set of measurements."""

    dim: int  # residual rows per measurement

    def __len__(self) -> int: ...

    def linearize(self, p: np.ndarray, R: np.ndarray, jacobian: bool = True) -> Linearization: ...


def project_model_points(
    camera: PinholeCamera, X_obj: np.ndarray, p: np.ndarray, R: np.ndarray, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Pixels ``(n, 2)`` of object points at pose ``(R, p)`` and ``∂uv/∂[δp, δθ]`` ``(n, 2, 6)``.

    ``X_cam = R_rig (R X + p) + t_rig``; ``∂X_cam/∂δp = R_rig``, ``∂X_cam/∂δθ = -R_rig X(R X)``.
    """
    RX = X_obj @ R.T
    X_ref = RX + p
    if camera.is_reference and not camera.has_distortion:
        return _project_pinhole(camera, RX, X_ref, jacobian)
    X_cam = X_ref if camera.is_reference else X_ref @ camera.R_rig.T + camera.t_rig
    uv, Jx = camera.project_with_jacobian(X_cam, jacobian)
    if not jacobian:
        return uv, None
    if not camera.is_reference:
        Jx = Jx @ camera.R_rig
    J = np.empty(Jx.shape[:-1] + (6,))
    J[..., :3] = Jx
    # row · (-X(a)) == a × row, for each of the two rows
    J[..., 3:] = cross(RX[:, None, :], Jx)
    return uv, J


def _project_pinhole(camera: PinholeCamera, RX: np.ndarray, X: np.ndarray, jacobian: bool):
    """:func:`project_model_points` for the reference camera without distortion, written out:
    ``u = fx x/z + cx``, ``v = fy y/z + cy``; ``∂uv/∂δp`` has the rows ``(fx/z, 0, −fx x/z²)``
    and ``(0, fy/z, −fy y/z²)``, and ``∂uv/∂δθ`` row by row ``RX × row`` (the general path's
    arithmetic without its products by zero; tests/test_measurements.py compares them)."""
    iz = 1.0 / X[:, 2]
    x = X[:, 0] * iz
    y = X[:, 1] * iz
    uv = np.empty((len(X), 2))
    uv[:, 0] = camera.fx * x + camera.cx
    uv[:, 1] = camera.fy * y + camera.cy
    if not jacobian:
        return uv, None
    a0, a1, a2 = RX[:, 0], RX[:, 1], RX[:, 2]
    u0 = camera.fx * iz
    u2 = -camera.fx * x * iz
    v1 = camera.fy * iz
    v2 = -camera.fy * y * iz
    J = np.zeros((len(X), 2, 6))
    J[:, 0, 0] = u0
    J[:, 0, 2] = u2
    J[:, 1, 1] = v1
    J[:, 1, 2] = v2
    # a × (u0, 0, u2) and a × (0, v1, v2)
    J[:, 0, 3] = a1 * u2
    J[:, 0, 4] = a2 * u0 - a0 * u2
    J[:, 0, 5] = -(a1 * u0)
    J[:, 1, 3] = a1 * v2 - a2 * v1
    J[:, 1, 4] = -(a0 * v2)
    J[:, 1, 5] = a0 * v1
    return uv, J


def sqrt_information(covariance: np.ndarray) -> np.ndarray:
    """``W`` with ``WᵀW = Σ⁻¹`` for stacked covariances ``(n, d, d)`` (upper-triangular).

    For ``d = 2`` in closed form (numpy's batched ``inv`` and ``cholesky`` cost more in call
    overhead than the arithmetic): ``Σ⁻¹ = [[d, −b], [−b, a]] / (ad − b²)`` for ``Σ = [[a, b], [b, d]]``,
    and its Cholesky factor ``L = [[√i₀₀, 0], [i₁₀/√i₀₀, √(i₁₁ − i₁₀²/i₀₀)]]``, ``W = Lᵀ``."""
    cov = np.asarray(covariance, dtype=float)
    if cov.ndim == 3 and cov.shape[1:] == (2, 2):
        a, b, d = cov[:, 0, 0], 0.5 * (cov[:, 0, 1] + cov[:, 1, 0]), cov[:, 1, 1]
        det = a * d - b * b
        with np.errstate(divide="ignore", invalid="ignore"):
            i00, i10, i11 = d / det, -b / det, a / det
            l00 = np.sqrt(i00)
            l10 = i10 / l00
            l11 = np.sqrt(i11 - l10 * l10)
        if not (np.all(det > 0) and np.all(a > 0) and np.all(np.isfinite(l00)) and np.all(np.isfinite(l11))
                and np.all(l11 > 0)):
            raise np.linalg.LinAlgError("a covariance is not positive definite")
        W = np.zeros_like(cov)
        W[:, 0, 0], W[:, 0, 1], W[:, 1, 1] = l00, l10, l11
        return W
    info = np.linalg.inv(cov)
    L = np.linalg.cholesky(info)  # info = L Lᵀ  ⇒  W = Lᵀ
    return np.swapaxes(L, -1, -2)


def _whiten(W: np.ndarray, e: np.ndarray, J: np.ndarray | None) -> Linearization:
    """``W e`` and ``W J`` per measurement; for 2×2 ``W`` written out (a batched 2×2 product in
    numpy costs several times the arithmetic)."""
    if W.shape[1:] == (2, 2):
        w00, w01, w10, w11 = W[:, 0, 0, None], W[:, 0, 1, None], W[:, 1, 0, None], W[:, 1, 1, None]
        e_w = np.empty_like(e)
        e_w[:, 0] = w00[:, 0] * e[:, 0] + w01[:, 0] * e[:, 1]
        e_w[:, 1] = w10[:, 0] * e[:, 0] + w11[:, 0] * e[:, 1]
        if J is None:
            return Linearization(e_w, None)
        J_w = np.empty_like(J)
        J_w[:, 0] = w00 * J[:, 0] + w01 * J[:, 1]
        J_w[:, 1] = w10 * J[:, 0] + w11 * J[:, 1]
        return Linearization(e_w, J_w)
    e_w = np.einsum("nij,nj->ni", W, e)
    return Linearization(e_w, None if J is None else W @ J)


@dataclass(frozen=True)
class PointMeasurements:
    """Image points ``(n, 2)`` of model points ``(n, 3)`` (object frame) seen by one camera."""

    camera: PinholeCamera
    model_points: np.ndarray
    image_points: np.ndarray
    sqrt_info: np.ndarray  # (n, 2, 2)
    dim: int = 2

    @classmethod
    def create(
        cls,
        camera: PinholeCamera,
        model_points: np.ndarray,
        image_points: np.ndarray,
        covariance: np.ndarray | float = 1.0,
    ) -> "PointMeasurements":
        """``covariance``: a pixel standard deviation (scalar), or per-point 2×2 matrices (n, 2, 2)."""
        X = np.asarray(model_points, dtype=float)
        y = np.asarray(image_points, dtype=float)
        # (an (n, 2) array of model points, or image points of 3 columns — the two swapped — was
        # reshaped into other points without a word)
        if X.ndim > 2 or (X.ndim == 2 and X.shape[1] != 3):
            raise ValueError(f"model points: an (n, 3) array, got shape {X.shape} (not 3 columns)")
        if y.ndim > 2 or (y.ndim == 2 and y.shape[1] != 2):
            raise ValueError(f"image points: an (n, 2) array, got shape {y.shape} (not 2 columns)")
        X, y = X.reshape(-1, 3), y.reshape(-1, 2)
        if X.shape[0] != y.shape[0]:
            raise ValueError(f"{X.shape[0]} model points but {y.shape[0]} image points")
        if np.isscalar(covariance) or np.ndim(covariance) == 0:
            sigma = float(covariance)
            if not sigma > 0:
                raise ValueError("point standard deviation must be positive")
            W = np.broadcast_to(np.eye(2) / sigma, (X.shape[0], 2, 2)).copy()
        else:
            W = sqrt_information(np.broadcast_to(covariance, (X.shape[0], 2, 2)))
        return cls(camera, X, y, W)

    def __len__(self) -> int:
        return self.model_points.shape[0]

    def linearize(self, p: np.ndarray, R: np.ndarray, jacobian: bool = True) -> Linearization:
        cam = self.camera
        if cam.is_reference and not cam.has_distortion and len(self) and self.sqrt_info.shape[1:] == (2, 2):
            # the adjustment's inner loop (~10 times a tracked frame): the two functions below
            # in one compiled pass, the same bits (tests/test_measurements.py)
            RX = self.model_points @ R.T
            e = np.empty((len(self), 2))
            J = np.empty((len(self), 2, 6)) if jacobian else np.empty((0, 2, 6))
            _compiled_linearize()(RX, RX + p, cam.fx, cam.fy, cam.cx, cam.cy, self.sqrt_info, self.image_points,
                                  jacobian, e, J)
            return Linearization(e, J if jacobian else None)
        uv, J = project_model_points(cam, self.model_points, p, R, jacobian)
        return _whiten(self.sqrt_info, uv - self.image_points, J)


def _linearize_pinhole(RX, X, fx, fy, cx, cy, W, y, jacobian, e_out, J_out):  # pragma: no cover (compiled)
    """:func:`_project_pinhole` then :func:`_whiten` (2×2 ``W``) for one point at a time,
    compiled (:func:`quatrack.tracking.jit.lazily_compiled`): whitened residuals into ``e_out``
    (n, 2) and, with ``jacobian``, their Jacobian into ``J_out`` (n, 2, 6). Each expression is
    the numpy one's, in its order, zeros of the Jacobian included, so the results are the same
    bits; numpy's dozens of whole-array operations on a few hundred points cost ~10× more."""
    for i in range(X.shape[0]):
        iz = 1.0 / X[i, 2]
        x = X[i, 0] * iz
        yy = X[i, 1] * iz
        e0 = (fx * x + cx) - y[i, 0]
        e1 = (fy * yy + cy) - y[i, 1]
        w00, w01, w10, w11 = W[i, 0, 0], W[i, 0, 1], W[i, 1, 0], W[i, 1, 1]
        e_out[i, 0] = w00 * e0 + w01 * e1
        e_out[i, 1] = w10 * e0 + w11 * e1
        if not jacobian:
            continue
        a0, a1, a2 = RX[i, 0], RX[i, 1], RX[i, 2]
        u0 = fx * iz
        u2 = -fx * x * iz
        v1 = fy * iz
        v2 = -fy * yy * iz
        r0 = (u0, 0.0, u2, a1 * u2, a2 * u0 - a0 * u2, -(a1 * u0))
        r1 = (0.0, v1, v2, a1 * v2 - a2 * v1, -(a0 * v2), a0 * v1)
        for k in range(6):
            J_out[i, 0, k] = w00 * r0[k] + w01 * r1[k]
            J_out[i, 1, k] = w10 * r0[k] + w11 * r1[k]


_compiled_linearize = lazily_compiled(_linearize_pinhole)


def wrap_half_turn(a: np.ndarray) -> np.ndarray:
    """Angle difference of undirected lines, wrapped to ``[-π/2, π/2)``."""
    return (np.asarray(a) + 0.5 * np.pi) % np.pi - 0.5 * np.pi


def reduced_midpoint(endpoints: np.ndarray) -> np.ndarray:
    """Segments ``(n, 2, 2)`` → reduced mid-point parameters ``(n, 3)``: ``[x_m, y_m, θ]``."""
    e = np.asarray(endpoints, dtype=float)
    mid = 0.5 * (e[:, 0] + e[:, 1])
    d = e[:, 1] - e[:, 0]
    return np.column_stack([mid, np.arctan2(d[:, 1], d[:, 0])])


def segment_covariance(endpoints: np.ndarray, sigma_along: float, sigma_across: float) -> np.ndarray:
    """Deriche–Faugeras (1990) covariance ``(n, 3, 3)`` of ``[x_m, y_m, θ]`` for noisy end points.

    Each end point has independent noise ``σ∥`` along the segment and ``σ⊥`` across it. To first
    order the mid-point has ``σ∥²/2`` along and ``σ⊥²/2`` across, the angle ``2σ⊥²/l²`` (``l`` the
    length), and the angle is uncorrelated with the mid-point.
    """
    e = np.asarray(endpoints, dtype=float)
    d = e[:, 1] - e[:, 0]
    length = np.linalg.norm(d, axis=-1)
    if np.any(length <= 0):
        raise ValueError("degenerate segment: both end points coincide")
    c, s = d[:, 0] / length, d[:, 1] / length
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # columns: along, across
    local = np.diag([0.5 * sigma_along**2, 0.5 * sigma_across**2])
    cov = np.zeros((e.shape[0], 3, 3))
    cov[:, :2, :2] = rot @ local @ np.swapaxes(rot, -1, -2)
    cov[:, 2, 2] = 2.0 * sigma_across**2 / length**2
    return cov


@dataclass(frozen=True)
class SegmentMeasurements:
    """Image line segments of model edges, in Ude's reduced mid-point form ``[x_m, y_m, θ]``.

    ``model_segments`` ``(n, 2, 3)``: the edge's two end points in the object frame. The model
    side is the mid-point and angle of the *projected* end points (not the projected 3-D
    mid-point), which is what a detected segment's mid-point measures. Angles compare as
    undirected lines.
    """

    camera: PinholeCamera
    model_segments: np.ndarray
    measured: np.ndarray  # (n, 3)
    sqrt_info: np.ndarray  # (n, 3, 3)
    dim: int = 3

    @classmethod
    def from_endpoints(
        cls,
        camera: PinholeCamera,
        model_segments: np.ndarray,
        image_endpoints: np.ndarray,
        sigma_along: float,
        sigma_across: float,
    ) -> "SegmentMeasurements":
        """Measured end points ``(n, 2, 2)`` with the Deriche–Faugeras covariance."""
        S = np.asarray(model_segments, dtype=float).reshape(-1, 2, 3)
        E = np.asarray(image_endpoints, dtype=float).reshape(-1, 2, 2)
        if S.shape[0] != E.shape[0]:
            raise ValueError(f"{S.shape[0]} model segments but {E.shape[0]} image segments")
        cov = segment_covariance(E, sigma_along, sigma_across)
        return cls(camera, S, reduced_midpoint(E), sqrt_information(cov))

    def __len__(self) -> int:
        return self.model_segments.shape[0]

    def predict(self, p: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Predicted ``[x_m, y_m, θ]`` ``(n, 3)`` at a pose."""
        uv, _ = project_model_points(self.camera, self.model_segments.reshape(-1, 3), p, R, False)
        return reduced_midpoint(uv.reshape(-1, 2, 2))

    def linearize(self, p: np.ndarray, R: np.ndarray, jacobian: bool = True) -> Linearization:
        n = len(self)
        uv, J = project_model_points(self.camera, self.model_segments.reshape(-1, 3), p, R, jacobian)
        uv = uv.reshape(n, 2, 2)
        d = uv[:, 1] - uv[:, 0]
        e = np.empty((n, 3))
        e[:, :2] = 0.5 * (uv[:, 0] + uv[:, 1]) - self.measured[:, :2]
        e[:, 2] = wrap_half_turn(np.arctan2(d[:, 1], d[:, 0]) - self.measured[:, 2])
        if not jacobian:
            return _whiten(self.sqrt_info, e, None)
        J = J.reshape(n, 2, 2, 6)
        G = np.empty((n, 3, 6))
        G[:, :2] = 0.5 * (J[:, 0] + J[:, 1])
        dJ = J[:, 1] - J[:, 0]  # ∂d/∂δ, (n, 2, 6)
        l2 = np.sum(d * d, axis=-1)
        # θ = atan2(d_y, d_x): ∂θ/∂d = [-d_y, d_x] / ‖d‖²
        G[:, 2] = (-d[:, 1, None] * dJ[:, 0] + d[:, 0, None] * dJ[:, 1]) / l2[:, None]
        return _whiten(self.sqrt_info, e, G)

"""Rotation matrices and rotation vectors (SO(3)), the matrix side of Ude (1999), eqs. 18–21.

A *rotation vector* ``phi`` (radians) is a full rotation: angle ``‖phi‖`` about ``phi/‖phi‖``.
``rodrigues(phi)`` is ``Exp(phi)``; the left Jacobian ``J_l(phi) = ∫_0^1 Exp(s·phi) ds`` is what
Ude's ``G_i`` (eq. 21) is, scaled by Δt. Everything is vectorised over leading axes.
"""

from __future__ import annotations

import numpy as np

_SMALL = 1e-6  # below this angle (rad) the closed forms lose digits: use Taylor series


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` over leading axes; component-wise because ``np.cross`` costs ~50 µs a call."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``X(v)`` of eq. 18: ``skew(v) @ w == cross(v, w)``. Shape (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    out[..., 0, 1], out[..., 0, 2] = -z, y
    out[..., 1, 0], out[..., 1, 2] = z, -x
    out[..., 2, 0], out[..., 2, 1] = -y, x
    return out


def _angle_coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sin θ/θ``, ``(1-cos θ)/θ²`` and ``(θ - sin θ)/θ³``, exact to double precision near 0.

    ``1 - cos θ`` is computed as ``2 sin²(θ/2)`` (no cancellation at any θ). ``θ - sin θ``
    cancels (relative error ~6ε/θ²), so below θ = 0.1 a Taylor series to θ⁸ replaces it: both
    stay within ~1e-13 relative (``1 - cos θ`` directly lost 5 digits at θ = 2.5e-6).
    """
    small = theta < _SMALL
    t = np.where(small, 1.0, theta)
    t2 = t * t
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, 2.0 * np.sin(0.5 * t) ** 2 / t2)
    th2 = theta * theta
    series = 1.0 / 6.0 + th2 * (-1.0 / 120.0 + th2 * (1.0 / 5040.0 + th2 * (-1.0 / 362880.0 + th2 / 39916800.0)))
    tc = np.where(theta < 0.1, 1.0, theta)
    c = np.where(theta < 0.1, series, (tc - np.sin(tc)) / (tc * tc * tc))
    return a, b, c


def rodrigues(phi: np.ndarray) -> np.ndarray:
    """``Exp(phi)``: the rotation matrix of a full rotation vector (Rodrigues' formula, eq. 18).

    ``R = I + sin θ X(n) + (1 - cos θ) X(n)²`` with ``θ = ‖phi‖``, ``n = phi/θ``.
    """
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    a, b, _ = _angle_coefficients(theta)
    K = skew(phi)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """``J_l(phi) = ∫_0^1 Exp(s·phi) ds``, so that ``Exp(phi + d) ≈ Exp(J_l(phi) d) Exp(phi)``.

    Ude's eq. 21 is ``G_i = Δt · J_l(Δt ω_i)``: ``J_l = (sin θ/θ) I + (1-cos θ)/θ² X(phi) +
    (θ - sin θ)/θ³ X(phi)²``, which equals his ``(1-c) n nᵀ + c I + s X(n)``.
    """
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    _, b, c = _angle_coefficients(theta)
    K = skew(phi)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + b[..., None, None] * K + c[..., None, None] * (K @ K)


def left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """``J_l(phi)⁻¹``: how ``Log(Exp(d) Exp(phi))`` moves with a small left increment ``d``.

    ``J_l⁻¹ = I - X(phi)/2 + (1/θ² - (1 + cos θ)/(2 θ sin θ)) X(phi)²``; valid for ``θ < 2π``.
    ``(1 + cos θ)/sin θ`` is computed as ``cot(θ/2)``, which stays exact at the half-turn.
    """
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < _SMALL
    t = np.where(small, 1.0, theta)
    coeff = np.where(small, 1.0 / 12.0 + theta**2 / 720.0, 1.0 / t**2 - 1.0 / (2.0 * t * np.tan(0.5 * t)))
    K = skew(phi)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye - 0.5 * K + coeff[..., None, None] * (K @ K)

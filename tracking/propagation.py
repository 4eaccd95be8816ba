"""Prediction and error propagation on R³×S³ (Ude 1999, eqs. 11–23).

Orientation errors are full rotation vectors ``δθ`` (``q_true = exp(δθ/2) * q``). In these units
Ude's ``J_i`` (eq. 22) and plant noise (eq. 23) hold as printed: ``G_i`` integrates ``R(tω)``
against an angular-velocity error, which yields a full rotation vector (not Ude's half-angle
``u^q`` of eq. 16, for which ``G_i`` would need a factor ½).
"""

from __future__ import annotations

import numpy as np

from . import quaternion as quat
from .rotation import left_jacobian, rodrigues


def predict_mean(
    p: np.ndarray, q: np.ndarray, v: np.ndarray, omega: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eqs. 11–14: ``p + dt v``, ``exp(dt ω/2) * q``, ``v``, ``ω`` (exact for zero acceleration)."""
    return p + dt * v, quat.multiply(quat.exp(0.5 * dt * omega), q), v.copy(), omega.copy()


def orientation_gain(omega: np.ndarray, dt: float) -> np.ndarray:
    """``G_i = ∫_0^Δt R(tω) dt = Δt J_l(Δt ω)`` (eq. 21): how an ω error turns into ``δθ``."""
    return dt * left_jacobian(dt * np.asarray(omega, dtype=float))


def transition_jacobian(omega: np.ndarray, dt: float) -> np.ndarray:
    """``J_i`` of eq. 22: the 12×12 map of errors ``[p, δθ, v, ω]`` from ``t_i`` to ``t_{i+1}``."""
    J = np.eye(12)
    J[0:3, 6:9] = dt * np.eye(3)
    J[3:6, 3:6] = rodrigues(dt * np.asarray(omega, dtype=float))
    J[3:6, 9:12] = orientation_gain(omega, dt)
    return J


def plant_noise(dt: float, a: float, alpha: float) -> np.ndarray:
    """Eq. 23's second term: covariance added by random accelerations of spectral density
    ``a`` ((mesh unit)²/s³) and ``alpha`` (rad²/s³) over ``dt`` seconds."""
    Q = np.zeros((12, 12))
    for k, (i, j) in zip((a, alpha), ((0, 6), (3, 9))):
        Q[i : i + 3, i : i + 3] = (k * dt**3 / 3.0) * np.eye(3)
        Q[i : i + 3, j : j + 3] = Q[j : j + 3, i : i + 3] = (k * dt**2 / 2.0) * np.eye(3)
        Q[j : j + 3, j : j + 3] = (k * dt) * np.eye(3)
    return Q

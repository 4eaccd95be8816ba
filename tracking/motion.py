"""Motion models behind one interface: Ude's constant velocity on R³×S³ and Kragic & Kyrki's
Models 1–3.

A model predicts a :class:`FilterState` ``dt`` seconds ahead (mean and covariance). The
adjustment is the same for all of them: the prediction becomes the prior of eq. 24.

- ``ude``: constant velocity on R³×S³ (Ude 1999, eqs. 11–14, 22, 23), random accelerations with
  spectral densities ``a`` (mesh units²/s³) and ``alpha`` (rad²/s³).
- ``m1``: Kragic & Kyrki's Model 1, zeroth order, the object turning about its own origin:
  ``p`` and ``δθ`` random walks, ``Q1 = dt·diag(σp² I, σφ² I)`` (their eq. 5).
- ``m2``: Model 2, zeroth order, the *camera* turning about its centre, so a rotation ``w`` of
  the view moves the object's position too: ``δp = w × p``, ``δθ = w`` (their eqs. 6–9).
- ``m3``: Model 3, constant velocity, *linear*: ``F = [[I, dt I], [0, I]]`` on
  ``[pose, rates]`` (their eq. 10) with their ``Q3`` (eq. 11, the same matrix as Ude's plant noise).
  Unlike ``ude`` it ignores how the orientation error rotates with ``ω`` (``R(dt ω)``, ``G``).

Zeroth-order models do not estimate velocities: their state keeps ``v = ω = 0`` with zero
covariance, and the adjustment solves for the pose only (``estimates_velocity = False``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from .propagation import plant_noise, predict_mean, transition_jacobian
from .rotation import skew
from .state import FilterState


class MotionModel(Protocol):
    name: ClassVar[str]
    estimates_velocity: ClassVar[bool]

    def predict(self, state: FilterState, dt: float) -> FilterState: ...


def _check_dt(dt: float) -> float:
    dt = float(dt)
    if not np.isfinite(dt) or dt < 0.0:
        raise ValueError(f"time step must be finite and non-negative, got {dt}")
    return dt


def _check_positive(**params: float) -> None:
    for key, value in params.items():
        if not (np.isfinite(value) and value >= 0.0):
            raise ValueError(f"motion-model parameter {key} must be finite and >= 0, got {value}")


@dataclass(frozen=True)
class UdeConstantVelocity:
    """Ude (1999): constant velocity on R³×S³ with random-acceleration plant noise (eq. 2)."""

    a: float = 2.0
    alpha: float = 0.0002
    name: ClassVar[str] = "ude"
    estimates_velocity: ClassVar[bool] = True

    def __post_init__(self) -> None:
        _check_positive(a=self.a, alpha=self.alpha)

    def predict(self, state: FilterState, dt: float) -> FilterState:
        dt = _check_dt(dt)
        p, q, v, w = predict_mean(state.p, state.q, state.v, state.omega, dt)
        J = transition_jacobian(state.omega, dt)
        S = J @ state.covariance @ J.T + plant_noise(dt, self.a, self.alpha)
        return FilterState(state.t + dt, p, q, v, w, 0.5 * (S + S.T))


def _zeroth_order(state: FilterState, dt: float, Q6: np.ndarray) -> FilterState:
    S = np.zeros((12, 12))
    S[:6, :6] = state.covariance[:6, :6] + Q6
    return FilterState(state.t + dt, state.p.copy(), state.q.copy(), np.zeros(3), np.zeros(3), S)


@dataclass(frozen=True)
class ObjectRandomWalk:
    """Kragic & Kyrki Model 1: random walk of the pose about the object's origin."""

    sigma_p2: float = 1.0  # mesh units²/s
    sigma_phi2: float = 0.01  # rad²/s
    name: ClassVar[str] = "m1"
    estimates_velocity: ClassVar[bool] = False

    def __post_init__(self) -> None:
        _check_positive(sigma_p2=self.sigma_p2, sigma_phi2=self.sigma_phi2)

    def process_covariance(self, dt: float) -> np.ndarray:
        """``Q1(dt)`` (eq. 5)."""
        return dt * np.diag([self.sigma_p2] * 3 + [self.sigma_phi2] * 3)

    def predict(self, state: FilterState, dt: float) -> FilterState:
        dt = _check_dt(dt)
        return _zeroth_order(state, dt, self.process_covariance(dt))


@dataclass(frozen=True)
class CameraRandomWalk:
    """Kragic & Kyrki Model 2: random walk of the camera, rotating about the camera centre."""

    sigma_p2: float = 1.0  # mesh units²/s
    sigma_phi2: float = 0.01  # rad²/s
    name: ClassVar[str] = "m2"
    estimates_velocity: ClassVar[bool] = False

    def __post_init__(self) -> None:
        _check_positive(sigma_p2=self.sigma_p2, sigma_phi2=self.sigma_phi2)

    def process_covariance(self, dt: float, p: np.ndarray) -> np.ndarray:
        """``Q2`` (eq. 9) with ``A = -X(p)`` (eq. 8), so that ``A w = w × p``.

        With ``δθ = w`` (our sign) the cross term is ``+dt σφ² A``; the paper writes
        ``φ = -w`` and so prints ``-dt σφ² A``: the same physical model.
        """
        A = -skew(p)
        Q = np.zeros((6, 6))
        Q[:3, :3] = dt * self.sigma_p2 * np.eye(3) + dt * self.sigma_phi2 * (A @ A.T)
        Q[:3, 3:] = dt * self.sigma_phi2 * A
        Q[3:, :3] = Q[:3, 3:].T
        Q[3:, 3:] = dt * self.sigma_phi2 * np.eye(3)
        return Q

    def predict(self, state: FilterState, dt: float) -> FilterState:
        dt = _check_dt(dt)
        return _zeroth_order(state, dt, self.process_covariance(dt, state.p))


@dataclass(frozen=True)
class LinearConstantVelocity:
    """Kragic & Kyrki Model 3: constant velocity, linear in the incremental angles."""

    sigma_p2: float = 2.0  # mesh units²/s³
    sigma_phi2: float = 0.0002  # rad²/s³
    name: ClassVar[str] = "m3"
    estimates_velocity: ClassVar[bool] = True

    def __post_init__(self) -> None:
        _check_positive(sigma_p2=self.sigma_p2, sigma_phi2=self.sigma_phi2)

    def predict(self, state: FilterState, dt: float) -> FilterState:
        dt = _check_dt(dt)
        p, q, v, w = predict_mean(state.p, state.q, state.v, state.omega, dt)
        F = np.eye(12)
        F[0:3, 6:9] = F[3:6, 9:12] = dt * np.eye(3)
        S = F @ state.covariance @ F.T + plant_noise(dt, self.sigma_p2, self.sigma_phi2)
        return FilterState(state.t + dt, p, q, v, w, 0.5 * (S + S.T))


MOTION_MODELS: dict[str, type] = {
    cls.name: cls
    for cls in (UdeConstantVelocity, ObjectRandomWalk, CameraRandomWalk, LinearConstantVelocity)
}


def make_motion_model(name: str, **params: float) -> MotionModel:
    """The model called ``name`` (``ude``, ``m1``, ``m2``, ``m3``) with its noise parameters."""
    try:
        cls = MOTION_MODELS[name]
    except KeyError:
        raise ValueError(f"unknown motion model {name!r}; expected one of {sorted(MOTION_MODELS)}") from None
    return cls(**params)


# Ude's transition Jacobian, re-exported for users who compose their own model.
__all__ = [
    "MotionModel",
    "UdeConstantVelocity",
    "ObjectRandomWalk",
    "CameraRandomWalk",
    "LinearConstantVelocity",
    "MOTION_MODELS",
    "make_motion_model",
    "transition_jacobian",
]

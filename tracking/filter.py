"""The pose filter: predict and adjust kept apart (in the manner of filterpy).

    f = PoseFilter(UdeConstantVelocity(a=2.0, alpha=2e-4))
    f.initialize(t0, pose, pose_covariance)       # a Pose; velocities unknown: variance 1e8
    for t, blocks in frames:
        f.predict(t)                                # eqs. 11–14 and 22–23 (or another model)
        result = f.update(blocks)                   # eqs. 24–30

The pure functions underneath are ``model.predict(state, dt)`` and
:func:`tracking.adjust.adjust`; this class only keeps the current state and the last prior.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .adjust import AdjustOptions, AdjustResult, adjust
from .measurements import MeasurementBlock
from .motion import MotionModel
from .pose import Pose
from .state import FilterState, initial_state


class PoseFilter:
    """Quaternion pose filter with a pluggable motion model and measurement blocks."""

    def __init__(self, motion: MotionModel, options: AdjustOptions = AdjustOptions()) -> None:
        self.motion = motion
        self.options = options
        self.state: FilterState | None = None
        self.prior: FilterState | None = None  # the last prediction

    def initialize(
        self,
        t: float,
        pose: Pose,
        pose_covariance: np.ndarray,
        velocity_variance: float = 1e8,
    ) -> FilterState:
        """Start from a pose estimate (covariance 6×6 over ``[p, δθ]``); velocities zero, with
        variance ``velocity_variance`` (and not estimated by zeroth-order models)."""
        if not isinstance(pose, Pose):  # (an estimate itself, a (t, q) pair: AttributeError 't')
            raise TypeError(f"pose: a Pose (estimate_pose's result gives it as .pose), got {type(pose).__name__}")
        if np.shape(pose_covariance) != (6, 6):  # (numpy's "could not broadcast input array" before)
            raise ValueError(f"pose_covariance: 6×6 over [p, δθ], got shape {np.shape(pose_covariance)}")
        _check_covariance(np.asarray(pose_covariance, dtype=float))
        if not (np.isfinite(velocity_variance) and velocity_variance >= 0.0):
            raise ValueError(f"velocity_variance must be finite and ≥ 0, got {velocity_variance!r}")
        state = initial_state(t, pose.t, pose.q_wxyz, pose_covariance, velocity_variance=velocity_variance)
        if not self.motion.estimates_velocity:
            state.covariance[6:, 6:] = 0.0
        self.state, self.prior = state, None
        return state

    def _require_state(self) -> FilterState:
        if self.state is None:
            raise RuntimeError("the filter has no state: call initialize() first")
        return self.state

    def predict(self, t: float) -> FilterState:
        """Predict the state at time ``t`` (s); it becomes the prior of the next :meth:`update`."""
        state = self._require_state()
        self.prior = self.motion.predict(state, t - state.t)
        self.state = self.prior
        return self.prior

    def update(self, blocks: Sequence[MeasurementBlock]) -> AdjustResult:
        """Adjust the last prediction to the measurements (eq. 24) and keep the result."""
        if self.prior is None:
            raise RuntimeError("update() needs a prediction: call predict(t) first")
        result = adjust(self.prior, blocks, self.options, self.motion.estimates_velocity)
        self.state = result.state
        return result


def _check_covariance(C: np.ndarray) -> None:
    """ValueError unless ``C`` is a covariance: finite, symmetric and positive semi-definite
    (within rounding: 1e-9 of its largest entry). One with a negative variance, or standard
    deviations where variances belong, was filtered on without a word: its (DᵀD)⁻¹ and 1σ NaN."""
    if not np.all(np.isfinite(C)):
        raise ValueError("pose_covariance must be finite")
    scale = float(np.abs(C).max())
    if np.abs(C - C.T).max() > 1e-9 * scale:
        raise ValueError("pose_covariance must be symmetric")
    lowest = float(np.linalg.eigvalsh(0.5 * (C + C.T)).min())
    if lowest < -1e-9 * scale:
        raise ValueError(f"pose_covariance must be positive semi-definite (an eigenvalue is {lowest:.3g})")

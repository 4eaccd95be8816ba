"""The filter's state: pose, velocities and their covariance at one time instant."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from . import quaternion as quat
from .pose import Pose

STATE_DIM = 12  # [p, δθ, v, ω]
POSE_DIM = 6  # [p, δθ]


@dataclass(frozen=True)
class FilterState:
    """Object pose and velocity at time ``t`` (s), with a 12×12 covariance.

    - ``p`` (3,): object origin in the camera frame, mesh units (``X_cam = R(q) X_obj + p``).
    - ``q`` (4,): unit quaternion ``[w, x, y, z]``, object → camera.
    - ``v`` (3,): ``dp/dt``, mesh units/s, camera frame.
    - ``omega`` (3,): angular velocity, rad/s, camera frame: ``q(t+dt) = exp(dt·ω/2) * q(t)``.
    - ``covariance`` (12, 12): over ``[p, δθ, v, ω]`` with ``q_true = exp(δθ/2) * q``
      (``δθ`` a full rotation vector, radians).
    """

    t: float
    p: np.ndarray
    q: np.ndarray
    v: np.ndarray
    omega: np.ndarray
    covariance: np.ndarray

    @cached_property
    def R(self) -> np.ndarray:
        """Rotation matrix of ``q``, read-only (computed once: a step asks for it ~30 times)."""
        R = quat.to_matrix(self.q)
        R.setflags(write=False)
        return R

    @cached_property
    def pose(self) -> Pose:
        """``(q, p)`` as the project's :class:`~tracking.pose.Pose` (canonical quaternion),
        computed once (a state's ``p`` and ``q`` are never changed in place)."""
        return Pose(self.q, self.p)

    @property
    def pose_covariance(self) -> np.ndarray:
        """6×6 covariance over ``[p, δθ]`` (ROS ``PoseWithCovariance`` order)."""
        return self.covariance[:POSE_DIM, :POSE_DIM]

    def replace(self, **changes) -> "FilterState":
        return replace(self, **changes)


def initial_state(
    t: float,
    p: np.ndarray,
    q: np.ndarray,
    pose_covariance: np.ndarray,
    v: np.ndarray | None = None,
    omega: np.ndarray | None = None,
    velocity_variance: float = 1e8,
) -> FilterState:
    """A state from a pose estimate: unknown velocities get zero mean and a large variance.

    Ude (1999, Section 5) starts with zero velocities whose variances are 1e8.
    """
    cov = np.zeros((STATE_DIM, STATE_DIM))
    cov[:POSE_DIM, :POSE_DIM] = np.asarray(pose_covariance, dtype=float)
    cov[POSE_DIM:, POSE_DIM:] = velocity_variance * np.eye(6)
    return FilterState(
        t=float(t),
        p=np.asarray(p, dtype=float).copy(),
        q=np.asarray(q, dtype=float).copy(),
        v=np.zeros(3) if v is None else np.asarray(v, dtype=float).copy(),
        omega=np.zeros(3) if omega is None else np.asarray(omega, dtype=float).copy(),
        covariance=cov,
    )

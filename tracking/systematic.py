"""The systematic floor of a reported pose covariance: what the filter's own covariance leaves out.

The filter (eq. 24/30) treats every measured point and edge sample as an independent error. Their
errors share causes it does not model: points born on the mesh at a pose that was itself a little
off carry that pose's error together, an edge locks onto the print beside the outline along its
whole length, KLT on a blurred or re-lit patch slides the same way for all its neighbours. Such
a shared error does not average out over hundreds of measurements, so the posterior of 200
points claims an accuracy no tracker of a real image has: on the rendered zoo walks (six shapes,
mm/cm/m, ground truth) the filter's own 6-dof NEES had a median of 18–82 on the textured objects
(≈ 5.3 is honest) and its 95 % ellipsoid held the truth in 6–30 % of the frames
(bench/RESULTS.md, "Honest covariances").

The floor models the shared error as one error of the whole pose, independent of the number of
measurements: a displacement of the object's centre ``Δc`` with standard deviation ``a·d``
across the line of sight and ``r·a·d`` along it (``d`` the diameter: free of units; monocular
depth is the weak direction), and a rotation error ``δθ`` of ``b`` radians about every axis.
In the state's coordinates ``[p, δθ]`` (``X_cam = R X + p``, ``q_true = exp(δθ/2) * q``) a
rotation about the centre moves the origin: ``Δp = Δc + [R c]ₓ δθ`` (``c`` the centre in the
object frame), so with ``T = [[I, [R c]ₓ], [0, I]]``

    floor = T · blockdiag(Σ_c, b² I₃) · Tᵀ,   Σ_c = (a d)² (I₃ + (r² − 1) ẑ ẑᵀ),

``ẑ`` the unit line of sight to the centre. The reported covariance is the filter's plus the
floor (independent errors add); the filter itself keeps its own for its gates and weights.
"""

from __future__ import annotations

import numpy as np

from .rotation import skew


def systematic_floor(R: np.ndarray, p: np.ndarray, centre: np.ndarray, diameter: float, lateral: float,
                     depth_ratio: float, angle_rad: float) -> np.ndarray:
    """The 6×6 floor over ``[p, δθ]`` for a pose ``(R, p)`` (see the module): the centre's error
    ``lateral·diameter`` across the line of sight, ``depth_ratio`` times that along it, and
    ``angle_rad`` about every axis.

    A pure shift of the centre (no rotation error) is a pure shift of the origin:

    >>> F = systematic_floor(np.eye(3), np.array([0.0, 0.0, 5.0]), np.zeros(3), 1.0, 0.01, 3.0, 0.0)
    >>> np.round(np.sqrt(np.diag(F)), 3)
    array([0.01, 0.01, 0.03, 0.  , 0.  , 0.  ])

    A rotation about the centre, which lies 1 unit along x of the origin, moves the origin
    (``Δp = [R c]ₓ δθ``: a turn about z by ``+δθ`` shifts it by ``−δθ`` along y):

    >>> F = systematic_floor(np.eye(3), np.array([-1.0, 0.0, 5.0]), np.array([1.0, 0.0, 0.0]), 1.0, 0.0, 1.0, 0.1)
    >>> float(np.round(F[1, 5], 3)), float(np.round(F[1, 1], 3))
    (-0.01, 0.01)
    """
    R = np.asarray(R, float)
    Rc = R @ np.asarray(centre, float)
    c_cam = Rc + np.asarray(p, float)
    n = np.linalg.norm(c_cam)
    z = c_cam / n if n > 0 else np.array([0.0, 0.0, 1.0])
    S = np.zeros((6, 6))
    S[:3, :3] = (lateral * diameter) ** 2 * (np.eye(3) + (depth_ratio**2 - 1.0) * np.outer(z, z))
    S[3:, 3:] = angle_rad**2 * np.eye(3)
    T = np.eye(6)
    T[:3, 3:] = skew(Rc)
    return T @ S @ T.T


def carried_covariance(R: np.ndarray, R_birth: np.ndarray, cov_birth: np.ndarray) -> np.ndarray:
    """The covariance over ``[p, δθ]`` at the pose ``R`` of an error the track has carried, fixed to
    the object, since a birth at the pose ``R_birth`` with covariance ``cov_birth``.

    A track re-found on its own keyframes and carried by points lifted at its own poses keeps its
    birth error as an error of the object's points: ``X → X + u + ω × X`` (object frame). With
    ``X_cam = R X + p`` and ``q_true = exp(δθ/2) * q`` that is ``δp = R u`` and ``δθ = R ω`` at any
    pose, so with ``B = blockdiag(R R_bᵀ, R R_bᵀ)``

        carried = B · cov_birth · Bᵀ.

    At the birth pose it is the birth covariance; it turns with the object:

    >>> C = np.diag([1.0, 0.0, 0.0, 0.0, 0.0, 4.0])
    >>> Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90° about z
    >>> np.diag(carried_covariance(Rz, np.eye(3), C))
    array([0., 1., 0., 0., 0., 4.])
    """
    A = np.asarray(R, float) @ np.asarray(R_birth, float).T
    B = np.zeros((6, 6))
    B[:3, :3] = B[3:, 3:] = A
    return B @ np.asarray(cov_birth, float) @ B.T

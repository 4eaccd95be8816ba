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

A shared error is also an error *in the image*: the outline and the texture of the whole object
off by the same fraction of a pixel. What that does to the pose depends on the object's shape
and on where it stands, which a pose-level floor cannot know: a tall box's or a cylinder's turn
about its long axis moves its points only across its narrow width, and a far object's depth only
shows as a change of its apparent size. :func:`image_floor` is the pose error of ``s`` pixels
shared by every point of the object: the covariance of a pose fitted to the object's own points
with independent errors of ``s`` px, times their number (one shared error does not average out),
``s² (mean_i J_iᵀ J_i)⁻¹``. The tracker reports the filter's covariance plus both floors.
"""

from __future__ import annotations

import numpy as np

from .camera import PinholeCamera
from .measurements import project_model_points
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


def image_floor(camera: PinholeCamera, R: np.ndarray, p: np.ndarray, points: np.ndarray, sigma_px: float) -> np.ndarray:
    """The 6×6 floor over ``[p, δθ]`` of an image error of ``sigma_px`` pixels shared by the object's
    ``points`` (object frame, e.g. its mesh's vertices) at the pose ``(R, p)``:

        floor = s² · (1/n Σᵢ Jᵢᵀ Jᵢ)⁻¹,   Jᵢ = ∂π(R Xᵢ + p)/∂[p, δθ]  (2×6),

    the covariance of a pose fitted to the ``n`` points' pixels with independent errors of ``s``
    px, times ``n`` (the error is one error: it does not average out over the points). Why: see
    the module. Free of units (pixels in, the pose's own units out), it grows with the distance
    (across the line of sight as ``z``, along it as ``z²`` — depth shows only as a change of
    size) and about the axes round which the object is narrow. Zeros when the points do not
    determine a pose (fewer than three, all on one ray).

    A flat square of side 2 seen face-on 10 units away by a camera of focal length 500, with a
    shared error of 0.5 px: along the line of sight the centre is known to ``s·z²/(f·ρ)``, ``ρ``
    the corners' RMS distance from the centre (√2), and the turn about the line of sight to
    ``s·z/(f·ρ)`` rad; across it, to more than one point's ``s·z/f`` = 0.01 (a shift and a tilt
    of a flat object look alike):

    >>> from quatrack.tracking.camera import PinholeCamera
    >>> cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, np.zeros(5), width=640, height=480)
    >>> X = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    >>> sd = np.sqrt(np.diag(image_floor(cam, np.eye(3), np.array([0.0, 0.0, 10.0]), X, 0.5)))
    >>> [round(float(v), 6) for v in (sd[2], 0.5 * 10**2 / (500 * np.sqrt(2)), sd[5], 0.5 * 10 / (500 * np.sqrt(2)))]
    [0.070711, 0.070711, 0.007071, 0.007071]
    >>> bool(sd[0] > 0.01)
    True
    """
    R, p = np.asarray(R, float), np.asarray(p, float)
    X = np.asarray(points, float)
    X = X[(X @ R[2] + p[2]) > 0]  # (in front of the camera)
    if len(X) < 3:
        return np.zeros((6, 6))
    _, J = project_model_points(camera, X, p, R, True)
    A = np.einsum("nki,nkj->ij", J, J) / len(X)
    try:
        return sigma_px**2 * np.linalg.inv(A)
    except np.linalg.LinAlgError:  # (the points do not determine a pose: no floor of this kind)
        return np.zeros((6, 6))


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

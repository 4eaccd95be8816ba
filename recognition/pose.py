"""Initial pose from 2-D/3-D matches: RANSAC PnP, refinement, covariance and verification.

RANSAC (OpenCV) finds a consensus; the refinement is the project's own Levenberg–Marquardt on
the inliers (:func:`quatrack.tracking.adjust.estimate_pose`), whose ``(DᵀD)⁻¹`` scaled by the
residual variance is the pose covariance over ``[p, δθ]`` (contract conventions). A pose is
*verified* before anyone is told the object was found.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.adjust import AdjustOptions, SingularProblemError, estimate_pose
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.measurements import PointMeasurements


@dataclass(frozen=True)
class PoseParams:
    """RANSAC and verification thresholds (pixels of the query image)."""

    ransac_px: float = 6.0
    ransac_iterations: int = 1000
    ransac_confidence: float = 0.999
    inlier_px: float = 4.0  # after refinement, a match within this is an inlier
    min_inliers: int = 12
    min_inlier_ratio: float = 0.15
    max_rms_px: float = 2.5
    min_visible_fraction: float = 0.5  # of the object's projected box inside the image
    min_window_iou: float = 0.25  # projected box vs the localised window, when there is one
    min_facing: float = 0.9  # share of inliers whose surface faces the camera at the pose
    planar_ratio: float = 0.03  # inliers flatter than this (σ3/σ1) are one plane: check the mirror
    # (DᵀD)⁻¹ s² treats every inlier's error as independent; model-point and rendering errors
    # are not, so it is ~6× (variance) too confident. Calibrated on rendered scenes at known
    # poses (median NEES 32 → 4.3 on a held-out set; bench/RESULTS.md).
    covariance_inflation: float = 6.0
    max_view_angle_deg: float = 60.0  # viewing direction vs the matched viewset's


@dataclass(frozen=True)
class PoseEstimate:
    """A refined pose (object → camera) with its 6×6 covariance over ``[p, δθ]``."""

    t: np.ndarray
    q: np.ndarray  # [w, x, y, z], w ≥ 0
    covariance: np.ndarray
    inliers: np.ndarray  # indices into the matches
    rms_px: float

    @property
    def R(self) -> np.ndarray:
        return quat.to_matrix(self.q)


def _reprojection_errors(camera: PinholeCamera, X: np.ndarray, uv: np.ndarray, t: np.ndarray, q: np.ndarray) -> np.ndarray:
    Xc = X @ quat.to_matrix(q).T + t
    err = np.full(len(X), np.inf)
    front = Xc[:, 2] > 1e-9
    if np.any(front):
        err[front] = np.linalg.norm(camera.project(Xc[front]) - uv[front], axis=1)
    return err


def refine(camera: PinholeCamera, X: np.ndarray, uv: np.ndarray, t0: np.ndarray, q0: np.ndarray, inflation: float = 1.0):
    """LM refinement on inliers; the covariance is ``(DᵀD)⁻¹`` at unit pixel noise times the
    residual variance ``s² = Σ r² / (2n − 6)``, times ``inflation``."""
    block = PointMeasurements.create(camera, X, uv, 1.0)
    est = estimate_pose([block], t0, q0, AdjustOptions(method="levenberg-marquardt", max_iterations=30))
    dof = max(2 * len(X) - 6, 1)
    s2 = max(2.0 * est.cost / dof, 1e-4)  # cost = ½ Σ r²; floor: digitisation never vanishes
    return est.p, quat.canonical(est.q), est.covariance * s2 * inflation


def viewing_direction(R: np.ndarray, t: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Unit vector, in the object frame, from the object's centre towards the camera. Unlike the
    rotation it ignores the camera's roll, to which SIFT is blind."""
    d = -R.T @ (R @ centre + t)
    return d / np.linalg.norm(d)


def view_angle_deg(R: np.ndarray, t: np.ndarray, reference_R: np.ndarray, reference_t: np.ndarray, centre: np.ndarray) -> float:
    """Angle between the directions the object is seen from in two poses."""
    a = viewing_direction(R, t, centre)
    b = viewing_direction(reference_R, reference_t, centre)
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def _mirror_candidates(camera: PinholeCamera, X: np.ndarray, uv: np.ndarray):
    """Both poses that fit points on one plane (IPPE): the planar pose ambiguity."""
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(X, uv, camera.matrix, camera.dist_coeffs, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return []
    return [(np.asarray(tv).ravel(), quat.from_rotvec(np.asarray(rv).ravel())) for rv, tv in zip(rvecs[:n], tvecs[:n])]


def solve_pnp(
    camera: PinholeCamera, X: np.ndarray, uv: np.ndarray, params: PoseParams = PoseParams(),
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> PoseEstimate | None:
    """RANSAC PnP, refinement on the inliers, a second inlier pass at the refined pose.

    ``prior`` = (R, t, centre) of the matched viewset's view: when the inliers lie on one plane
    the mirrored solution fits them as well, and the one seen from nearer the viewset's
    direction is kept (the query looks like that viewset, or it would not have matched it)."""
    X = np.asarray(X, np.float64).reshape(-1, 3)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if len(X) < max(6, params.min_inliers):
        return None
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X, uv, camera.matrix, camera.dist_coeffs, iterationsCount=params.ransac_iterations,
        reprojectionError=params.ransac_px, confidence=params.ransac_confidence, flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or inl is None or len(inl) < 6:
        return None
    idx = inl.ravel()
    t, q = tvec.ravel(), quat.from_rotvec(rvec.ravel())
    try:
        for _ in range(2):  # refine, re-collect inliers at the better pose, refine again
            t, q, cov = refine(camera, X[idx], uv[idx], t, q)
            err = _reprojection_errors(camera, X, uv, t, q)
            new = np.flatnonzero(err < params.inlier_px)
            if len(new) < 6:
                return None
            if np.array_equal(new, idx):
                break
            idx = new
        t, q, cov = refine(camera, X[idx], uv[idx], t, q, params.covariance_inflation)
        if prior is not None and len(idx) >= 4:
            Xi = X[idx] - X[idx].mean(axis=0)
            sv = np.linalg.svd(Xi, compute_uv=False)
            if sv[2] < params.planar_ratio * sv[0]:
                best = (view_angle_deg(quat.to_matrix(q), t, *prior), t, q, cov)
                for t2, q2 in _mirror_candidates(camera, X[idx], uv[idx]):
                    t2, q2, cov2 = refine(camera, X[idx], uv[idx], t2, q2, params.covariance_inflation)
                    err2 = _reprojection_errors(camera, X[idx], uv[idx], t2, q2)
                    if np.sqrt(np.mean(err2**2)) <= params.max_rms_px:
                        angle = view_angle_deg(quat.to_matrix(q2), t2, *prior)
                        if angle < best[0]:
                            best = (angle, t2, q2, cov2)
                _, t, q, cov = best
    except SingularProblemError:
        return None
    err = _reprojection_errors(camera, X[idx], uv[idx], t, q)
    return PoseEstimate(t, q, cov, idx, float(np.sqrt(np.mean(err**2))))


def projected_bbox(camera: PinholeCamera, vertices: np.ndarray, t: np.ndarray, q: np.ndarray):
    """(x, y, w, h) of the projected mesh vertices, or None if any lies behind the camera."""
    Xc = vertices @ quat.to_matrix(q).T + t
    if np.any(Xc[:, 2] <= 1e-9):
        return None
    uv = camera.project(Xc)
    x0, y0 = uv.min(axis=0)
    x1, y1 = uv.max(axis=0)
    return float(x0), float(y0), float(x1 - x0), float(y1 - y0)


def intersection(a, b) -> float:
    """Area shared by two (x, y, w, h) boxes."""
    iw = max(0.0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    return iw * ih


def iou(a, b) -> float:
    """Intersection over union of two (x, y, w, h) boxes."""
    inter = intersection(a, b)
    union = a[2] * a[3] + b[2] * b[3] - inter
    return inter / union if union > 0 else 0.0


def facing_share(est: PoseEstimate, points3d: np.ndarray, normals: np.ndarray) -> float:
    """Share of the inliers whose surface faces the camera at the pose. A mirrored solution
    (the planar pose ambiguity) fits the points as well, but shows their face from behind."""
    idx = est.inliers
    R = est.R
    X = points3d[idx] @ R.T + est.t
    n = normals[idx] @ R.T
    return float(np.mean(np.einsum("ij,ij->i", n, X) < 0.0)) if len(idx) else 0.0


def verify(
    est: PoseEstimate,
    n_matches: int,
    camera: PinholeCamera,
    vertices: np.ndarray,
    window: tuple | None,
    params: PoseParams = PoseParams(),
    points3d: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> str | None:
    """Why the pose must not be reported (a short reason), or None if it passes every check.
    ``points3d``/``normals``: the matched model points (indexed like the matches) and their
    surface normals, for the facing check; ``prior``: the matched viewset's (R, t, centre)."""
    if len(est.inliers) < params.min_inliers:
        return f"too few inliers ({len(est.inliers)} < {params.min_inliers})"
    if len(est.inliers) < params.min_inlier_ratio * n_matches:
        return f"inlier ratio {len(est.inliers) / max(n_matches, 1):.2f} below {params.min_inlier_ratio}"
    if est.rms_px > params.max_rms_px:
        return f"reprojection RMS {est.rms_px:.2f} px above {params.max_rms_px}"
    if points3d is not None and normals is not None:
        share = facing_share(est, points3d, normals)
        if share < params.min_facing:
            return f"only {100 * share:.0f} % of the inliers face the camera (a mirrored pose)"
    if prior is not None:
        angle = view_angle_deg(est.R, est.t, *prior)
        if angle > params.max_view_angle_deg:
            return f"seen from {angle:.0f}° away from its matched viewset's view"
    box = projected_bbox(camera, vertices, est.t, est.q)
    if box is None:
        return "the object would be behind the camera"
    area = box[2] * box[3]
    image = (0.0, 0.0, float(camera.width), float(camera.height))
    if area <= 0 or intersection(box, image) / area < params.min_visible_fraction:
        return "the object would lie mostly outside the image"
    if window is not None and iou(box, window) < params.min_window_iou:
        return f"the projected object does not fit the window (IoU {iou(box, window):.2f})"
    return None

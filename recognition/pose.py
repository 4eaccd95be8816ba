"""Initial pose from 2-D/3-D matches: RANSAC PnP, refinement, covariance and verification.

RANSAC (OpenCV) finds a consensus (:func:`ransac_pnp`, reusable by the tracker); the refinement
is the project's own Levenberg–Marquardt on the inliers (:func:`quatrack.tracking.adjust.estimate_pose`),
whose ``(DᵀD)⁻¹`` scaled by the residual variance is the pose covariance over ``[p, δθ]``
(contract conventions). A pose is *verified* before anyone is told the object was found:
:func:`verify` gives the first reason to refuse it, :func:`verification` the evidence and a
confidence (issue 13). Poses are judged on the part of the object inside the image
(:func:`plausible`): a pose that puts half the object out of frame is not refused for that.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.adjust import AdjustOptions, SingularProblemError, estimate_pose
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.measurements import PointMeasurements
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import Mesh

from .evidence import EdgeEvidence, EdgeParams, edge_agreement, inlier_spread, silhouette_inside


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
    min_visible_fraction: float = 0.2  # of the object's silhouette inside the image
    min_visible_px: float = 0.004  # × the image's area: the visible part must have some size
    min_window_iou: float = 0.25  # projected box vs the localised window, when there is one
    min_facing: float = 0.9  # share of inliers whose surface faces the camera at the pose
    planar_ratio: float = 0.03  # inliers flatter than this (σ3/σ1) are one plane: check the mirror
    # (DᵀD)⁻¹ s² treats every inlier's error as independent; model-point and rendering errors
    # are not, so it is ~6× (variance) too confident. Calibrated on rendered scenes at known
    # poses (median NEES 32 → 4.3 on a held-out set; bench/RESULTS.md).
    covariance_inflation: float = 6.0
    max_view_angle_deg: float = 60.0  # viewing direction vs the matched viewset's
    # evidence a wrong pose cannot fake (recognition/evidence.py), judged inside the image
    edges: EdgeParams = EdgeParams()
    min_edge_agreement: float = 0.5  # share of visible model edge samples on aligned image edges
    min_edge_lead: float = 0.25  # … above this image's chance level (edges displaced)
    min_edge_samples: int = 12
    min_spread: float = 0.02  # inliers' hull over the visible silhouette
    max_rival_ratio: float = 0.8  # a different pose with this share of the inliers is a rival
    # confidence = σ(a + b·lead + c·agreement + d·ln(inliers) + e·spread). The coefficients were
    # set by hand from ~90 zoo poses (right: agreement 0.7–1.0, lead ≥ 0.4, spread ≥ 0.3 mostly;
    # wrong: agreement 0.57–0.70, spread 0.1–0.26), NOT fitted yet: the benchmark reports how
    # well calibrated it is (bench/RESULTS.md, "confidence vs share correct")
    confidence_coef: tuple[float, ...] = (-9.0, 6.0, 6.0, 0.6, 3.0)


@dataclass(frozen=True)
class PnPSolution:
    """A refined PnP pose (object → camera) with its 6×6 covariance over ``[p, δθ]``, the
    inliers (indices into the matches) and their reprojection RMS."""

    pose: Pose
    covariance: np.ndarray
    inliers: np.ndarray
    rms_px: float

    @property
    def t(self) -> np.ndarray:
        return self.pose.t

    @property
    def q(self) -> np.ndarray:
        """[w, x, y, z], w ≥ 0."""
        return self.pose.q_wxyz

    @property
    def R(self) -> np.ndarray:
        return self.pose.R


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


def ransac_pnp(
    camera: PinholeCamera, X: np.ndarray, uv: np.ndarray, reprojection_px: float = 6.0, iterations: int = 1000,
    confidence: float = 0.999, guess: Pose | None = None, min_inliers: int = 6,
) -> tuple[Pose, np.ndarray] | None:
    """RANSAC PnP consensus (OpenCV): the pose and the inlier indices, or None.

    Without ``guess`` minimal samples are solved by EPnP; with it, by iterative PnP started at
    the guess (the tracker's re-anchoring: the pose of the frame the matches were found in)."""
    X = np.asarray(X, np.float64).reshape(-1, 3)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if len(X) < max(6, min_inliers):
        return None
    try:
        if guess is None:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                X, uv, camera.matrix, camera.dist_coeffs, iterationsCount=iterations,
                reprojectionError=reprojection_px, confidence=confidence, flags=cv2.SOLVEPNP_EPNP)
        else:
            rvec0 = cv2.Rodrigues(guess.R)[0]
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                X, uv, camera.matrix, camera.dist_coeffs, rvec0.copy(), guess.t.reshape(3, 1).copy(),
                useExtrinsicGuess=True, iterationsCount=iterations, reprojectionError=reprojection_px,
                confidence=confidence, flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:
        return None
    if not ok or inl is None or len(inl) < max(6, min_inliers):
        return None
    try:
        return Pose.from_rvec(rvec.ravel(), tvec.ravel()), inl.ravel()
    except ValueError:  # non-finite solution
        return None


def solve_pnp(
    camera: PinholeCamera, X: np.ndarray, uv: np.ndarray, params: PoseParams = PoseParams(),
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> PnPSolution | None:
    """RANSAC PnP, refinement on the inliers, a second inlier pass at the refined pose.

    ``prior`` = (R, t, centre) of the matched viewset's view: when the inliers lie on one plane
    the mirrored solution fits them as well, and the one seen from nearer the viewset's
    direction is kept (the query looks like that viewset, or it would not have matched it)."""
    X = np.asarray(X, np.float64).reshape(-1, 3)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if len(X) < max(6, params.min_inliers):
        return None
    found = ransac_pnp(camera, X, uv, params.ransac_px, params.ransac_iterations, params.ransac_confidence)
    if found is None:
        return None
    pose0, idx = found
    t, q = pose0.t, pose0.q_wxyz
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
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        return None
    return PnPSolution(Pose(q, t), cov, idx, float(np.sqrt(np.mean(err**2))))


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


def facing_share(est: PnPSolution, points3d: np.ndarray, normals: np.ndarray) -> float:
    """Share of the inliers whose surface faces the camera at the pose. A mirrored solution
    (the planar pose ambiguity) fits the points as well, but shows their face from behind."""
    idx = est.inliers
    R = est.R
    X = points3d[idx] @ R.T + est.t
    n = normals[idx] @ R.T
    return float(np.mean(np.einsum("ij,ij->i", n, X) < 0.0)) if len(idx) else 0.0


def plausible(camera: PinholeCamera, mesh: Mesh, pose: Pose, params: PoseParams = PoseParams()) -> str | None:
    """Why ``pose`` cannot be the object's in this camera's image (None if it can): behind the
    camera, or too little of the silhouette inside the image (judged on the silhouette, so a
    pose with part of the object out of frame passes when enough is in)."""
    if np.any(pose.apply(mesh.vertices)[:, 2] <= 1e-9):
        return "the object would be (partly) behind the camera"
    share, area = silhouette_inside(mesh, camera, pose)
    if share < params.min_visible_fraction:
        return f"only {100 * share:.0f} % of the object would be inside the image (< {100 * params.min_visible_fraction:.0f} %)"
    if area < params.min_visible_px * camera.width * camera.height:
        return f"the object would show only {area:.0f} px inside the image"
    return None


def _basic_checks(est: PnPSolution, n_matches: int, params: PoseParams, points3d, normals, prior) -> str | None:
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
    return None


def verify(
    est: PnPSolution,
    n_matches: int,
    camera: PinholeCamera,
    mesh: Mesh,
    window: tuple | None,
    params: PoseParams = PoseParams(),
    points3d: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> str | None:
    """Why the pose must not be reported (a short reason), or None if it passes the geometric
    checks (inliers, RMS, facing, viewing angle, plausibility, window). ``points3d``/``normals``:
    the matched model points (indexed like the matches) and their surface normals, for the facing
    check; ``prior``: the matched viewset's (R, t, centre). The image evidence is
    :func:`verification`'s."""
    why = _basic_checks(est, n_matches, params, points3d, normals, prior)
    if why is None:
        why = plausible(camera, mesh, est.pose, params)
    if why is None and window is not None:
        box = projected_bbox(camera, mesh.vertices, est.t, est.q)
        if box is not None:
            image = (0.0, 0.0, float(camera.width), float(camera.height))
            clipped = _clip_box(box, image)
            if iou(clipped, window) < params.min_window_iou:
                return f"the projected object does not fit the window (IoU {iou(clipped, window):.2f})"
    return why


def _clip_box(box, image):
    x0, y0 = max(box[0], image[0]), max(box[1], image[1])
    x1, y1 = min(box[0] + box[2], image[0] + image[2]), min(box[1] + box[3], image[1] + image[3])
    return (x0, y0, max(x1 - x0, 0.0), max(y1 - y0, 0.0))


@dataclass(frozen=True)
class Verification:
    """The evidence for a pose (reported as the JSON's ``verification``) and the reason to
    refuse it, if any. ``confidence`` ∈ [0, 1] estimates the probability that the pose is
    right (within 5 % of the diameter and 5°), from a logistic fit on the zoo benchmark."""

    passed: bool
    reason: str | None
    confidence: float
    inside_fraction: float
    edges: EdgeEvidence
    spread: float
    inliers: int
    rival_inliers: int

    def to_json(self) -> dict:
        return {
            "passed": self.passed,
            "confidence": round(self.confidence, 4),
            "inside_fraction": round(self.inside_fraction, 4),
            "edge_samples": int(self.edges.samples),
            "edge_agreement": round(self.edges.agreement, 4),
            "edge_chance": round(self.edges.chance, 4),
            "edge_weakest": round(self.edges.weakest, 4),
            "inlier_spread": round(self.spread, 4),
            "inliers": int(self.inliers),
            "rival_inliers": int(self.rival_inliers),
            "reason": self.reason,
        }


def confidence(params: PoseParams, lead: float, agreement: float, inliers: int, spread: float) -> float:
    """σ(a + b·lead + c·agreement + d·ln(inliers) + e·spread), the calibrated confidence."""
    a, b, c, d, e = params.confidence_coef
    z = a + b * lead + c * agreement + d * np.log(max(inliers, 1)) + e * spread
    return float(1.0 / (1.0 + np.exp(-z)))


def rival_inliers(camera: PinholeCamera, X: np.ndarray, uv: np.ndarray, est: PnPSolution, mesh: Mesh,
                  params: PoseParams = PoseParams()) -> int:
    """Inliers of the best *different* pose among the matches that are not ``est``'s inliers (a
    second consensus: repeated texture, a symmetric object). 0 if none; a rival differs by more
    than 5 % of the diameter or 5°."""
    rest = np.setdiff1d(np.arange(len(X)), est.inliers)
    if len(rest) < max(6, params.min_inliers // 2):
        return 0
    found = ransac_pnp(camera, X[rest], uv[rest], params.ransac_px, 200, 0.99)
    if found is None:
        return 0
    pose, inl = found
    c = mesh.centre
    dt = np.linalg.norm((pose.R @ c + pose.t) - (est.R @ c + est.t))
    dr = np.degrees(quat.angle_between(pose.q_wxyz, est.q))
    return int(len(inl)) if (dt > 0.05 * mesh.extent or dr > 5.0) else 0


def verification(
    est: PnPSolution, grey: np.ndarray, camera: PinholeCamera, mesh: Mesh, uv: np.ndarray,
    params: PoseParams = PoseParams(), rival: int = 0,
) -> Verification:
    """The image evidence for a pose that passed :func:`verify`: the model's visible edges on
    the image's edges (above chance), the inliers' spread over the visible silhouette, no rival
    consensus; ``grey``: the 8-bit grey image, ``uv``: the matched keypoints (indexed like the
    matches)."""
    share, area = silhouette_inside(mesh, camera, est.pose)
    edges = edge_agreement(grey, mesh, camera, est.pose, params.edges)
    spread = inlier_spread(uv[est.inliers], area)
    n = len(est.inliers)
    conf = confidence(params, edges.lead, edges.agreement, n, spread)
    reason = None
    if edges.samples < params.min_edge_samples:
        reason = f"too little of the model's outline is visible to check ({edges.samples} edge samples)"
    elif edges.agreement < params.min_edge_agreement:
        reason = f"the model's edges do not lie on image edges ({100 * edges.agreement:.0f} % agree)"
    elif edges.lead < params.min_edge_lead:
        reason = (f"the model's edges agree with the image no better than chance "
                  f"({100 * edges.agreement:.0f} % vs {100 * edges.chance:.0f} %)")
    elif spread < params.min_spread:
        reason = f"the inliers cover only {100 * spread:.1f} % of the visible object"
    elif rival >= params.max_rival_ratio * n:
        reason = f"another pose fits almost as many matches ({rival} vs {n} inliers)"
    return Verification(reason is None, reason, conf if reason is None else min(conf, 0.5), share, edges, spread, n, rival)

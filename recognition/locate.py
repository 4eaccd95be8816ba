"""Recognition and initial pose, the path behind ``quatrack locate`` and ``POST .../pose``.

``locate`` = localise (RFCH window) → SIFT in the window plus a margin → match to every viewset →
the viewset with most matches → RANSAC PnP + refinement → verification. If the window yields no
verified pose, the whole image is searched before giving up. Per-stage times are reported.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.features import Features
from quatrack.viewsets.store import ObjectModel

from .images import DEFAULT_MAX_PIXELS, prepare_image
from .localise import LocaliseParams, Window, localise
from .match import ModelIndex, index_for, rank_viewsets
from .pose import PoseEstimate, PoseParams, solve_pnp, verify


@dataclass(frozen=True)
class LocateParams:
    localise: LocaliseParams = field(default_factory=LocaliseParams)
    pose: PoseParams = field(default_factory=PoseParams)
    margin: float = 0.25  # the window is enlarged by this fraction on every side for SIFT
    viewsets_tried: int = 2  # the best and the runner-up
    pool_all: bool = True  # then all matches of every viewset together
    whole_image_fallback: bool = True
    use_window: bool = True  # False: skip localisation, match in the whole image
    max_pixels: int = DEFAULT_MAX_PIXELS


@dataclass
class Located:
    """The answer for one image (pixels of the original image; pose in mesh units)."""

    found: bool
    bbox: tuple[float, float, float, float] | None = None
    chi2: float | None = None
    viewset: str | None = None
    matches: int = 0
    inliers: int = 0
    reprojection_rms_px: float | None = None
    t: np.ndarray | None = None
    q_wxyz: np.ndarray | None = None
    covariance: np.ndarray | None = None
    time_ms: dict = field(default_factory=dict)
    reason: str | None = None  # why not found
    searched: str = "window"  # "window" or "image": where the pose came from

    def to_json(self) -> dict:
        """The contract's JSON object (``image`` is added by the caller)."""
        return {
            "found": self.found,
            "bbox": None if self.bbox is None else [round(float(v), 2) for v in self.bbox],
            "chi2": None if self.chi2 is None else float(self.chi2),
            "viewset": self.viewset,
            "matches": int(self.matches),
            "inliers": int(self.inliers),
            "reprojection_rms_px": None if self.reprojection_rms_px is None else float(self.reprojection_rms_px),
            "pose": None if not self.found else {"t": [float(v) for v in self.t], "q_wxyz": [float(v) for v in self.q_wxyz]},
            "covariance": None if not self.found else [[float(v) for v in row] for row in self.covariance],
            "time_ms": {k: round(v, 3) for k, v in self.time_ms.items()},
            "reason": self.reason,
            "searched": self.searched,
        }


def _crop_box(bbox, margin: float, w: int, h: int) -> tuple[int, int, int, int]:
    x, y, bw, bh = bbox
    x0 = int(max(0, np.floor(x - margin * bw)))
    y0 = int(max(0, np.floor(y - margin * bh)))
    x1 = int(min(w, np.ceil(x + bw * (1 + margin))))
    y1 = int(min(h, np.ceil(y + bh * (1 + margin))))
    return x0, y0, x1, y1


def _pose_from(
    features: Features, index: ModelIndex, model: ObjectModel, camera: PinholeCamera,
    window: tuple | None, params: LocateParams, timer: dict,
) -> tuple[PoseEstimate | None, int, str | None, str | None]:
    """Match, rank viewsets by votes, PnP on the best one's matches (then the runner-up's, then
    all matches pooled); the first verified pose wins. Returns (pose, matches used, why not,
    viewset label)."""
    t0 = time.perf_counter()
    matches = index.match(features)
    ranked = rank_viewsets(matches, len(model.viewsets))
    timer["match"] = timer.get("match", 0.0) + (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    trials = [(model.viewsets[v].label, np.flatnonzero(matches.viewset == v)) for v in ranked[: params.viewsets_tried]]
    if params.pool_all and ranked:
        trials.append((model.viewsets[ranked[0]].label, np.arange(len(matches))))
    reason, n_best = "no viewset has enough matches", len(trials[0][1]) if trials else 0
    try:
        for label, keep in trials:
            if len(keep) < params.pose.min_inliers:
                continue
            m = matches.subset(keep)
            vs = model.viewsets[int(np.bincount(m.viewset).argmax())]
            prior = (vs.pose.R, vs.pose.t, model.mesh.centre)
            est = solve_pnp(camera, m.points3d, features.keypoints[m.query_idx], params.pose, prior)
            if est is None:
                reason = f"PnP found no consensus ({len(keep)} matches, viewset {label})"
                continue
            why = verify(est, len(keep), camera, model.mesh.vertices, window, params.pose, m.points3d, m.normals, prior)
            if why is None:
                return est, len(keep), None, label
            reason = f"{why} (viewset {label})"
        return None, n_best, reason, trials[0][0] if trials else None
    finally:
        timer["pnp"] = timer.get("pnp", 0.0) + (time.perf_counter() - t0) * 1e3


def locate(
    image: np.ndarray, camera: PinholeCamera, model: ObjectModel, params: LocateParams = LocateParams(),
    index: ModelIndex | None = None,
) -> Located:
    """Find ``model`` in ``image`` (any bit depth/channels) seen by ``camera``; never raises for
    an image without the object (``found`` is False), raises ImageError for an unusable image."""
    t_start = time.perf_counter()
    prep = prepare_image(image, camera, params.max_pixels)
    img, cam = prep.image, prep.camera
    index = index or index_for(model)
    timer: dict[str, float] = {"localise": 0.0, "match": 0.0, "pnp": 0.0}
    h, w = img.shape[:2]

    win: Window | None = None
    if params.use_window:
        t0 = time.perf_counter()
        win = localise(img, cam, model, params.localise)
        timer["localise"] = (time.perf_counter() - t0) * 1e3

    est, n_matches, reason, vs_label, searched = None, 0, "no object-like window", None, "window"
    if win is not None and win.found:
        t0 = time.perf_counter()
        feats = index.describe(img, _crop_box(win.bbox, params.margin, w, h))
        timer["match"] += (time.perf_counter() - t0) * 1e3
        est, n_matches, reason, vs_label = _pose_from(feats, index, model, cam, win.bbox, params, timer)
    # the whole image is searched when there is no window search, or when the window looked
    # like the object but gave no verified pose; a window that is nothing like the object
    # (χ² beyond the gate) ends the search: "not found" stays fast
    window_failed = win is not None and win.found and est is None
    if est is None and (not params.use_window or (params.whole_image_fallback and window_failed)):
        searched = "image"
        t0 = time.perf_counter()
        feats = index.describe(img)
        timer["match"] += (time.perf_counter() - t0) * 1e3
        est, n_matches, reason, vs_label = _pose_from(feats, index, model, cam, None, params, timer)

    timer["total"] = (time.perf_counter() - t_start) * 1e3
    inv = 1.0 / prep.scale
    bbox = None
    if win is not None:
        bbox = tuple(float((v + 0.5) * inv - 0.5) if i < 2 else float(v * inv) for i, v in enumerate(win.bbox))
    if est is None:
        return Located(False, bbox, None if win is None else win.chi2, vs_label, n_matches, 0, None,
                       time_ms=timer, reason=reason, searched=searched)
    return Located(
        True, bbox, None if win is None else win.chi2, vs_label, n_matches, len(est.inliers), est.rms_px * inv,
        est.t, est.q, est.covariance, time_ms=timer, searched=searched,
    )

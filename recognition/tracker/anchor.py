"""SIFT re-anchoring: the measurement source that ties the tracks to the model (no drift).

SIFT in the object's predicted window, matched to the viewsets (:class:`~recognition.match.ModelIndex`),
made consistent by RANSAC PnP started at the current pose (:func:`recognition.pose.ransac_pnp`),
kept if visible there. The matches are exact 2-D/3-D correspondences: they join the trained
point tracks (and replace the tracks they coincide with). The costly half (SIFT + FLANN) may run
on an executor the *caller* owns (the service's pool), beside the next frames' steps.
"""

from __future__ import annotations

from concurrent.futures import Executor, Future
from dataclasses import dataclass

import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import Mesh

from ..klt import Frame, track_points
from ..match import ModelIndex
from ..pose import ransac_pnp
from ..visibility import visible_points
from .params import TrackerParams
from .points import Tracks


def object_window(mesh: Mesh, camera: PinholeCamera, pose: Pose, margin: float = 0.15) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1) of the projected mesh enlarged by ``margin``, clipped to the
    image; None when the object is behind the camera or the box is under 16 px."""
    Xc = pose.apply(mesh.vertices)
    if np.any(Xc[:, 2] <= 0):
        return None
    uv = camera.project(Xc)
    x0, y0 = uv.min(axis=0)
    x1, y1 = uv.max(axis=0)
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    w, h = camera.width, camera.height
    box = (int(max(0, x0 - mx)), int(max(0, y0 - my)), int(min(w, x1 + mx + 1)), int(min(h, y1 + my + 1)))
    if box[2] - box[0] < 16 or box[3] - box[1] < 16:
        return None
    return box


@dataclass
class AnchorJob:
    """SIFT + matching of an earlier frame, running on the caller's executor."""

    future: Future
    pose: Pose  # the pose of the frame the features come from
    frame: Frame
    full: bool = False  # SIFT on the window at full resolution, all features (Anchor.features)


class Anchor:
    """Re-anchoring against the model's viewsets (trained, and learned ones if the index has them)."""

    def __init__(self, mesh: Mesh, index: ModelIndex, params: TrackerParams) -> None:
        self.mesh, self.index, self.params = mesh, index, params

    def features(self, img: np.ndarray, box, full: bool = False) -> tuple:
        """SIFT in ``box`` and its matches to the model: the costly half of re-anchoring. The
        window is shrunk to ``anchor_max_side`` with its ``anchor_max_features`` strongest
        features (live streams), unless ``full``: full resolution, every feature (offline)."""
        p = self.params
        side, most = (None, None) if full else (p.anchor_max_side, p.anchor_max_features)
        feats = self.index.describe(img, box, max_side=side, max_features=most)
        return feats, self.index.match(feats)

    @property
    def reduced(self) -> bool:
        """Whether :meth:`features` shrinks the window or keeps only the strongest features."""
        return self.params.anchor_max_side is not None or self.params.anchor_max_features is not None

    def submit(self, executor: Executor, img: np.ndarray, camera: PinholeCamera, pose: Pose, frame: Frame,
               full: bool = False) -> AnchorJob | None:
        """Start the costly half on ``executor`` for the frame ``img`` at ``pose`` (``full``:
        see :meth:`features`)."""
        box = object_window(self.mesh, camera, pose, 0.15)
        if box is None:
            return None
        crop = np.ascontiguousarray(img[box[1] : box[3], box[0] : box[2]])
        shifted = (0, 0, box[2] - box[0], box[3] - box[1])

        def work():
            feats, m = self.features(crop, shifted, full)
            kp = feats.keypoints + np.array([box[0], box[1]], np.float32)
            return type(feats)(kp, feats.descriptors, feats.sizes, feats.angles), m

        return AnchorJob(executor.submit(work), pose, frame, full)

    def carry(self, feats, m, camera: PinholeCamera, frame_then: Frame, frame_prev: Frame, pose_prev: Pose):
        """Keypoints found on an older frame, tracked by KLT into the previous frame (which the
        next KLT step starts from); those that do not follow are dropped with their matches."""
        kp = feats.keypoints[m.query_idx].astype(np.float64)
        guess = camera.project(pose_prev.apply(np.asarray(m.points3d, float)))
        moved, ok, _ = track_points(frame_then, frame_prev, kp, guess, self.params.klt)
        keep = np.flatnonzero(ok)
        kp_new = np.zeros_like(feats.keypoints)
        kp_new[m.query_idx[keep]] = moved[keep]
        feats = type(feats)(kp_new.astype(np.float32), feats.descriptors, feats.sizes, feats.angles)
        return feats, m.subset(keep), pose_prev

    def now(self, img: np.ndarray, camera: PinholeCamera, pose: Pose, tracks: Tracks, wide: bool,
            alternative=None) -> tuple[Tracks, int, bool]:
        """Re-anchor in this frame: SIFT in the object's window, then :meth:`merge`. Where that
        gives fewer than ``min_anchor_matches`` consistent matches, ``alternative(features)``
        (other matches of the same features, or None) is merged instead if it gives more — one
        SIFT pass either way."""
        box = object_window(self.mesh, camera, pose, 0.3 if wide else 0.15)
        if box is None:
            return tracks, 0, False
        feats, m = self.features(img, box)
        out = self.merge(feats, m, camera, pose, tracks, wide)
        if out[1] >= self.params.min_anchor_matches or alternative is None:
            return out
        m_alt = alternative(feats)
        if m_alt is None:
            return out
        alt = self.merge(feats, m_alt, camera, pose, tracks, wide)
        return alt if alt[1] > out[1] else out

    def merge(self, feats, m, camera: PinholeCamera, pose: Pose, tracks: Tracks, wide: bool) -> tuple[Tracks, int, bool]:
        """Make SIFT matches consistent by RANSAC PnP started at ``pose`` (the pose of the frame
        they were found in) and merge them into ``tracks``.

        Returns ``(tracks, consistent matches, replaced)``. Fresh matches are exact
        correspondences, so they replace tracks within 3 px of them; if the pose disagrees with
        them (median reprojection > ``anchor_radius_px / 2``) while they are many, the KLT
        tracks have slid (occlusion, drift) and are all replaced (``replaced``). OpenCV's PnP
        stops on absolute tolerances: it works in diameters, so every mesh unit agrees.
        """
        p = self.params
        if len(m) < max(p.min_anchor_matches, 6):
            return tracks, 0, False
        kp = feats.keypoints[m.query_idx].astype(np.float64)
        X = np.asarray(m.points3d, np.float64)
        d = self.mesh.extent
        found = ransac_pnp(camera, X / d, kp, reprojection_px=3.0, iterations=100, confidence=0.99,
                           guess=Pose(pose.q_wxyz, pose.t / d), min_inliers=p.min_anchor_matches)
        if found is None:
            return tracks, 0, False
        pnp_d, inl = found
        pnp = Pose(pnp_d.q_wxyz, pnp_d.t * d)
        vis, _ = visible_points(self.mesh, camera, pnp, X[inl], p.visibility)
        X, kp = X[inl][vis], kp[inl][vis]
        if len(X) < p.min_anchor_matches:
            return tracks, 0, False
        uv_cur = camera.project(pose.apply(X))
        off = float(np.median(np.linalg.norm(uv_cur - kp, axis=1)))
        z = float(pose.apply(self.mesh.centre[None])[0, 2])
        if off > 0.05 * camera.fx * d / max(z, 1e-9):
            # consistent among themselves, but they put the object's points more than 5 % of its
            # apparent size from where the track has them: texture repeated on another face (a
            # cube's sides cut from one photo) matched them; taken, they turned a right track by
            # 90°, and the cube's edges agreed. KLT slides a few pixels, not that far.
            return tracks, 0, False
        disagree = off > 0.5 * p.anchor_radius_px
        replaced = disagree and len(X) >= 2 * p.min_inliers and not wide
        if len(tracks) and not replaced:
            dist = np.linalg.norm(tracks.uv[:, None, :] - kp[None, :, :], axis=2)
            tracks = tracks.keep(dist.min(axis=1) > 3.0)
        elif replaced:
            tracks = Tracks.empty()
        merged = Tracks(X, kp) + tracks
        return merged.keep(np.arange(len(merged)) < p.max_points), len(X), replaced

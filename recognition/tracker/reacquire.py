"""Re-acquisition near the last pose: what the tracker keeps of its last good frame before a
loss, and where the object's image went since (issue 12, item 5).

An object that left the frame, or went behind a hand, mostly comes back where it went, turned a
little; the tracker then picks the track up from its last good frame (:class:`LastSeen`) by KLT
instead of waiting for recognition, which cannot find sides no training photo shows. KLT reaches
a few tens of pixels; an object that slid out of the frame and back may reappear a hundred
pixels away from where it was last seen. :func:`object_shift` finds that displacement first —
the last good frame's patch of the object, compared with the new frame by normalised
cross-correlation over the object's own pixels (its projected hull: the background it stood on
does not vote) — and :func:`shifted_pose` moves the held pose so its image moves by as much.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.tracking.state import FilterState

from ..klt import Frame
from .mesh_points import MeshPoints
from .points import Tracks


@dataclass(frozen=True)
class LastSeen:
    """The track's last good frame before a loss: the posterior there, the frame (KLT starts
    from it), and the point sources' tracks then (``mesh``: a shallow copy of the
    :class:`~.mesh_points.MeshPoints` source, whose updates rebind, never mutate, its arrays)."""

    state: FilterState
    frame: Frame
    trained: Tracks
    mesh: MeshPoints
    followed: bool = False  # a frame after the loss whose pose the measurements supported (not reported)
    # the track was re-found on the tracker's own keyframes (Tracker._second_hand) and its birth
    # (R, covariance): picked up again, it stays second-hand, judged and reported as such
    second_hand: bool = False
    birth: tuple | None = None
    doubted: bool = False  # the pose was withheld in doubt (Tracker._doubt), not reported


def hull_mask(camera: PinholeCamera, vertices: np.ndarray, pose: Pose) -> np.ndarray:
    """uint8 mask (image size) of the convex hull of the mesh's projected vertices, clipped to
    the image: the object's pixels, roughly (no render needed). Empty if it is behind the camera."""
    mask = np.zeros((camera.height, camera.width), np.uint8)
    Xc = pose.apply(vertices)
    if np.any(Xc[:, 2] <= 1e-9):
        return mask
    uv = camera.project(Xc)
    hull = cv2.convexHull(np.round(uv).astype(np.int32))
    cv2.fillConvexPoly(mask, hull, 255)
    return mask


def object_shift(before: np.ndarray, now: np.ndarray, mask: np.ndarray, max_side: int = 96,
                 min_pixels: int = 64) -> tuple[np.ndarray, float]:
    """The image displacement ``(du, dv)`` (px) of the patch of ``before`` under ``mask`` that best
    matches ``now`` — the maximum of the masked normalised cross-correlation
    ``Σ m (T − T̄)(I − Ī) / √(Σ m (T − T̄)² Σ m (I − Ī)²)`` (``cv2.TM_CCOEFF_NORMED``: blind to a
    change of gain and offset, as when the light changes) — and that maximum (−1…1). Both images
    are shrunk so that the patch's longer side is at most ``max_side`` px (the search costs
    ∝ image area × patch area). ``(0, 0), -1`` when the mask holds too few pixels.

    >>> rng = np.random.default_rng(0)
    >>> img = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.uint8), (0, 0), 2.0)
    >>> moved = np.roll(img, (12, -30), axis=(0, 1))  # 30 px left, 12 px down
    >>> m = np.zeros_like(img); m[80:160, 100:200] = 255
    >>> d, score = object_shift(img, moved, m)
    >>> np.round(d).tolist(), bool(score > 0.9)
    ([-30.0, 12.0], True)
    """
    ys, xs = np.nonzero(mask)
    if len(xs) < min_pixels:
        return np.zeros(2), -1.0
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    s = min(1.0, max_side / max(x1 - x0, y1 - y0))
    tpl, m = before[y0:y1, x0:x1], mask[y0:y1, x0:x1]
    img = now
    if s < 1.0:
        size = lambda a: (max(1, round(a.shape[1] * s)), max(1, round(a.shape[0] * s)))  # noqa: E731
        tpl = cv2.resize(tpl, size(tpl), interpolation=cv2.INTER_AREA)
        m = cv2.resize(m, size(m), interpolation=cv2.INTER_NEAREST)
        img = cv2.resize(now, size(now), interpolation=cv2.INTER_AREA)
    if tpl.shape[0] > img.shape[0] or tpl.shape[1] > img.shape[1] or np.count_nonzero(m) < 16:
        return np.zeros(2), -1.0
    res = cv2.matchTemplate(img, tpl, cv2.TM_CCOEFF_NORMED, mask=m)
    res[~np.isfinite(res)] = -1.0
    _, best, _, (bx, by) = cv2.minMaxLoc(res)
    return np.array([bx / s - x0, by / s - y0], float), float(best)


def shifted_pose(pose: Pose, centre: np.ndarray, camera: PinholeCamera, shift: np.ndarray) -> Pose:
    """``pose`` moved sideways at the depth ``z`` of ``centre`` so that its image moves by
    ``shift`` px: ``t' = t + z·(du/fx, dv/fy, 0)``."""
    z = float(pose.apply(np.asarray(centre, float)[None])[0, 2])
    return Pose(pose.q_wxyz, pose.t + z * np.array([shift[0] / camera.fx, shift[1] / camera.fy, 0.0]))

"""Points born on the mesh at the current pose: texture the training photos never showed.

When the pose is confident, corners (``cv2.goodFeaturesToTrack``) are detected in the current
frame inside the projected *visible* faces — away from the silhouette and self-occlusion
boundaries, where a KLT window straddles the background or another face, and off faces seen
at a grazing angle — and lifted to 3-D by casting their rays onto the mesh at the pose
(:func:`viewsets.render.cast_rays`). KLT then follows them like the trained points.

A born point inherits its birth pose's error ``δ = [δp, δθ]`` (covariance ``P_b``): it was
placed where the ray through its corner met the mesh *at the estimated pose* ``(R_b, p_b)``.
Had the pose been right, the same corner would lie at ``X + G δ`` with
``G = R_bᵀ [−I | [R_b X]×]`` (the rigid part), slid back along the ray ``d`` (object frame) onto
the face of normal ``n``: ``Q = I − d nᵀ / (nᵀ d)``. So the point's own uncertainty, in the object
frame, is ``Σ_X = Q G P_b Gᵀ Qᵀ`` (3×3, rank ≤ 2: in the face's plane), and at any later pose
``(R, p)`` its pixel is off by ``J_X Σ_X J_Xᵀ`` with ``J_X = ∂uv/∂X_cam · R``. At the birth pose
this is exactly ``J P_b Jᵀ``; later it follows the object as it turns (the birth covariance is
over the birth camera's axes, not the current one's).

The points born together share one ``δ``: their errors are one error, not ``n`` independent
ones, and treating them as independent makes the pose ``n`` times too sure of itself (NEES far
above its 6 degrees of freedom on faces no photo shows). For ``n`` perfectly correlated errors
``Cov(Σ eᵢ) ≤ n Σ Cov(eᵢ)`` (Cauchy–Schwarz), so each point of a birth *cohort* with ``n``
members measured in this frame gets the inherited part inflated ``n`` times:
``C = σ² I + n J_X Σ_X J_Xᵀ``; the cohort then tells the pose about as much as its birth pose
knew, which is the truth. Points born at an uncertain pose count less, and cannot pull the pose
away from the trained (exact) points. Points whose posterior residual keeps growing (an
exponential average above ``mesh_retire_px``) are retired: they sit on a wrong face, on
specular texture, or slid.

That holds while something else gives the pose absolute evidence: the trained points (exact
3-D), against which a cohort lifted at a pose a little off must not pull. Without them (a side
no photo shows, a track started on the mesh), the state's error *is* the birth error carried
forward: the points were lifted at the state's own pose, so a point's residual
``J ε_k − J_X Q G δ_b`` keeps only the motion since birth (at the birth pose ``J_X Q G = J``)
and the inherited part cancels. Adding it anyway made the points weightless (σ ≈ 28 px for a
cohort of 94 lifted at a given pose of 1 %/2°) and the edges, ~10 % of them locked on print
lines beside the creases, turned a pose started at the truth 5° away in one frame (the zoo
cube, bench/RESULTS.md, session 25). So a frame whose trained points are fewer than
``min_inliers`` (:attr:`FrameContext.anchored` false) measures the mesh points at ``σ² I`` alone.

The innovation gate (at the prediction) keeps a point only where the prediction expects it,
unless a camera's jolt put the whole prediction off (:func:`~.points.unless_off`, the rule the
trained points follow too).
"""

from __future__ import annotations

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.measurements import project_model_points
from quatrack.tracking.state import FilterState
from quatrack.viewsets.mesh import Mesh
from quatrack.viewsets.render import (cast_rays, depth_edges, face_normals, footprint, render_window, undistort_pixels,
                                      unit_pixel_rays)

from ..visibility import scaled_camera
from .params import TrackerParams
from .points import PointBlock, Tracks, gate, unless_off
from .sources import FrameContext, klt_block


def confident(state: FilterState, diameter: float, sigma_p: float, sigma_deg: float) -> bool:
    """The pose's 1-σ position error below ``sigma_p`` diameters and rotation below ``sigma_deg``."""
    P = state.pose_covariance
    sp = np.sqrt(max(np.linalg.eigvalsh(P[:3, :3])[-1], 0.0))
    sr = np.degrees(np.sqrt(max(np.linalg.eigvalsh(P[3:, 3:])[-1], 0.0)))
    return bool(sp < sigma_p * diameter and sr < sigma_deg)


def birth_mask(mesh: Mesh, ctx_camera, pose, params: TrackerParams) -> np.ndarray:
    """uint8 mask (image size) of pixels where a corner may be born: visible faces not seen
    at a grazing angle, ``mesh_edge_margin_px`` away from silhouette and depth edges.

    Worked out at half resolution on the object's box only (:func:`render_window` over its
    :func:`footprint`, grown by the erosion's radius + 3 px of background), then pasted into the
    half-size frame and enlarged: every pixel nearer the box's edge than the erosions reach is
    background, so the erosions and dilations there give what they give on the whole frame
    (tests/test_step_speed_equivalence.py compares it with the whole-frame form)."""
    cam = ctx_camera
    small = scaled_camera(cam, 0.5)
    r = max(1, int(round(0.5 * params.mesh_edge_margin_px)))
    box = footprint(mesh, small, pose, r + 3)
    if box is None:
        return np.zeros((cam.height, cam.width), np.uint8)
    out = np.zeros((small.height, small.width), np.uint8)
    x0, y0, x1, y1 = box
    buf = render_window(mesh, small, pose, (x0, y0, x1, y1))
    ok = buf.face >= 0
    if ok.any():
        normals = face_normals(mesh) @ pose.R.T  # camera frame
        # |cos| between the face and the view ray, on the object's pixels only (the rays are cached)
        face = buf.face[ok]
        rays = unit_pixel_rays(small)[y0:y1, x0:x1]
        ok[ok] = np.abs(np.einsum("nk,nk->n", normals[face], rays[ok])) >= params.visibility.min_cos
        ok &= ~depth_edges(buf)
        element = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)
        out[y0:y1, x0:x1] = cv2.erode(ok.astype(np.uint8), element)
    return cv2.resize(out * 255, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)


def corners_in_mask(gray: np.ndarray, mask: np.ndarray, n: int, quality: float, min_distance: float) -> np.ndarray | None:
    """``cv2.goodFeaturesToTrack(gray, n, quality, min_distance, mask=mask)`` as pixels (k, 2),
    None when it finds none — computed on the mask's box grown by 8 px instead of the frame.

    The corners' minimal eigenvalues (3×3 Sobel, 3×3 block) and the 3×3 local-maximum test read
    3 px round a pixel, so inside the box they are the frame's; the quality threshold is relative
    to the largest inside the mask, the candidates are met in the same (row-major) order and
    sorted alike, and the spacing test depends on distances only: the same corners
    (tests/test_step_speed_equivalence.py). Along an axis where the box would reach the image's
    border it spans the whole frame (OpenCV's filters treat a crop's last columns by its width)."""
    h, w = gray.shape[:2]
    bx, by, bw, bh = cv2.boundingRect(mask)  # (of its non-zero pixels)
    if bw == 0 or bh == 0:
        return None
    x0, x1 = bx - 8, bx + bw + 8
    y0, y1 = by - 8, by + bh + 8
    if x0 <= 0 or x1 >= w:
        x0, x1 = 0, w
    if y0 <= 0 or y1 >= h:
        y0, y1 = 0, h
    corners = cv2.goodFeaturesToTrack(np.ascontiguousarray(gray[y0:y1, x0:x1]), n, quality, min_distance,
                                      mask=np.ascontiguousarray(mask[y0:y1, x0:x1]))
    if corners is None:
        return None
    return corners.reshape(-1, 2).astype(float) + np.array([x0, y0], float)


def lift_jacobian(pose, X: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``Q G`` (n, 3, 6): how points ``X`` lifted by rays at ``pose`` onto faces of object-frame
    ``normals`` move (object frame) when the pose is off by ``δ = [δp, δθ]`` (see the module:
    ``G = Rᵀ [−I | [R X]×]``, ``Q = I − d nᵀ / (nᵀ d)``)."""
    R = pose.R
    RX = X @ R.T
    G = np.zeros((len(X), 3, 6))
    G[:, :, :3] = -R.T
    # [a]× column by column: [a]× e_k = a × e_k
    skew = np.zeros((len(X), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -RX[:, 2], RX[:, 1], -RX[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = RX[:, 2], -RX[:, 1], RX[:, 0]
    G[:, :, 3:] = R.T @ skew
    d = X - (-R.T @ pose.t)  # the rays, object frame
    nd = np.einsum("ni,ni->n", normals, d)
    Q = np.eye(3) - np.einsum("ni,nj->nij", d, normals) / nd[:, None, None]
    return Q @ G


def lifted_covariance(pose, X: np.ndarray, normals: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``Σ_X = Q G P Gᵀ Qᵀ`` (n, 3, 3): the object-frame uncertainty of points ``X`` lifted at
    ``pose`` whose covariance over ``[p, δθ]`` is ``P`` (:func:`lift_jacobian`)."""
    QG = lift_jacobian(pose, X, normals)
    return QG @ P @ np.swapaxes(QG, 1, 2)


def inherited_spread(camera, X: np.ndarray, cov_X: np.ndarray, cohort: np.ndarray, state: FilterState) -> np.ndarray:
    """``n_c J_X Σ_X J_Xᵀ`` (m, 2, 2) at the pose of ``state``: the pixel spread of the points'
    inherited uncertainty, each inflated by the number ``n_c`` of its cohort's points among
    ``X`` (one shared birth error, see the module)."""
    if len(X) == 0:
        return np.zeros((0, 2, 2))
    _, J = project_model_points(camera, X, state.p, state.R, True)
    JX = J[:, :, :3] @ state.R
    _, inv, counts = np.unique(cohort, return_inverse=True, return_counts=True)
    return counts[inv.ravel()][:, None, None] * (JX @ cov_X @ np.swapaxes(JX, 1, 2))


class MeshPoints:
    """Corners born on the mesh at the current pose, followed by KLT (see the module)."""

    name = "mesh"
    follows_klt = True  # its tracks join follow_together's one KLT call

    def __init__(self, mesh: Mesh, params: TrackerParams) -> None:
        self.mesh, self.params = mesh, params
        self.diameter = float(mesh.extent)
        self.reset()

    def __len__(self) -> int:
        return len(self.tracks)

    def reset(self) -> None:
        self.tracks = Tracks.empty()
        self.cov_X = np.zeros((0, 3, 3))  # Σ_X: each point's inherited uncertainty, object frame
        self.cohort = np.zeros(0, int)  # which birth (one shared pose error per cohort)
        # born at a pose the tracker reported (vouched for by the edges), not while it followed
        # an object mostly out of the image (Tracker._reacquire): only vouched points are
        # evidence for a pose in the edge refit; the others agree with the pose they were lifted at
        self.vouched = np.zeros(0, bool)
        self.ema = np.zeros(0)
        self._since_spawn = 10**9
        self._births = 0
        self._idx = np.zeros(0, int)

    def measure(self, ctx: FrameContext, timings: dict) -> PointBlock:
        block, idx = klt_block(self.name, self.mesh, ctx, self.tracks, self.params, timings)
        if len(block):
            if ctx.anchored:  # (unanchored, the birth error is the state's own: see the module)
                block.C = block.C + inherited_spread(ctx.camera, block.X, self.cov_X[idx], self.cohort[idx], ctx.prior)
            g = unless_off(gate(ctx.camera, block, ctx.prior, self.params.gate_chi2), self.params.min_inliers)
            block, idx = block.keep(g), idx[g]
        self._idx = idx
        return block

    def settle(self, ctx: FrameContext, block: PointBlock, inliers: np.ndarray, state: FilterState) -> None:
        p = self.params
        idx = self._idx[inliers]
        kept = block.keep(inliers)
        if len(kept):
            uv, _ = project_model_points(ctx.camera, kept.X, state.p, state.R, False)
            err = np.linalg.norm(uv - kept.uv, axis=1)
            ema = 0.7 * self.ema[idx] + 0.3 * err
            alive = ema < p.mesh_retire_px
            self.tracks, self.ema = kept.tracks.keep(alive), ema[alive]
            self.cov_X, self.cohort = self.cov_X[idx][alive], self.cohort[idx][alive]
            self.vouched = self.vouched[idx][alive]
        else:
            self.tracks, self.ema = Tracks.empty(), np.zeros(0)
            self.cov_X, self.cohort = np.zeros((0, 3, 3)), np.zeros(0, int)
            self.vouched = np.zeros(0, bool)
        self._since_spawn += 1
        if (self._since_spawn >= p.mesh_spawn_every and len(self.tracks) < 0.7 * p.mesh_max_points and ctx.vouched
                and confident(state, self.diameter, p.mesh_spawn_sigma_p, p.mesh_spawn_sigma_deg)):
            self.spawn(ctx, state)

    def _lifted(self, camera: PinholeCamera, state: FilterState, uv: np.ndarray) -> tuple[Tracks, np.ndarray]:
        """The pixels ``uv`` lifted onto the mesh at ``state``'s pose (those whose ray hits a face
        seen at ``cos ≥ visibility.min_cos``) and their 3-D covariances inherited from the pose's."""
        pose = state.pose
        X, face, cos = cast_rays(self.mesh, pose, undistort_pixels(camera, uv))
        ok = (face >= 0) & (cos >= self.params.visibility.min_cos)
        cov = lifted_covariance(pose, X[ok], face_normals(self.mesh)[face[ok]], state.pose_covariance)
        return Tracks(X[ok], np.asarray(uv)[ok]), cov

    def relift(self, camera: PinholeCamera, state: FilterState) -> int:
        """Every point lifted again, from where it is seen now, onto the mesh at ``state``'s pose
        (a pose the tracker moved to because its points had drifted with it: Tracker._texture_audit);
        they form one new cohort, not vouched for (the pose is not reported). Returns how many hit
        the mesh (the others are dropped)."""
        if not len(self.tracks):
            return 0
        self.tracks, self.cov_X = self._lifted(camera, state, self.tracks.uv)
        n = len(self.tracks)
        self.cohort, self._births = np.full(n, self._births), self._births + 1
        self.vouched, self.ema = np.zeros(n, bool), np.zeros(n)
        return n

    def spawn(self, ctx: FrameContext, state: FilterState, vouched: bool = True) -> int:
        """Detect corners on the visible mesh in this frame and lift them at ``state``'s pose
        (``vouched``: a pose the tracker reports; see :attr:`vouched`)."""
        p = self.params
        cam = ctx.camera
        pose = state.pose
        mask = birth_mask(self.mesh, cam, pose, p)
        m = int(p.klt.win // 2 + 1)
        mask[:m], mask[-m:], mask[:, :m], mask[:, -m:] = 0, 0, 0, 0
        for u, v in np.rint(self.tracks.uv).astype(int):
            cv2.circle(mask, (int(u), int(v)), int(p.mesh_min_distance_px), 0, -1)
        n_new = p.mesh_max_points - len(self.tracks)
        self._since_spawn = 0
        if n_new <= 0 or not mask.any():
            return 0
        uv = corners_in_mask(ctx.frame.gray, mask, n_new, p.mesh_quality, p.mesh_min_distance_px)
        if uv is None:
            return 0
        born, cov = self._lifted(cam, state, uv)
        n = len(born)
        if not n:
            return 0
        self.tracks = self.tracks + born
        self.cov_X = np.concatenate([self.cov_X, cov])
        self.cohort = np.concatenate([self.cohort, np.full(n, self._births)])
        self.vouched = np.concatenate([self.vouched, np.full(n, vouched)])
        self._births += 1
        self.ema = np.concatenate([self.ema, np.zeros(n)])
        return n

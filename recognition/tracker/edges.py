"""Model edges measured in the image: the moving-edges idea (Bouthemy 1989; ViSP's ``vpMe``).

The mesh's sharp edges (faces meeting at more than ``edge_crease_deg``; on a box all twelve)
are sampled every ``edge_step_px`` pixels at the predicted pose; samples the visibility
z-buffer does not show are dropped (:func:`~..visibility.edge_samples_visible`: one of the
edge's own faces seen next to it, or nothing nearer). From each visible sample a 1-D search
along the projected edge's normal ``n`` finds the strongest image gradient whose direction
agrees with ``n`` (|cos| ≥ 0.9), within ``±r``, ``r = 3·√(nᵀ J P Jᵀ n)`` (the prediction's
spread across the edge, 2–15 px) but no further than halfway to another, parallel model edge
(:func:`~..visibility.model_gap`: a face seen edge-on is a strip a few px wide), refined to
sub-pixel by a parabola through the three gradient values. A sample
whose search also meets a *rival* — another aligned maximum more than 2 px away at least
``edge_ambiguity`` (0.5) times as strong: a crease beside a parallel line of the print, an
outline beside the background's edge — is dropped: the search cannot tell which edge is the
model's, and taking the stronger locked whole edges on the print (rendered zoo walks, 30 fps:
mean error −0.08 % of the diameter and −0.13° over six objects; bench/RESULTS.md, session 24).

A sample measures only the edge's position *across* it: it becomes a point residual with the
anisotropic covariance ``C = σ⊥² n nᵀ + σ∥² t tᵀ`` (``t`` along the edge, ``σ∥`` large), i.e.
Ude's point-to-line distance in the form the other sources use (:class:`~.points.PointBlock`),
gated and robustly weighted with them. Edges carry the pose where texture is weak or new.

Honest ``σ⊥``: a variance factor estimated from the samples' posterior residuals
(:class:`~.points.VarianceFactor`, the median over the inliers, floored at 1) scales ``σ⊥`` to
what the images show. (The samples of one model edge share part of their error — a search
locked onto the print's edge next to the outline is off along the whole edge — but inflating
each sample by its edge's count, ``σ⊥² + n_e σ_c²``, made the pose lean on the mesh-born points
and measured worse in both error and NEES on rendered orbits: not done.)
"""

from __future__ import annotations

import cv2
import numpy as np

from quatrack.tracking.jit import lazily_compiled
from quatrack.tracking.measurements import project_model_points
from quatrack.tracking.state import FilterState
from quatrack.viewsets.mesh import Mesh

from ..visibility import edge_samples_visible, model_gap, segment_samples, sharp_edges
from .params import TrackerParams
from .points import PointBlock, VarianceFactor, mahalanobis2, posterior_m2
from .sources import FrameContext

_SIGMA_ALONG_PX = 50.0  # an edge sample says nothing along the edge
_MAX_RADIUS_PX = 15.0  # the 1-D search reaches at most this far from the prediction


def edge_points(mesh: Mesh, edges3d: np.ndarray, camera, state: FilterState, params: TrackerParams,
                zbuffer, edge_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Visible samples on the sharp model edges ``edges3d`` (k, 2, 3), which border the faces
    ``edge_faces`` (k, 2) (:func:`~..visibility.sharp_edges`), at the pose of ``state``: object
    points (n, 3), unit image normals (n, 2) of their projected edges, and their edges (n,)."""
    E = edges3d
    if len(E) == 0:
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, int)
    pose = state.pose
    A, B = pose.apply(E[:, 0]), pose.apply(E[:, 1])
    front = (A[:, 2] > 1e-9) & (B[:, 2] > 1e-9)
    seg, Xc, uv, normal = segment_samples(A[front], B[front], camera, params.edge_step_px)
    X = (Xc - pose.t) @ pose.R
    w, h = camera.width, camera.height
    m = params.visibility.margin_px
    ok = (uv[:, 0] >= m) & (uv[:, 1] >= m) & (uv[:, 0] <= w - 1 - m) & (uv[:, 1] <= h - 1 - m)
    ok &= edge_samples_visible(zbuffer, uv, Xc[:, 2], np.asarray(edge_faces)[front][seg], mesh.plane_ids, (w, h),
                               params.visibility.depth_tol * mesh.extent)
    return X[ok], normal[ok], np.flatnonzero(front)[seg][ok]


def search_edges(gx: np.ndarray, gy: np.ndarray, uv: np.ndarray, normal: np.ndarray, radius: np.ndarray,
                 min_grad: float) -> tuple[np.ndarray, np.ndarray]:
    """1-D search along ``normal`` from ``uv`` within ``±radius`` px for the strongest gradient
    aligned with the normal; returns the measured points (n, 2) and a found mask (n,)."""
    meas, found, _ = edge_candidates(gx, gy, uv, normal, radius, min_grad)
    return meas, found


def edge_candidates(gx: np.ndarray, gy: np.ndarray, uv: np.ndarray, normal: np.ndarray, radius: np.ndarray,
                    min_grad: float, ambiguity: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`search_edges`, and for each sample the distance (px, along the normal) from the
    strongest aligned gradient to its strongest *rival*: another local maximum, more than 2 px
    away, reaching ``ambiguity ×`` its strength (0 where there is none). A rival means two
    edges in reach — a crease beside a parallel line of the print — of which the search cannot
    tell which is the model's (the edge counterpart of Lowe's ratio test): the measurement is
    uncertain by about their distance.

    Along each sample's line, at whole-pixel offsets ``o`` within ``±radius``, the image
    gradient ``g`` (nearest pixel) scores ``|g·n|`` where it is aligned with the normal
    (``|g·n| ≥ 0.9 |g|``) and at least ``min_grad`` strong; the best score's offset is refined by
    a parabola through its neighbours' scores (at most ±½ px). Runs compiled (:func:`_candidates`,
    numba; the numpy version, a (samples × offsets) array per step, cost ~1.4 ms a frame), with
    the numpy version's arithmetic and dtypes, so the same bits (tests/test_tracker_sources.py).
    """
    n = len(uv)
    rmax = int(np.ceil(radius.max())) if n else 0
    meas = np.empty((n, 2))
    found = np.zeros(n, bool)
    gap = np.zeros(n)
    # (numpy compares a float32 array with a Python float in float32, with a numpy float64 in float64)
    grad = np.float32(min_grad) if isinstance(min_grad, (int, float)) else np.float64(min_grad)
    _compiled_candidates()(np.ascontiguousarray(gx), np.ascontiguousarray(gy), np.ascontiguousarray(uv, float),
                           np.ascontiguousarray(normal, float), np.ascontiguousarray(radius, float), rmax, grad,
                           float(ambiguity), meas, found, gap)
    return meas, found, gap


def _candidates(gx, gy, uv, normal, radius, rmax, min_grad, ambiguity, meas, found, gap):  # pragma: no cover (compiled)
    """The per-sample search of :func:`edge_candidates`, compiled (one line of ``2·rmax + 1``
    offsets at a time)."""
    h, w = gx.shape
    K = 2 * rmax + 1
    score = np.empty(K)
    for i in range(uv.shape[0]):
        n0, n1 = normal[i, 0], normal[i, 1]
        for k in range(K):
            o = float(k - rmax)
            px = uv[i, 0] + o * n0
            py = uv[i, 1] + o * n1
            ui = min(max(int(np.rint(px)), 0), w - 1)
            vi = min(max(int(np.rint(py)), 0), h - 1)
            ex, ey = gx[vi, ui], gy[vi, ui]
            gn = abs(np.float64(ex) * n0 + np.float64(ey) * n1)
            mag = np.hypot(ex, ey)
            ok = abs(o) <= radius[i] and gn >= np.float32(0.9) * mag and mag >= min_grad
            ok = ok and px >= 0 and py >= 0 and px <= w - 1 and py <= h - 1
            score[k] = gn if ok else -1.0
        j = 0
        for k in range(1, K):
            if score[k] > score[j]:
                j = k
        best = score[j]
        found[i] = best > 0
        if ambiguity < 1.0:
            kk, top = 0, -np.inf
            for k in range(K):
                left = score[k - 1] if k > 0 else -1.0
                right = score[k + 1] if k < K - 1 else -1.0
                peak = score[k] > 0 and score[k] >= left and score[k] >= right
                rival = score[k] if peak and abs(k - j) > 2 else 0.0
                if rival > top:
                    kk, top = k, rival
            if best > 0 and top >= ambiguity * best:
                gap[i] = abs(float(kk - rmax) - float(j - rmax))
        jl, jr = max(j - 1, 0), min(j + 1, K - 1)
        a, b, c = max(score[jl], 0.0), max(score[j], 0.0), max(score[jr], 0.0)
        den = a - 2 * b + c
        frac = 0.5 * (a - c) / den if (jl != j and jr != j and den < 0) else 0.0
        off = float(j - rmax) + min(max(frac, -0.5), 0.5)
        meas[i, 0] = uv[i, 0] + off * n0
        meas[i, 1] = uv[i, 1] + off * n1


_compiled_candidates = lazily_compiled(_candidates)


def gradients(gray: np.ndarray, uv: np.ndarray, pad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sobel gradients (/8) of the σ = 1 blurred image, only over the box round the pixels ``uv``
    grown by ``pad`` (the search's reach; the edges of a small object do not need the whole
    frame's): ``(gx, gy, origin)``, ``origin`` the box's top-left pixel (x, y)."""
    h, w = gray.shape
    x0 = int(max(np.floor(uv[:, 0].min() - pad) - 8, 0))
    y0 = int(max(np.floor(uv[:, 1].min() - pad) - 8, 0))
    x1 = int(min(np.ceil(uv[:, 0].max() + pad) + 9, w))
    y1 = int(min(np.ceil(uv[:, 1].max() + pad) + 9, h))
    roi = gray[y0:y1, x0:x1].astype(np.float32)
    g = cv2.GaussianBlur(roi, (0, 0), 1.0)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return gx, gy, np.array([float(x0), float(y0)])


def fit_image(grey: np.ndarray, mesh: Mesh, camera, pose, params, reach: float):
    """What :func:`recognition.evidence.edge_fit` needs of :func:`~recognition.evidence.measure_edges`
    (its :class:`~recognition.evidence.EdgeImage`) without the agreement and chance tests that
    measure_edges also makes: the tracker's audit asks only how far the refit moves the pose.

    The same visible samples (``_edge_samples``) and the same crop (measure_edges' box: the
    samples' box grown by ``0.25 size + radius_px + radius_share × size + 2``, where its chance
    test looks), but gradients computed only where the fit reads them: the samples' box grown by
    the fit's reach ``r = radius_px + (radius_share + reach) × size`` plus 8 px (zero beyond),
    spanning the whole crop along an axis where the crop meets the image's border (there
    OpenCV's filters depend on the crop's width or height in the last bits). With ``s`` =
    :func:`~recognition.evidence.gradient_scale` (1 for images of 640 px and less) the part is
    grown by ``8 s`` px more, so every pixel the fit reads lies at least ``8 s − 1`` px inside it,
    and the σ = ``s`` blur (``4 s`` px of taps each side) and the 3×3 Sobel read at most
    ``4 s + 1`` px round a pixel: the gradients there are the full crop's bit for bit; the crop's
    origin is the same, so are the coordinates: the fit is the same (tests/test_step_speed_equivalence.py
    compares the two). None when no sample is visible (as measure_edges)."""
    from ..evidence import EdgeImage, _edge_samples, gradient_scale, image_gradients

    uv, normal, seg, X = _edge_samples(mesh, camera, pose, params, None, 0.5)
    if len(uv) == 0:
        return None
    span = np.ptp(uv, axis=0)
    size = float(max(np.hypot(*span), 8.0))
    h, w = grey.shape[:2]

    def box(pad: int) -> tuple[int, int, int, int]:
        lo = np.floor(uv.min(axis=0)) - pad
        hi = np.ceil(uv.max(axis=0)) + pad
        return int(max(lo[0], 0)), int(max(lo[1], 0)), int(min(hi[0] + 1, w)), int(min(hi[1] + 1, h))

    radius = params.radius_px + params.radius_share * size
    full = box(int(np.ceil(0.25 * size + radius + 2)))  # measure_edges' crop
    part = box(int(np.ceil(radius + reach * size)) + int(np.ceil(8 * gradient_scale(grey.shape))))
    part = [max(part[0], full[0]), max(part[1], full[1]), min(part[2], full[2]), min(part[3], full[3])]
    # where the crop meets the image's border, OpenCV's filters treat its last columns (rows)
    # by the crop's width (height) — a part of another width differs there in the last bits —
    # so along an axis that meets the border the part spans the full crop
    if part[0] == 0 or part[2] == w:
        part[0], part[2] = full[0], full[2]
    if part[1] == 0 or part[3] == h:
        part[1], part[3] = full[1], full[3]
    gx_p, gy_p, _ = image_gradients(grey, part)
    gx = np.zeros((full[3] - full[1], full[2] - full[0]), np.float32)
    gy = np.zeros_like(gx)
    rows, cols = slice(part[1] - full[1], part[3] - full[1]), slice(part[0] - full[0], part[2] - full[0])
    gx[rows, cols], gy[rows, cols] = gx_p, gy_p
    return EdgeImage(uv, normal, X, gx, gy, (full[0], full[1]), size, seg)


class ModelEdges:
    """Measurement source: visible sharp model edges (see the module). It keeps no tracks: the
    edges are searched afresh in every frame around their predicted position."""

    name = "edges"

    def __init__(self, mesh: Mesh, params: TrackerParams) -> None:
        self.mesh, self.params = mesh, params
        self.edges3d, self.edge_faces = sharp_edges(mesh, params.edge_crease_deg)
        self.factor = VarianceFactor(1)

    def __len__(self) -> int:
        return 0

    def reset(self) -> None:
        self.factor.reset()

    def measure(self, ctx: FrameContext, timings: dict) -> PointBlock:
        import time

        t0 = time.perf_counter()
        p = self.params
        X, normal, edge = edge_points(self.mesh, self.edges3d, ctx.camera, ctx.prior, p, ctx.zbuffer(self.mesh, p),
                                      self.edge_faces)
        empty = PointBlock(self.name, np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2, 2)))
        if len(X) == 0:
            return empty
        uv, J = project_model_points(ctx.camera, X, ctx.prior.p, ctx.prior.R, True)
        S = J @ ctx.prior.pose_covariance @ np.swapaxes(J, 1, 2)
        spread = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", normal, S, normal), 0.0))
        radius = np.clip(3.0 * spread, 2.0, _MAX_RADIUS_PX)
        # no further than halfway to another model edge parallel to it (a thin strip's other
        # side); only a gap below twice the longest search can shorten one, so none further is
        # looked for (fewer pairs: the prediction's spread keeps most searches at 2–5 px)
        reach = min(_MAX_RADIUS_PX, 2.0 * float(radius.max()))
        radius = np.minimum(radius, np.maximum(0.5 * model_gap(uv, normal, edge, reach, p.edge_step_px), 1.0))
        gx, gy, origin = gradients(ctx.frame.gray, uv, float(radius.max()) + 4.0)
        ambiguity = 1.0 if p.edge_ambiguity is None else p.edge_ambiguity
        meas, found, gap = edge_candidates(gx, gy, uv - origin, normal, radius, p.edge_min_grad, ambiguity)
        found &= gap == 0  # two edges in reach: which one is the model's? (edge_candidates)
        meas = meas + origin
        X, meas, normal = X[found], meas[found], normal[found]
        t = np.column_stack([-normal[:, 1], normal[:, 0]])
        var = np.full(len(X), self.factor.value * p.edge_sigma_px**2)
        C = (var[:, None, None] * np.einsum("ni,nj->nij", normal, normal)
             + _SIGMA_ALONG_PX**2 * np.einsum("ni,nj->nij", t, t))
        block = PointBlock(self.name, X, meas, C)
        # the innovation gate (points.gate) with the projections and J P Jᵀ already at hand
        block = block.keep(mahalanobis2(meas - uv[found], S[found] + C) < p.gate_chi2)
        timings["edges"] = (time.perf_counter() - t0) * 1e3
        return block

    def settle(self, ctx: FrameContext, block: PointBlock, inliers: np.ndarray, state: FilterState) -> None:
        self.factor.update(posterior_m2(ctx.camera, block.keep(inliers), state))

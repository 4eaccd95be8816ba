"""The object's outline, found by colour statistics: a sparse region-based measurement source.

Edges (:mod:`.edges`) find the outline as the strongest image gradient near it, and the print
beside the outline, a background edge, motion blur or a dimmer light fool them. Region-based
trackers (PWP3D, RBOT; here the sparse form of Stoiber et al., *SRT3D: A Sparse Region-Based 3D
Object Tracking Approach for the Real World*, IJCV 2022) ask instead where the object's
*colours* end: what lies inside the outline looks like the object, what lies outside like the
background round it. Every frame:

1. **Contour lines.** The silhouette's edges at the prediction — mesh edges between a face that
   turns to the camera and one that turns away, and the mesh's boundary edges — are sampled
   every ``contour_step_px``; a sample is kept where the visibility z-buffer shows the object on
   one side of it and background on the other (the outer outline, not a part of the object
   in front of another), and its image normal ``n`` is turned outwards. Along ``n``, pixels
   ``x = −L … L`` (px from the predicted outline, ``L`` = the search reach + ``contour_margin_px``)
   are read; where the z-buffer says the line has crossed the object to its other side, or
   left the image, a pixel tells nothing (``p = ½``).
2. **Pixel posteriors.** Colour histograms of the object ``h_f`` and of its surroundings ``h_b``
   (16³ bins of BGR; a grey image fills the diagonal) give ``p_f(y) = h_f(y) / (h_f(y) + h_b(y))``.
   With ``contour_normalise`` (off by default: see its comment) a pixel is read relative to its
   frame's mean colour (:func:`frame_gains`: each channel × 128 / its mean), so a change of light
   that scales the whole image (the zoo's dimming with a colour cast, a camera's auto-exposure)
   leaves the bins where the histograms learned them. Read raw, a gain of 0.6 with a cast moved
   the found outline from 0.3 to 9.5 px off the true one on a rendered box
   (tests/test_tracker_sources.py).
3. **The outline's position along the line.** With smoothed step functions
   ``h_F(x) = ½ − α tanh(x / 2s)``, ``h_B = 1 − h_F`` (α = ``contour_alpha``, s =
   ``contour_slope_px``: the object's inside is probably object, its outside probably not,
   never certainly), the outline lies at ``d`` with probability
   ``P(d) ∝ ∏ₓ [h_F(x − d) p_f(yₓ) + h_B(x − d) (1 − p_f(yₓ))]`` (SRT3D eq. 12), for ``d`` within
   ``±r``, ``r = 3·√(nᵀ J P Jᵀ n)`` (the prediction's spread across the outline). Its mean
   ``μ`` and variance ``σ²`` are the measurement: the outline point is at ``uv + μ n``, with the
   covariance ``κ max(σ², σ_min²) n nᵀ + σ∥² t tᵀ`` across and along the outline (the
   point-to-line form of the edges), ``κ`` a variance factor learned from the posterior
   residuals (:class:`~.points.VarianceFactor`: neighbouring pixels are not independent, so
   ``σ²`` alone is too sure). A line whose ``μ`` ends at its reach, or whose ``σ`` spans half of
   it, says nothing and is dropped.
4. **Learning the colours.** After the adjustment, where the posterior's outline lies along each
   kept line, the pixels more than 2 px inside update ``h_f`` and those more than 2 px outside
   ``h_b`` (exponential forgetting: ``h ← (1 − a) h + a ĥ``, ``a`` = ``contour_rate_f`` / ``_b``; the
   first frame of a track sets them) — only from frames whose pose the tracker reports.

A line is one 1-D measurement, like an edge sample, so the outline joins the filter as a
:class:`~.points.PointBlock` and is gated and robustly weighted with the other sources.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from quatrack.tracking.measurements import project_model_points
from quatrack.tracking.state import FilterState
from quatrack.viewsets.mesh import Mesh

from ..visibility import segment_samples
from .params import TrackerParams
from .points import PointBlock, VarianceFactor, mahalanobis2, posterior_m2
from .sources import FrameContext

_SIGMA_ALONG_PX = 50.0  # a line says nothing along the outline
_BINS = 16  # per colour channel
_PRIOR = 1e-4  # added to every histogram bin (no colour is impossible)


def silhouette_samples(mesh: Mesh, camera, pose, step_px: float, zbuffer, scale: float,
                       margin_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Samples of the object's outer outline at ``pose``: object points (n, 3) on silhouette
    edges and their image normals (n, 2), turned outwards (see the module, step 1). ``zbuffer``
    is the visibility render at ``scale`` of the image."""
    edges, faces, _ = mesh.edge_faces
    V = np.asarray(mesh.vertices, float)
    normals = mesh.face_normals
    eye = -pose.R.T @ pose.t  # the camera's centre, object frame
    tri0 = V[np.asarray(mesh.faces)[:, 0]]
    front = np.einsum("ij,ij->i", normals, eye[None] - tri0) > 0
    f0 = front[faces[:, 0]]
    f1 = np.where(faces[:, 1] >= 0, front[np.maximum(faces[:, 1], 0)], ~f0)
    sil = f0 != f1
    if not sil.any():
        return np.zeros((0, 3)), np.zeros((0, 2))
    A, B = pose.apply(V[edges[sil, 0]]), pose.apply(V[edges[sil, 1]])
    front = (A[:, 2] > 1e-9) & (B[:, 2] > 1e-9)
    _, Xc, uv, n = segment_samples(A[front], B[front], camera, step_px)
    X = (Xc - pose.t) @ pose.R
    w, h = camera.width, camera.height
    inside = (uv[:, 0] >= margin_px) & (uv[:, 1] >= margin_px) & (uv[:, 0] <= w - 1 - margin_px) & (uv[:, 1] <= h - 1 - margin_px)
    # which side is the object's: the z-buffer a little beyond the z-buffer's own pixel each way
    obj = zbuffer.face >= 0
    reach = 1.5 / scale + 1.0
    sh, sw = obj.shape

    def on_object(p):
        ui = np.clip(np.rint((p[:, 0] + 0.5) * scale - 0.5).astype(int), 0, sw - 1)
        vi = np.clip(np.rint((p[:, 1] + 0.5) * scale - 0.5).astype(int), 0, sh - 1)
        return obj[vi, ui]

    plus, minus = on_object(uv + reach * n), on_object(uv - reach * n)
    keep = inside & (plus != minus)
    n = np.where(plus[:, None], -n, n)  # outwards: towards the background
    return X[keep], n[keep]


def bin_index(bgr: np.ndarray) -> np.ndarray:
    """The histogram bin of BGR pixels (…, 3) uint8: ``_BINS`` levels per channel; in a grey
    image (every pixel's channels equal) the same ``_BINS³`` bins hold ``_BINS³`` grey levels
    instead (all 256: a grey image has only its brightness to tell the object by, and 16
    levels of it lost the outline on a rendered box over clutter).

    >>> int(bin_index(np.array([[255, 255, 255]], np.uint8))[0]), int(bin_index(np.array([[0, 0, 255]], np.uint8))[0])
    (255, 15)
    """
    if np.array_equal(bgr[..., 0], bgr[..., 1]) and np.array_equal(bgr[..., 1], bgr[..., 2]):
        return bgr[..., 0].astype(np.int32)
    q = (bgr >> 4).astype(np.int32)
    return (q[..., 0] * _BINS + q[..., 1]) * _BINS + q[..., 2]


def frame_gains(image: np.ndarray) -> np.ndarray:
    """Per-channel gains (3,) that bring ``image``'s mean colour to mid-grey: ``128 / mean``,
    within ¼…4 (a black frame stays a black frame). A grey image's channels have one mean, so
    they get one gain and its pixels stay grey (:func:`bin_index`'s grey path).

    >>> img = np.full((4, 4, 3), (32, 64, 128), np.uint8)
    >>> frame_gains(img).tolist()
    [4.0, 2.0, 1.0]
    """
    m = np.asarray(cv2.mean(image)[:3], np.float32)
    return np.clip(128.0 / np.maximum(m, 1.0), 0.25, 4.0).astype(np.float32)


@dataclass
class ColourModel:
    """Normalised colour histograms of the object (``fg``) and of its surroundings (``bg``)."""

    fg: np.ndarray | None = None
    bg: np.ndarray | None = None

    @property
    def ready(self) -> bool:
        return self.fg is not None

    def posterior(self, bins: np.ndarray) -> np.ndarray:
        """``p_f = h_f / (h_f + h_b)`` per pixel bin."""
        f, b = self.fg[bins] + _PRIOR, self.bg[bins] + _PRIOR
        return f / (f + b)

    def update(self, fg_bins: np.ndarray, bg_bins: np.ndarray, rate_f: float, rate_b: float) -> None:
        """Blend in the histograms of these pixels (the first call sets them)."""
        if len(fg_bins) < 20 or len(bg_bins) < 20:
            return
        hf = np.bincount(fg_bins, minlength=_BINS**3).astype(float)
        hb = np.bincount(bg_bins, minlength=_BINS**3).astype(float)
        hf /= hf.sum()
        hb /= hb.sum()
        if self.fg is None:
            self.fg, self.bg = hf, hb
        else:
            self.fg = (1 - rate_f) * self.fg + rate_f * hf
            self.bg = (1 - rate_b) * self.bg + rate_b * hb


def outline_posterior(p_f: np.ndarray, x: np.ndarray, radius: np.ndarray, alpha: float,
                      slope: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each line's outline lies (see the module, step 3): for pixel posteriors ``p_f``
    (n, L) at whole-pixel offsets ``x`` (L,) along the lines and search radii ``radius`` (n,),
    the mean ``μ`` and variance ``σ²`` of ``P(d)`` over the whole pixels ``d`` within
    ``±radius``, and ``P(d)`` itself (n, D) over ``d = −R … R`` (``R`` the largest radius).

    ``log P(d) = Σₓ log(1 − p_f + h_F(x − d)(2p_f − 1))`` + const. The smoothed step is flat
    beyond ``w = ⌈5.5 s⌉`` px of ``d`` (``tanh(w / 2s) > 0.99``, ``h_F`` within ``0.005 α`` of
    ``½ ± α``), so the terms beyond come from two running sums of their flat values and only
    ``2w + 1`` terms per candidate are evaluated: about a quarter of the work of the whole
    product, the same ``μ`` within ~0.01 px.

    A line that is object up to 3 px outside the predicted outline and background beyond:

    >>> x = np.arange(-12.0, 13.0)
    >>> p = np.where(x <= 3, 0.9, 0.1)[None]
    >>> mu, var, _ = outline_posterior(p, x, np.array([8.0]), 0.43, 1.3)
    >>> round(float(mu[0]), 1), round(float(np.sqrt(var[0])), 1)  # (the step lies between 3 and 4)
    (3.5, 1.5)
    """
    n, L = p_f.shape
    R = int(np.ceil(radius.max())) if len(radius) else 0
    d = np.arange(-R, R + 1, dtype=float)
    w = int(np.ceil(5.5 * slope))
    a = 1.0 - p_f
    q = 2.0 * p_f - 1.0  # the mixture: (1 − p) + h_F (2p − 1)
    inside = np.log(np.maximum(a + (0.5 + alpha) * q, 1e-12))  # h_F far inside the outline
    outside = np.log(np.maximum(a + (0.5 - alpha) * q, 1e-12))  # … far outside it
    before = np.concatenate([np.zeros((n, 1)), np.cumsum(inside, axis=1)], axis=1)  # Σ over indices < j
    after = np.concatenate([np.cumsum(outside[:, ::-1], axis=1)[:, ::-1], np.zeros((n, 1))], axis=1)  # ≥ j
    centre = np.rint(d - x[0]).astype(int)  # index of x = d
    t = np.arange(-w, w + 1)
    J = centre[:, None] + t[None, :]  # (D, 2w+1)
    valid = (J >= 0) & (J < L)
    Jc = np.clip(J, 0, L - 1)
    hF = 0.5 - alpha * np.tanh(t / (2.0 * slope))  # h_F(x − d) at x − d = t
    a32, q32 = a.astype(np.float32), q.astype(np.float32)  # (the bulk of the work: single precision)
    mix = a32[:, Jc] + hF.astype(np.float32)[None, None, :] * q32[:, Jc]  # (n, D, 2w+1)
    np.maximum(mix, np.float32(1e-12), out=mix)
    np.log(mix, out=mix)
    mix[:, ~valid] = 0.0
    near = mix.sum(axis=2, dtype=np.float64)
    lo, hi = np.clip(centre - w, 0, L), np.clip(centre + w + 1, 0, L)
    ll = before[:, lo] + near + after[:, hi]
    ll = np.where(np.abs(d)[None, :] <= radius[:, None], ll, -np.inf)
    ll -= ll.max(axis=1, keepdims=True)
    P = np.exp(ll)
    P /= P.sum(axis=1, keepdims=True)
    mu = P @ d
    var = np.einsum("nd,nd->n", P, (d[None, :] - mu[:, None]) ** 2)
    return mu, var, P


class Contour:
    """Measurement source: the object's outline located by colour statistics (see the module).
    It keeps no tracks, only the colour histograms it learns while the track lasts."""

    name = "contour"

    def __init__(self, mesh: Mesh, params: TrackerParams) -> None:
        self.mesh, self.params = mesh, params
        self.factor = VarianceFactor(1)
        self.colours = ColourModel()
        # this frame's lines, for settle: (bins, informative, x, normals, uv at the prior, kept)
        self._lines: tuple | None = None

    def __len__(self) -> int:
        return 0

    def reset(self) -> None:
        self.factor.reset()
        self.colours = ColourModel()
        self._lines = None

    def _read_lines(self, ctx: FrameContext, normal: np.ndarray, uv: np.ndarray, reach: np.ndarray):
        """Pixel bins along each line (n, 2L+1), their offsets ``x`` (2L+1,), and which pixels
        say anything: inside the image, and on this outline's two sides (:func:`side_runs`)."""
        p = self.params
        L = int(np.ceil(reach.max() + p.contour_margin_px))
        x = np.arange(-L, L + 1, dtype=float)
        P = uv[:, None, :] + x[None, :, None] * normal[:, None, :]  # (n, 2L+1, 2)
        h, w = ctx.image.shape[:2]
        ui, vi = np.rint(P[..., 0]).astype(int), np.rint(P[..., 1]).astype(int)
        inside = (ui >= 0) & (vi >= 0) & (ui < w) & (vi < h)
        # (np.take of flat indices: the same pixels as image[v, u], at ~¼ of fancy indexing's time)
        flat = np.clip(vi, 0, h - 1) * w + np.clip(ui, 0, w - 1)
        pix = np.take(ctx.image.reshape(h * w, -1), flat, axis=0).reshape(flat.shape + ctx.image.shape[2:])
        if p.contour_normalise:  # (relative to the frame's mean colour: see the module, step 2)
            pix = np.clip(pix.astype(np.float32) * frame_gains(ctx.image), 0, 255).astype(np.uint8)
        bins = bin_index(pix)
        zb = ctx.zbuffer(self.mesh, p)
        s = p.visibility.scale
        sh, sw = zb.face.shape
        zi = np.clip(np.rint((P[..., 0] + 0.5) * s - 0.5).astype(int), 0, sw - 1)
        zj = np.clip(np.rint((P[..., 1] + 0.5) * s - 0.5).astype(int), 0, sh - 1)
        on = np.take(zb.face, zj * sw + zi) >= 0
        return bins, inside & side_runs(on, x, 2.0 / s + reach), x

    def measure(self, ctx: FrameContext, timings: dict) -> PointBlock:
        t0 = time.perf_counter()
        p = self.params
        empty = PointBlock(self.name, np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2, 2)))
        self._lines = None
        X, normal = silhouette_samples(self.mesh, ctx.camera, ctx.prior.pose, p.contour_step_px,
                                       ctx.zbuffer(self.mesh, p), p.visibility.scale, 2.0)
        if len(X) == 0:
            return empty
        uv, J = project_model_points(ctx.camera, X, ctx.prior.p, ctx.prior.R, True)
        S = J @ ctx.prior.pose_covariance @ np.swapaxes(J, 1, 2)
        spread = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", normal, S, normal), 0.0))
        radius = np.clip(3.0 * spread, 3.0, p.contour_max_reach_px)
        bins, informative, x = self._read_lines(ctx, normal, uv, radius)
        if not self.colours.ready:  # a track's first frame: its colours from the prediction
            self.colours.update(bins[informative & (x[None, :] < -2)], bins[informative & (x[None, :] > 2)], 1.0, 1.0)
        pf = np.where(informative, self.colours.posterior(bins), 0.5)
        mu, var, _ = outline_posterior(pf, x, radius, p.contour_alpha, p.contour_slope_px)
        sd = np.sqrt(var)
        kept = (np.abs(mu) < radius - 0.5) & (sd < 0.5 * radius) & (informative.sum(axis=1) >= 0.5 * len(x))
        if not kept.any():
            timings["contour"] = (time.perf_counter() - t0) * 1e3
            return empty
        n = normal[kept]
        meas = uv[kept] + mu[kept, None] * n
        t = np.column_stack([-n[:, 1], n[:, 0]])
        v = self.factor.value * np.maximum(var[kept], p.contour_sigma_min_px**2)
        C = v[:, None, None] * np.einsum("ni,nj->nij", n, n) + _SIGMA_ALONG_PX**2 * np.einsum("ni,nj->nij", t, t)
        block = PointBlock(self.name, X[kept], meas, C)
        g = mahalanobis2(meas - uv[kept], S[kept] + C) < p.gate_chi2
        self._lines = (bins, informative, x, normal, uv, np.flatnonzero(kept)[g])
        timings["contour"] = (time.perf_counter() - t0) * 1e3
        return block.keep(g)

    def settle(self, ctx: FrameContext, block: PointBlock, inliers: np.ndarray, state: FilterState) -> None:
        self.factor.update(posterior_m2(ctx.camera, block.keep(inliers), state))
        if self._lines is None or not ctx.vouched:
            return
        bins, informative, x, normal, uv, kept = self._lines
        if len(kept) != len(inliers):  # (not this frame's block)
            return
        rows = kept[inliers]
        if len(rows) < 8:
            return
        p = self.params
        # where the posterior's outline lies along each line: the object's side of it is object
        uv_post, _ = project_model_points(ctx.camera, block.X[inliers], state.p, state.R, False)
        d = np.einsum("ij,ij->i", uv_post - uv[rows], normal[rows])
        rel = x[None, :] - d[:, None]
        ok = informative[rows]
        self.colours.update(bins[rows][ok & (rel < -2)], bins[rows][ok & (rel > 2)], p.contour_rate_f, p.contour_rate_b)


def side_runs(on: np.ndarray, x: np.ndarray, near: np.ndarray) -> np.ndarray:
    """Per line (rows of ``on``, the z-buffer's object mask read at offsets ``x`` from the
    predicted outline), the pixels that belong to the outline's two sides: inwards up to the
    first pixel, beyond ``near`` px (per line), that the z-buffer shows off the object (its far
    side: a thin object); outwards up to the first beyond ``near`` that it shows on the object
    (another part of it).

    >>> on = np.array([[1, 0, 1, 1, 1, 0, 0, 1, 0]], bool)  # x = -4 … 4: far side at -3, a part at +3
    >>> side_runs(on, np.arange(-4.0, 5.0), np.array([1.0])).astype(int).tolist()
    [[0, 0, 1, 1, 1, 1, 1, 0, 0]]
    """
    L = (len(x) - 1) // 2
    close = np.abs(x)[None, :] <= np.asarray(near, float)[:, None]
    inwards = np.logical_and.accumulate((on | close)[:, L::-1], axis=1)[:, ::-1]  # x = -L … 0
    outwards = np.logical_and.accumulate((~on | close)[:, L:], axis=1)  # x = 0 … L
    return np.concatenate([inwards[:, :L], outwards], axis=1)

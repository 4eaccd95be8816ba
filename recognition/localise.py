"""Where is the object? RFCH window search with χ² (Ekvall & Kragic 2005; Kragic & Kyrki, Sec. 2).

Pixels of a reduced-resolution label map get their RFCH cluster label (the descriptors of
:mod:`quatrack.viewsets.rfch`, so a query is described as the model was) and the counts of each
label within distance ``d``. Windows of several sizes and aspect ratios then slide over the whole
image, and each window's co-occurrence histogram is compared with the object's by χ².

**Speed.** Per-cell histograms (cells of ``cell`` label-map pixels) are one sparse product:
a CSC matrix with one non-zero per pixel (its cell and label) times the neighbour counts. An
integral image over cells gives any cell-aligned window's histogram in four look-ups. Only the
model's ``bins`` heaviest bins are kept, the rest pooled into one bin: χ² on that merged binning
is still an exact χ², of a coarser histogram.

**Scale.** χ² alone prefers windows that hold only object texture, i.e. patches *inside* the
object (measured on ``box.mp4``: the best half-size window has a lower χ² than the best
full-size one in every frame). The search therefore scores centre against surround:
``χ²(window) − χ²(ring around it)``. A window inside the object has an object-like ring and no
contrast; the window that covers the object has a background ring; a larger one pays in its own χ².

Pixels whose descriptor lies far from every cluster centre stay unlabelled and count for nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sp

from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.rfch import RFCHModel, neighbour_planes, pixel_descriptors
from quatrack.viewsets.store import ObjectModel


@dataclass(frozen=True)
class LocaliseParams:
    """``label_side``: the label map's longer side (px); ``cell``: the window grid (label px);
    ``max_label_distance``: the cut-off (in units of the descriptor spread per dimension) beyond
    which a pixel stays unlabelled; window sides span ``size_factors`` × the training sizes seen
    through the query camera, ``n_sizes`` of them at each of ``aspects``; ``ring``: the surround's
    width as a fraction of the window; ``max_chi2`` gates a detection."""

    label_side: int = 320
    cell: int = 8
    max_label_distance: float = 3.0
    size_factors: tuple[float, float] = (0.6, 1.3)
    n_sizes: int = 9
    aspects: tuple[float, ...] = (0.7, 1.0, 1.4)
    ring: float = 0.15
    bins: int = 128
    refine: int = 6  # coarse candidates refined at full resolution
    min_ring_inside: float = 0.3  # fraction of a window's ring that must lie in the image
    ring_weight_power: float = 0.5  # contrast × (ring fraction inside)^power
    max_chi2: float = 1.2
    min_contrast: float = 0.05


@dataclass(frozen=True)
class Window:
    """The localised object: ``bbox`` (x, y, w, h) in image pixels, its χ² to the model, the
    χ² of its surround, and whether it passes the gate (``found``)."""

    bbox: tuple[float, float, float, float]
    chi2: float
    ring_chi2: float
    found: bool

    @property
    def confidence(self) -> float:
        """0 … 1: how far inside the gate the window is."""
        return float(np.clip(self.ring_chi2 - self.chi2, 0.0, 1.0)) if self.found else 0.0


@dataclass
class LabelMap:
    """Labels (h, w) int32 (-1 = unlabelled) and the map's scale: label pixels per image pixel."""

    labels: np.ndarray
    scale: float


def label_map(image: np.ndarray, rfch: RFCHModel, params: LocaliseParams = LocaliseParams()) -> LabelMap:
    """RFCH labels of a reduced-resolution copy of ``image``, unlabelled beyond the cut-off.

    The model's Gaussian scales are in image pixels; in the reduced map they shrink with it, so
    scale-normalised derivatives describe the same structures.
    """
    h, w = image.shape[:2]
    s = min(1.0, params.label_side / max(h, w))
    small = image if s == 1.0 else cv2.resize(image, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    desc = pixel_descriptors(small, tuple(float(sig) * s for sig in rfch.scales))
    x = ((desc.reshape(-1, desc.shape[-1]) - rfch.desc_mean) / rfch.desc_std).astype(np.float32)
    c = rfch.centres.astype(np.float32)
    d2 = x @ (-2.0 * c.T) + (c * c).sum(1)[None]  # ‖x - c‖² less ‖x‖², which argmin ignores
    lab = d2.argmin(axis=1).astype(np.int32)
    nearest = np.take_along_axis(d2, lab[:, None], 1)[:, 0] + (x * x).sum(1)
    lab[nearest > params.max_label_distance**2 * x.shape[1]] = -1
    return LabelMap(lab.reshape(small.shape[:2]), small.shape[1] / w)


def pair_planes(labels: np.ndarray, n: int, d: int) -> np.ndarray:
    """(n, h, w) uint16: labelled pixels of each label within distance ``d``, the pixel itself
    excluded (the histogram counts pairs of distinct pixels)."""
    valid = labels >= 0
    N = neighbour_planes(labels, valid, n, d)
    flat = N.reshape(n, -1)
    idx = np.flatnonzero(valid)
    flat[labels.ravel()[idx], idx] -= 1
    return N


def cell_histograms(labels: np.ndarray, N: np.ndarray, n: int, cell: int) -> np.ndarray:
    """(rows, cols, n·n) co-occurrence counts per cell: bin ``a·n + b`` counts pairs (a at p,
    b near p) with p in the cell. ``N``: :func:`pair_planes`. Pixels past the last whole cell
    are dropped."""
    H, W = labels.shape
    rows, cols = H // cell, W // cell
    lab = labels[: rows * cell, : cols * cell]
    flat = lab.ravel()
    ok = np.flatnonzero(flat >= 0)
    cy, cx = np.divmod(ok, cols * cell)
    key = (cy // cell) * cols + (cx // cell)
    key = key * n + flat[ok]
    cnt = N[:, : rows * cell, : cols * cell].reshape(n, -1)[:, ok].T.astype(np.float32)
    # CSC with one non-zero per column (pixel): built without any sort
    S = sp.csc_matrix((np.ones(len(ok), np.float32), key, np.arange(len(ok) + 1)), shape=(rows * cols * n, len(ok)))
    return np.asarray(S @ cnt).reshape(rows, cols, n * n)


def _kept_bins(model_hist: np.ndarray, k: int) -> np.ndarray:
    return np.argsort(model_hist.ravel())[::-1][: min(k, model_hist.size)]


def compress(hist: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Histograms (..., n·n) → (..., k + 1): the kept bins, then everything else pooled."""
    out = np.empty(hist.shape[:-1] + (len(kept) + 1,), dtype=np.float32)
    out[..., :-1] = hist[..., kept]
    out[..., -1] = hist.sum(axis=-1) - out[..., :-1].sum(axis=-1)
    return out


def chi2_rows(h: np.ndarray, m: np.ndarray) -> np.ndarray:
    """χ² of each row of unnormalised histograms ``h`` (..., k) to the normalised ``m`` (k,);
    2 (the maximum) for an empty row."""
    tot = h.sum(axis=-1, keepdims=True)
    hn = h / np.maximum(tot, 1e-12)
    s = hn + m
    diff = hn - m
    out = (diff * diff / np.maximum(s, 1e-30)).sum(axis=-1)  # 0/0 bins contribute 0
    return np.where(tot[..., 0] > 0, out, 2.0)


def window_shapes(model: ObjectModel, image_size: tuple[int, int], scale: float, grid, params: LocaliseParams):
    """Window (w, h) in cells. The object's apparent sizes in the training views, as fractions of
    their image, are carried to the query image and widened by ``size_factors``: the training
    views (registered and synthetic, at several distances) bound the search."""
    rf = model.rfch
    train_w = float(np.median([vs.camera.width for vs in model.viewsets])) if model.viewsets else image_size[0]
    zoom = image_size[0] / train_w * scale / params.cell
    (w0, h0), (w1, h1) = rf.size_min, rf.size_max
    base_aspect = np.sqrt((w0 / h0) * (w1 / h1))
    rows, cols = grid
    hi = min(np.sqrt(w1 * h1) * zoom * params.size_factors[1], 0.9 * min(rows, cols) * np.sqrt(base_aspect))
    lo = max(min(np.sqrt(w0 * h0) * zoom * params.size_factors[0], hi / 2), 3.0)
    shapes = set()
    for side in np.geomspace(lo, hi, params.n_sizes):
        for a in params.aspects:
            asp = base_aspect * a
            shapes.add((int(np.clip(round(side * np.sqrt(asp)), 2, cols)), int(np.clip(round(side / np.sqrt(asp)), 2, rows))))
    return sorted(shapes)


def _box_sums(I: np.ndarray, y0, x0, y1, x1) -> np.ndarray:
    return I[y1, x1] - I[y0, x1] - I[y1, x0] + I[y0, x0]


def localise(
    image: np.ndarray, camera: PinholeCamera, model: ObjectModel, params: LocaliseParams = LocaliseParams()
) -> Window | None:
    """The window most likely to hold the object (``found`` says whether it passes the χ² gate),
    or None if nothing in the image carries an object label. ``image``: 8-bit BGR for ``camera``."""
    rf = model.rfch
    n = rf.n_clusters
    lm = label_map(image, rf, params)
    if not (lm.labels >= 0).any():
        return None
    d = max(1, int(round(rf.distance * lm.scale)))
    N = pair_planes(lm.labels, n, d)
    kept = _kept_bins(rf.histogram, params.bins)
    m = compress(rf.histogram.reshape(1, -1).astype(np.float32), kept)[0]
    C = compress(cell_histograms(lm.labels, N, n, params.cell), kept)  # (rows, cols, k+1)
    rows, cols = C.shape[:2]
    I = np.zeros((rows + 1, cols + 1, C.shape[2]), np.float32)
    I[1:, 1:] = C.cumsum(0).cumsum(1)
    def evaluate(w: int, h: int, ys: np.ndarray, xs: np.ndarray):
        """Centre-surround scores of the windows of shape (w, h) at cells (ys, xs)."""
        inner = _box_sums(I, ys, xs, ys + h, xs + w)
        rw, rh = max(1, round(params.ring * w)), max(1, round(params.ring * h))
        oy0, ox0 = np.maximum(ys - rh, 0), np.maximum(xs - rw, 0)
        oy1, ox1 = np.minimum(ys + h + rh, rows), np.minimum(xs + w + rw, cols)
        ring = _box_sums(I, oy0, ox0, oy1, ox1) - inner
        c_in = chi2_rows(inner, m)
        c_ring = chi2_rows(ring, m)
        # the ring's histogram holds only its part inside the image; a window whose ring is
        # mostly outside has no surround to compare with (the whole image, say) and is skipped
        inside = ((oy1 - oy0) * (ox1 - ox0) - w * h) / ((h + 2 * rh) * (w + 2 * rw) - w * h)
        weight = np.where(inside >= params.min_ring_inside, inside**params.ring_weight_power, np.nan)
        return np.where(np.isnan(weight), np.inf, weight * (c_in - c_ring)), c_in, c_ring

    # coarse: every shape on a grid of every other cell; fine: ±1 cell around the best few
    coarse = []
    for w, h in window_shapes(model, (image.shape[1], image.shape[0]), lm.scale, (rows, cols), params):
        ys, xs = np.meshgrid(np.arange(0, rows - h + 1, 2), np.arange(0, cols - w + 1, 2), indexing="ij")
        ys, xs = ys.ravel(), xs.ravel()
        score, _, _ = evaluate(w, h, ys, xs)
        k = int(np.argmin(score))
        if np.isfinite(score[k]):
            coarse.append((float(score[k]), w, h, int(ys[k]), int(xs[k])))
    coarse.sort()
    best = None
    for _, w, h, y0, x0 in coarse[: params.refine]:
        ys, xs = np.meshgrid(np.arange(max(y0 - 1, 0), min(y0 + 2, rows - h + 1)),
                             np.arange(max(x0 - 1, 0), min(x0 + 2, cols - w + 1)), indexing="ij")
        ys, xs = ys.ravel(), xs.ravel()
        score, c_in, c_ring = evaluate(w, h, ys, xs)
        k = int(np.argmin(score))
        if best is None or score[k] < best[0]:
            best = (float(score[k]), float(c_in[k]), float(c_ring[k]), (int(xs[k]), int(ys[k]), w, h))
    if best is None:
        return None
    score, c_in, c_ring, (x, y, w, h) = best
    px = params.cell / lm.scale  # image pixels per cell
    bbox = (x * px, y * px, w * px, h * px)
    found = bool(c_in <= params.max_chi2 and -score >= params.min_contrast)
    return Window(bbox, c_in, c_ring, found)

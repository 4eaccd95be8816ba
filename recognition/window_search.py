"""Where is the object? RFCH window search with χ² (Ekvall & Kragic 2005; Kragic & Kyrki, Sec. 2).

Pixels of a reduced-resolution label map get their RFCH cluster label (the descriptors of
:mod:`quatrack.viewsets.rfch`, so a query is described as the model was) and the counts of each
label within distance ``d``. Windows of several sizes and aspect ratios then slide over the whole
image, and each window's co-occurrence histogram is compared with the object's by χ².

**Speed** (p50 ≈ 12 ms for 640×480 on 2 cores; ``bench/RESULTS.md``). Every step is a few
large numpy/OpenCV calls, with no per-window or per-pixel Python:

- descriptors are channel-first planes (``cv2.transform`` for the colour algebra), and the
  nearest centre is one augmented matrix product per block with the label packed into the
  distance's low bits, so a plain ``minimum`` is the argmin;
- neighbour counts come from one separable 8-bit filter over the stacked indicator planes of
  the labels that matter (those in the kept bins);
- only the model's ``bins`` heaviest bins are counted, the rest pooled into one bin: χ² on that
  merged binning is still an exact χ², of a coarser histogram. Each pair centre (every
  ``stride``-th pixel, an unbiased sample) adds its few kept (a, b) counts into its cell in one
  compiled pass (numba; whole numbers, so the same bits as its numpy original);
- an integral image over cells gives any window's histogram from four rows; all windows of all
  shapes are scored in one batch (``np.take`` of corner rows, then χ²), then the best few are
  refined by ±1 cell and their edges moved one cell at a time.

**Scale.** χ² alone prefers windows that hold only object texture, i.e. patches *inside* the
object (measured on ``box.mp4``: the best half-size window has a lower χ² than the best
full-size one in every frame). The search therefore scores centre against surround:
``χ²(window) − χ²(ring around it)``. A window inside the object has an object-like ring and no
contrast; the window that covers the object has a background ring; a larger one pays in its own χ².
The shapes are discrete; moving the best window's edges one cell at a time (while the score
drops) fits its extent finer (IoU ≥ 0.5 in 82 % of the benchmark's views, against 80 % without).

Pixels whose descriptor lies far from every cluster centre stay unlabelled and count for nothing.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.jit import lazily_compiled
from quatrack.viewsets.rfch import RFCHModel, descriptor_planes, nearest_centres, neighbour_planes, texture_zoom
from quatrack.viewsets.store import ObjectModel

from .fields import check_field_kinds


@dataclass(frozen=True)
class WindowSearchParams:
    """``label_side``: the label map's longer side (px); ``cell``: the window grid (label px);
    ``stride``: pair centres sampled every stride-th label pixel;
    ``max_label_distance``: the cut-off (in units of the descriptor spread per dimension) beyond
    which a pixel stays unlabelled; window sides span ``size_factors`` × the training sizes seen
    through the query camera, ``n_sizes`` of them at each of ``aspects``; ``ring``: the surround's
    width as a fraction of the window; ``max_chi2`` gates a detection."""

    def __post_init__(self) -> None:  # (cell=8.5 or a string failed deep in the window search: recognition.fields)
        check_field_kinds(self)

    label_side: int = 320
    cell: int = 8
    stride: int = 2  # every stride-th pixel (both axes) is a pair's centre: 4× fewer terms, same accuracy
    max_label_distance: float = 3.0
    size_factors: tuple[float, float] = (0.6, 1.3)
    n_sizes: int = 9
    aspects: tuple[float, ...] = (0.7, 1.0, 1.4)
    ring: float = 0.15
    bins: int = 128
    refine: int = 6  # coarse candidates refined at full resolution
    edge_refine: int = 3  # rounds of moving the best window's edges by ±1 cell
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


def label_map(image: np.ndarray, rfch: RFCHModel, params: WindowSearchParams = WindowSearchParams(),
              zoom: float = 1.0) -> LabelMap:
    """RFCH labels of a reduced-resolution copy of ``image``, unlabelled beyond the cut-off.

    The model's Gaussian scales are in training pixels, ``zoom`` image pixels each
    (:func:`~quatrack.viewsets.rfch.texture_zoom`); in the reduced map they shrink with it, so
    scale-normalised derivatives describe the same structures.
    """
    h, w = image.shape[:2]
    s = min(1.0, params.label_side / max(h, w))
    small = image if s == 1.0 else cv2.resize(image, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    planes = descriptor_planes(small, tuple(float(sig) * zoom * s for sig in rfch.scales))
    lab, d2 = nearest_centres(planes, rfch.centres, rfch.desc_mean, rfch.desc_std)
    lab[d2 > params.max_label_distance**2 * planes.shape[0]] = -1
    return LabelMap(lab.reshape(small.shape[:2]), small.shape[1] / w)


def cell_histograms(
    labels: np.ndarray, n: int, d: int, cell: int, bins: np.ndarray | None = None, stride: int = 1
) -> np.ndarray:
    """Co-occurrence counts per cell of ``cell`` × ``cell`` pixels: bin ``a·n + b`` counts pairs of
    distinct labelled pixels (a at p, b at q ≠ p, Chebyshev distance ≤ ``d``) with p in the cell;
    q may lie outside it. Pixels past the last whole cell are dropped.

    ``bins`` None: all (rows, cols, n·n) bins. Otherwise (rows, cols, len(bins) + 1): the bins
    listed (ascending), then all other pairs pooled — the model's heaviest bins, say: only
    those are ever counted. ``stride`` > 1 takes every stride-th pixel (both axes) as p, an
    unbiased sample of the histogram at 1/stride² the cost.

    Each sampled p with label a adds, for each listed bin (a, b), its count of b-labelled
    neighbours (read from :func:`neighbour_planes`) into its cell: one compiled pass over the
    sampled pixels (:func:`_pair_counts`), with no per-pixel n-vector and no n·n array. Its
    numpy original, :func:`_cell_histograms_numpy`, gathered the same terms into flat arrays
    first (~1.8 of the search's ~12 ms, against ~0.2; bench/RESULTS.md, session 55).
    """
    H, W = labels.shape
    rows, cols = H // cell, W // cell
    bins, pooled, plane_of, planes = _listed_planes(labels, n, d, bins)
    # the listed bins of label a are bins[first[a] : first[a] + count[a]] (they ascend, so they
    # are grouped by a); each reads the plane of its b, and (a, a) takes p itself back out
    count = np.bincount(bins // n, minlength=n)
    first = np.cumsum(count) - count
    counts = np.zeros((rows * cols, len(bins)), np.int64)
    _compiled_pair_counts()(np.ascontiguousarray(labels, np.int32), planes, first.astype(np.int64),
                            count.astype(np.int64), plane_of[bins % n + 1].astype(np.int64),
                            (bins // n == bins % n), int(d), int(cell), int(stride), int(cols), counts)
    return _assembled(counts, labels, d, cell, stride, pooled)


def _listed_planes(labels: np.ndarray, n: int, d: int, bins: np.ndarray | None):
    """The bins counted (all n·n, or ``bins`` checked), whether the rest is pooled, each label's
    plane index (``plane_of[label + 1]``, −1: not needed) and the neighbour counts of the labels b
    that some listed bin (a, b) needs (:func:`neighbour_planes`)."""
    pooled = bins is not None
    bins = np.arange(n * n) if bins is None else np.asarray(bins)
    if pooled and (np.any(np.diff(bins) <= 0) or bins[0] < 0 or bins[-1] >= n * n):
        raise ValueError("bins must be ascending indices below n·n")
    used = np.unique(bins % n)
    plane_of = np.full(n + 1, -1)
    plane_of[used + 1] = np.arange(len(used))
    return bins, pooled, plane_of, neighbour_planes(plane_of[labels + 1], None, len(used), d)


def _sampled(labels: np.ndarray, cell: int, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The labelled pair centres: every ``stride``-th pixel of the whole cells (both axes, from the
    middle of each stride × stride block) as flat pixel index, cell index and label."""
    H, W = labels.shape
    rows, cols = H // cell, W // cell
    o = stride // 2
    ys = np.arange(o, rows * cell, stride)
    xs = np.arange(o, cols * cell, stride)
    pix = (ys[:, None] * W + xs[None, :]).ravel()
    cells = ((ys // cell)[:, None] * cols + (xs // cell)[None, :]).ravel()
    lab = labels.ravel()[pix]
    ok = lab >= 0
    return pix[ok], cells[ok], lab[ok]


def _assembled(counts: np.ndarray, labels: np.ndarray, d: int, cell: int, stride: int, pooled: bool) -> np.ndarray:
    """(rows, cols, k [+ 1]) float32 histograms from the listed bins' counts per cell (rows · cols,
    k), with, when ``pooled``, all the cell's other pairs in a last bin: the labelled neighbours of
    each of its centres, less the centre itself, less the listed pairs."""
    H, W = labels.shape
    rows, cols = H // cell, W // cell
    k = counts.shape[1]
    out = np.zeros((rows * cols, k + pooled), np.float32)
    out[:, :k] = counts
    if pooled:
        pix, cells, _ = _sampled(labels, cell, stride)
        valid = (labels >= 0).astype(np.uint8)
        around = cv2.boxFilter(valid, cv2.CV_32F, (2 * d + 1, 2 * d + 1), normalize=False, borderType=cv2.BORDER_CONSTANT)
        total = np.bincount(cells, weights=around.ravel()[pix] - 1.0, minlength=rows * cols)
        out[:, k] = total - out[:, :k].sum(axis=1)
    return out.reshape(rows, cols, -1)


def _pair_counts(labels, planes, first, count, plane, own, d, cell, stride, cols, out):  # pragma: no cover (compiled)
    """For each sampled p (every ``stride``-th pixel of the whole cells, both axes, from the
    middle of each stride block) with label a ≥ 0, each listed bin j of a (``first[a] …
    first[a] + count[a]``) adds the count of its b's plane at p (``planes[plane[j]]``, rows
    offset by ``d``), less 1 where b = a (``own[j]``: p itself), into ``out[cell of p, j]``.
    Whole numbers: any order of the additions gives the same counts."""
    rows = out.shape[0] // cols
    o = stride // 2
    for y in range(o, rows * cell, stride):
        cy = (y // cell) * cols
        for x in range(o, cols * cell, stride):
            a = labels[y, x]
            if a < 0:
                continue
            c = cy + x // cell
            for j in range(first[a], first[a] + count[a]):
                out[c, j] += planes[plane[j], y + d, x] - (1 if own[j] else 0)


_compiled_pair_counts = lazily_compiled(_pair_counts)


def _cell_histograms_numpy(
    labels: np.ndarray, n: int, d: int, cell: int, bins: np.ndarray | None = None, stride: int = 1
) -> np.ndarray:
    """:func:`cell_histograms` in numpy alone, its original (a test compares the two): the terms
    (sampled p, listed bin) are gathered into flat arrays and added up with one weighted
    ``bincount`` over about #p · #bins / n terms."""
    H, W = labels.shape
    rows, cols = H // cell, W // cell
    bins, pooled, plane_of, planes = _listed_planes(labels, n, d, bins)
    k = len(bins)
    planes = planes.reshape(-1)
    plane_size = (H + 2 * d) * W
    pix, cells, lab = _sampled(labels, cell, stride)
    # one term per (sampled p, listed bin (a, b) with a = label of p)
    count = np.bincount(bins // n, minlength=n)
    first = np.cumsum(count) - count
    per = count[lab]
    start = np.cumsum(per) - per
    term_bin = np.arange(start[-1] + per[-1] if len(per) else 0) + np.repeat(first[lab] - start, per)
    offset = plane_of[bins % n + 1] * plane_size  # where each listed bin's b-plane starts
    value = np.take(planes, offset[term_bin] + np.repeat(pix + d * W, per))
    key = np.repeat(cells * k, per) + term_bin
    counts = np.bincount(key, weights=value, minlength=rows * cols * k)
    # q ≠ p: a p labelled a counted itself in its bin (a, a), when that bin is listed; the sums
    # are whole numbers in float64, so subtracting per cell equals subtracting per term
    diagonal = np.full(n, -1)
    on = bins // n == bins % n
    diagonal[bins[on] // n] = np.flatnonzero(on)
    own = diagonal[lab]
    mine = own >= 0
    counts -= np.bincount(cells[mine] * k + own[mine], minlength=rows * cols * k)
    return _assembled(counts.reshape(-1, k), labels, d, cell, stride, pooled)


def _kept_bins(model_hist: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` heaviest bins of the model, in index order (for a cache-friendly gather)."""
    return np.sort(np.argsort(model_hist.ravel())[::-1][: min(k, model_hist.size)])


def compress(hist: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Histograms (..., n·n) → (..., k + 1): the kept bins, then everything else pooled."""
    out = np.empty(hist.shape[:-1] + (len(kept) + 1,), dtype=np.float32)
    out[..., :-1] = np.take(hist, kept, axis=-1)  # 5× faster than hist[..., kept]
    out[..., -1] = hist.sum(axis=-1) - out[..., :-1].sum(axis=-1)
    return out


def chi2_rows(h: np.ndarray, m: np.ndarray) -> np.ndarray:
    """χ² of each row of unnormalised histograms ``h`` (..., k) to the normalised ``m`` (k,);
    2 (the maximum) for an empty row. ``h`` is overwritten (it is a scratch array here).

    For two normalised histograms Σ(a − b)²/(a + b) = Σ(a + b) − 4·Σ ab/(a + b) = 2 − 4·Σ ab/(a + b):
    five passes over the rows instead of eight. Empty model bins are raised to 1e-12 so no
    bin is 0/0 (a model seen in few views can have fewer non-zero bins than are kept).
    """
    m = np.maximum(m, np.float32(1e-12))
    tot = h.sum(axis=-1)
    h *= (1.0 / np.maximum(tot, 1e-12))[..., None]
    s = h + m
    h *= m
    h /= s
    return np.where(tot > 0, 2.0 - 4.0 * h.sum(axis=-1), 2.0)


def window_shapes(model: ObjectModel, image_size: tuple[int, int], scale: float, grid, params: WindowSearchParams):
    """Window (w, h) in cells. The object's apparent sizes in the training views, as fractions of
    their image, are carried to the query image and widened by ``size_factors``: the training
    views (registered and synthetic, at several distances) bound the search; views learned
    while tracking have their boxes in those units already (quatrack.viewsets.learn)."""
    train_w = model.training_width or float(image_size[0])
    rf = model.rfch
    return _window_shapes(train_w, tuple(rf.size_min), tuple(rf.size_max), image_size[0], float(scale), tuple(grid), params)


@functools.lru_cache(maxsize=256)
def _window_shapes(train_w: float, size_min, size_max, image_w: int, scale: float, grid, params: WindowSearchParams):
    zoom = image_w / train_w * scale / params.cell
    (w0, h0), (w1, h1) = size_min, size_max
    base_aspect = np.sqrt((w0 / h0) * (w1 / h1))
    rows, cols = grid
    hi = min(np.sqrt(w1 * h1) * zoom * params.size_factors[1], 0.9 * min(rows, cols) * np.sqrt(base_aspect))
    lo = max(min(np.sqrt(w0 * h0) * zoom * params.size_factors[0], hi / 2), 3.0)
    shapes = set()
    for side in np.geomspace(lo, hi, params.n_sizes):
        for a in params.aspects:
            asp = base_aspect * a
            shapes.add((min(max(round(side * np.sqrt(asp)), 2), cols), min(max(round(side / np.sqrt(asp)), 2), rows)))
    return tuple(sorted(shapes))


def _ring(w, h, params: WindowSearchParams):
    """The surround's width and height in cells (scalars or arrays; round half to even)."""
    return np.maximum(1, np.round(params.ring * np.asarray(w))).astype(int), np.maximum(1, np.round(params.ring * np.asarray(h))).astype(int)


@dataclass(frozen=True)
class _Integral:
    """Integral image of per-cell histograms, padded by ``pad`` on every side with its edge
    values, so that a corner outside the grid reads as the clamped corner: a window's ring is
    clipped to the image without any branch. Flattened to (positions, bins) for row gathers."""

    flat: np.ndarray  # ((rows + 1 + 2·pad) · (cols + 1 + 2·pad), k)
    pad: int
    rows: int
    cols: int

    @classmethod
    def of(cls, C: np.ndarray, pad: int) -> "_Integral":
        rows, cols, k = C.shape
        I = np.zeros((rows + 1 + 2 * pad, cols + 1 + 2 * pad, k), np.float32)
        core = I[pad + 1 : pad + 1 + rows, pad + 1 : pad + 1 + cols]
        core[...] = C
        for i in range(1, rows):  # row by row: numpy's cumsum along an outer axis is 10× slower
            core[i] += core[i - 1]
        for j in range(1, cols):
            core[:, j] += core[:, j - 1]
        I[pad + 1 + rows :, pad + 1 : pad + 1 + cols] = core[-1:]  # edge values below …
        I[:, pad + 1 + cols :] = I[:, pad + cols : pad + 1 + cols]  # … and to the right
        return cls(I.reshape(-1, k), pad, rows, cols)

    def box_sums(self, y0: np.ndarray, x0: np.ndarray, y1: np.ndarray, x1: np.ndarray) -> np.ndarray:
        """(N, k) sums over the cells [y0, y1) × [x0, x1), each clipped to the grid."""
        width = self.cols + 1 + 2 * self.pad
        at = lambda y, x: (y + self.pad) * width + (x + self.pad)  # noqa: E731
        c = np.take(self.flat, np.stack([at(y1, x1), at(y0, x1), at(y1, x0), at(y0, x0)]), axis=0)
        out = c[0] - c[1]
        out -= c[2]
        out += c[3]
        return out


def _score_windows(I: _Integral, m: np.ndarray, y: np.ndarray, x: np.ndarray, w: np.ndarray, h: np.ndarray,
                   params: WindowSearchParams):
    """Centre–surround scores (lower is better), χ² of the windows and of their rings, for the
    windows of w × h cells at (y, x), all given as (N,) arrays: one batch for every shape, so
    the cost is in the arithmetic, not in Python calls."""
    rw, rh = _ring(w, h, params)
    inner = I.box_sums(y, x, y + h, x + w)
    ring = I.box_sums(y - rh, x - rw, y + h + rh, x + w + rw)
    ring -= inner
    c_ring = chi2_rows(ring, m)
    c_in = chi2_rows(inner, m)
    # the ring's histogram holds only its part inside the image; a window whose ring is
    # mostly outside has no surround to compare with (the whole image, say) and is skipped
    oh = np.minimum(y + h + rh, I.rows) - np.maximum(y - rh, 0)
    ow = np.minimum(x + w + rw, I.cols) - np.maximum(x - rw, 0)
    inside = (oh * ow - w * h) / ((h + 2 * rh) * (w + 2 * rw) - w * h)
    score = np.full(len(y), np.inf)
    ok = inside >= params.min_ring_inside
    score[ok] = inside[ok] ** params.ring_weight_power * (c_in[ok] - c_ring[ok])
    return score, c_in, c_ring


@functools.lru_cache(maxsize=64)
def _coarse_windows(shapes: tuple, rows: int, cols: int) -> np.ndarray:
    """Every shape at every other cell: rows (y, x, w, h, shape index), each (N,). Cached: one
    image size and one model give one set of windows."""
    out = []
    for i, (w, h) in enumerate(shapes):
        yy, xx = np.meshgrid(np.arange(0, rows - h + 1, 2), np.arange(0, cols - w + 1, 2), indexing="ij")
        k = yy.size
        out.append(np.stack([yy.ravel(), xx.ravel(), np.full(k, w), np.full(k, h), np.full(k, i)]))
    grid = np.concatenate(out, axis=1) if out else np.zeros((5, 0), int)
    grid.setflags(write=False)
    return grid


_EDGE_MOVES = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 4, indexing="ij")).reshape(4, -1)  # (dy0, dx0, dy1, dx1)


def search_window(
    image: np.ndarray, camera: PinholeCamera, model: ObjectModel, params: WindowSearchParams = WindowSearchParams()
) -> Window | None:
    """The window most likely to hold the object (``found`` says whether it passes the χ² gate),
    or None if nothing in the image carries an object label. ``image``: 8-bit BGR for ``camera``."""
    rf = model.rfch
    n = rf.n_clusters
    zoom = texture_zoom(model.training_width, image.shape[1])
    lm = label_map(image, rf, params, zoom)
    if not (lm.labels >= 0).any():
        return None
    d = max(1, int(round(rf.distance * zoom * lm.scale)))
    kept = _kept_bins(rf.histogram, params.bins)
    m = compress(rf.histogram.reshape(1, -1).astype(np.float32), kept)[0]
    C = cell_histograms(lm.labels, n, d, params.cell, kept, params.stride)  # (rows, cols, k + 1)
    rows, cols = C.shape[:2]
    shapes = window_shapes(model, (image.shape[1], image.shape[0]), lm.scale, (rows, cols), params)
    y, x, w, h, shape = _coarse_windows(shapes, rows, cols)
    if len(y) == 0:
        return None
    I = _Integral.of(C, int(max(_ring(cols, rows, params))) + 1)  # any window in the grid, edge moves included

    # coarse: the best position of every shape; fine: ±1 cell around the best few of those
    score, _, _ = _score_windows(I, m, y, x, w, h, params)
    order = np.lexsort((score, shape))
    first = order[np.r_[True, shape[order][1:] != shape[order][:-1]]]  # best of each shape
    first = first[np.isfinite(score[first])]
    top = first[np.argsort(score[first], kind="stable")][: params.refine]
    if len(top) == 0:
        return None
    cand = []
    for i in top:
        ys = np.arange(max(y[i] - 1, 0), min(y[i] + 2, rows - h[i] + 1))
        xs = np.arange(max(x[i] - 1, 0), min(x[i] + 2, cols - w[i] + 1))
        yy, xx = np.meshgrid(ys, xs, indexing="ij")
        cand.append(np.stack([yy.ravel(), xx.ravel(), np.full(yy.size, w[i]), np.full(yy.size, h[i])]))
    fy, fx, fw, fh = np.concatenate(cand, axis=1)
    score, c_in, c_ring = _score_windows(I, m, fy, fx, fw, fh, params)
    k = int(np.argmin(score))
    if not np.isfinite(score[k]):
        return None
    # edges: move each side of the best window by −1, 0 or +1 cell while that lowers the score
    for _ in range(params.edge_refine):
        dy0, dx0, dy1, dx1 = _EDGE_MOVES
        y0, x0, y1, x1 = fy[k] + dy0, fx[k] + dx0, fy[k] + fh[k] + dy1, fx[k] + fw[k] + dx1
        ok = (y0 >= 0) & (x0 >= 0) & (y1 <= rows) & (x1 <= cols) & (y1 - y0 >= 2) & (x1 - x0 >= 2)
        fy, fx, fh, fw = y0[ok], x0[ok], (y1 - y0)[ok], (x1 - x0)[ok]
        score, c_in, c_ring = _score_windows(I, m, fy, fx, fw, fh, params)
        k_new = int(np.argmin(score))
        stay = int(np.flatnonzero((_EDGE_MOVES[:, ok] == 0).all(axis=0))[0])
        k = k_new if score[k_new] < score[stay] else stay
        if k == stay:
            break
    px = params.cell / lm.scale  # image pixels per cell
    bbox = (float(fx[k] * px), float(fy[k] * px), float(fw[k] * px), float(fh[k] * px))
    found = bool(c_in[k] <= params.max_chi2 and -score[k] >= params.min_contrast)
    return Window(bbox, float(c_in[k]), float(c_ring[k]), found)

"""Receptive Field Co-occurrence Histograms (Ekvall & Kragic 2005), used to find the object.

Every pixel gets a descriptor — illumination-normalised chromaticity (r, g), and gradient
magnitude and Laplacian of the intensity at several Gaussian scales — which is quantised to one
of N cluster centres learnt from the object's pixels. The histogram counts pairs of labels of
pixels at most ``distance`` apart (Chebyshev), so it captures which colours/textures occur *next to
each other*, not only how often. Windows of a query image are compared to the model with χ².
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class RFCHParams:
    """``n_clusters`` N, pair ``distance`` d (px), Gaussian ``scales`` (px) of the derivative
    channels, pixels sampled for k-means, and its seed (for determinism)."""

    n_clusters: int = 32  # defaults from bench/rfch_study.py (bench/RESULTS.md, 'RFCH defaults')
    distance: int = 8
    scales: tuple[float, ...] = (1.0, 2.0)
    max_samples: int = 20000
    seed: int = 0


@dataclass(frozen=True)
class RFCHModel:
    """A trained RFCH: ``centres`` (N, D) in scaled descriptor space, ``histogram`` (N, N) summing
    to 1, descriptor scaling (``desc_mean``, ``desc_std``, each (D,)), and the object's apparent
    size in the training views: ``size_min``/``size_max`` = (w, h) pixels of the smallest/largest."""

    centres: np.ndarray
    histogram: np.ndarray
    scales: tuple[float, ...]
    n_clusters: int
    distance: int
    desc_mean: np.ndarray
    desc_std: np.ndarray
    size_min: tuple[int, int]
    size_max: tuple[int, int]


CHROMA_STD_FLOOR = 0.03


def texture_zoom(training_width: float | None, image_width: float) -> float:
    """How many pixels of an image ``image_width`` wide one pixel of the training photos
    (``training_width`` wide: :attr:`~quatrack.viewsets.store.ObjectModel.training_width`) spans
    for the RFCH's Gaussian scales and pair distance: the widths' ratio where the image is the
    wider, else 1. A camera with 4× the pixels over the same field sees the texture 4× larger, and
    scales kept in its pixels would describe finer structure than training did (the window search
    then misses the object: a 2560 px frame of the cookie box 4 in 5 times); an image narrower than
    the photos cannot show structure finer than its own pixels, so the scales never shrink below
    the training's.

    >>> texture_zoom(640, 2560), texture_zoom(718, 640), texture_zoom(None, 640)
    (4.0, 1.0, 1.0)
    """
    if not training_width or training_width <= 0:
        return 1.0
    return max(1.0, float(image_width) / float(training_width))


def _bgr(image: np.ndarray) -> np.ndarray:
    """float32 (H, W, 3) from a grey, BGR or BGRA image of any depth (values kept)."""
    img = np.asarray(image, np.float32)
    if img.ndim == 2:
        img = img[..., None].repeat(3, axis=2)
    return np.ascontiguousarray(img[..., :3])


def descriptor_planes(image: np.ndarray, scales: tuple[float, ...]) -> np.ndarray:
    """(2 + 2·len(scales), H, W) float32, channel first: r, g chromaticity, then per scale σ the
    gradient magnitude and the scale-normalised Laplacian (σ²∇²) of the grey-world intensity.

    The per-pixel colour algebra is done by ``cv2.transform`` with one-row matrices (the
    grey-world gains folded in): numpy's reductions over a length-3 last axis cost 50× more.
    """
    img = _bgr(image)
    g = (0.5 / np.maximum(np.asarray(cv2.mean(img)[:3]), 1e-6)).astype(np.float32)
    s = cv2.transform(img, g[None]) + np.float32(1e-6)  # B' + G' + R'
    h, w = s.shape
    out = np.empty((2 + 2 * len(scales), h, w), np.float32)
    cv2.divide(cv2.transform(img, np.array([[0, 0, g[2]]], np.float32)), s, out[0])  # r (BGR order)
    cv2.divide(cv2.transform(img, np.array([[0, g[1], 0]], np.float32)), s, out[1])  # g
    intensity = s * np.float32(1.0 / 3.0)
    for i, sigma in enumerate(scales):
        blur = cv2.GaussianBlur(intensity, (0, 0), sigma)
        gx = cv2.Sobel(blur, cv2.CV_32F, 1, 0, ksize=3, scale=0.125 * sigma)
        gy = cv2.Sobel(blur, cv2.CV_32F, 0, 1, ksize=3, scale=0.125 * sigma)
        cv2.magnitude(gx, gy, out[2 + 2 * i])
        cv2.Laplacian(blur, cv2.CV_32F, out[3 + 2 * i], ksize=3, scale=0.25 * sigma * sigma)
    return out


def nearest_centres(
    planes: np.ndarray, centres: np.ndarray, mean: np.ndarray, std: np.ndarray, block: int = 2048
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest centre of each pixel: ``planes`` (D, P) raw descriptors → labels (P,) int32 and
    the squared distance (P,) float32, in the scaled space ``(x − mean) / std`` of ``centres``.

    ‖x − c‖² = ‖x‖² − 2·x·c + ‖c‖² is one (K, D + 2) × (D + 2, P) product: the scaling, ‖c‖²
    and ‖x‖² are folded into an augmented matrix and two extra rows (1, ‖x‖²). The argmin over
    K is a plain minimum: a non-negative float32 orders like its int32 bit pattern, so the label
    is written into the low ⌈log₂K⌉ mantissa bits and ``np.minimum`` over K rows picks distance
    and label together (exact up to ties within 2⁻¹⁸ relative; distances that round below zero
    are ≈ 0 and still win). numpy's ``argmin`` along a short axis is 4× slower. Blocks of pixels
    keep the (K, block) distances in cache.
    """
    c = np.asarray(centres, np.float64)
    k, dim = c.shape
    inv = 1.0 / np.asarray(std, np.float64)
    mu = np.asarray(mean, np.float64)
    W = np.empty((k, dim + 2), np.float32)
    W[:, :dim] = -2.0 * c * inv  # −2·c/σ
    W[:, dim] = (c * c).sum(1) + 2.0 * (c * inv) @ mu  # ‖c‖² + 2·c·μ/σ
    W[:, dim + 1] = 1.0
    X = np.empty((dim + 2, planes[0].size), np.float32)
    X[:dim] = np.asarray(planes, np.float32).reshape(dim, -1)
    X[dim] = 1.0
    xs = (X[:dim] - mu.astype(np.float32)[:, None]) * inv.astype(np.float32)[:, None]
    np.einsum("ij,ij->j", xs, xs, out=X[dim + 1])  # ‖x‖²
    bits = max(1, int(np.ceil(np.log2(k))))
    keep = np.int32(~((1 << bits) - 1))
    ids = np.arange(k, dtype=np.int32)[:, None]
    key = np.empty(X.shape[1], np.int32)
    for a in range(0, X.shape[1], block):
        b = min(a + block, X.shape[1])
        d2 = (W @ X[:, a:b]).view(np.int32)
        d2 &= keep
        d2 |= ids
        np.minimum.reduce(d2, axis=0, out=key[a:b])
    return key & ((1 << bits) - 1), (key & keep).view(np.float32)


def label_planes(planes: np.ndarray, centres: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Label (H, W) int32 of the nearest centre for each pixel of :func:`descriptor_planes` (D, H, W)."""
    return nearest_centres(planes, centres, mean, std)[0].reshape(planes.shape[1:])


def label_image(image: np.ndarray, model: RFCHModel) -> np.ndarray:
    """The cluster label of every pixel of ``image`` under ``model`` (training and query alike)."""
    return label_planes(descriptor_planes(image, model.scales), model.centres, model.desc_mean, model.desc_std)


def neighbour_planes(labels: np.ndarray, mask: np.ndarray | None, n: int, d: int) -> np.ndarray:
    """(N, H + 2d, W), uint8 if (2d + 1)² ≤ 255 else uint16: for each label, how many pixels of
    it lie within distance d of each pixel (Chebyshev, itself included), counting only labelled
    pixels (``labels`` ≥ 0) inside ``mask``. Each plane has ``d`` zero rows above and below:
    plane ``a``'s rows ``d … d + H`` are the image; :func:`neighbour_counts` is the same,
    pixel-major.

    All N indicator planes are stacked into one tall 8-bit image, ``d`` zero rows between planes
    so the box never reaches across, and filtered once: faster than float planes (10×) or one
    N-channel image (2×).
    """
    h, w = labels.shape
    if (2 * d + 1) ** 2 > 65535:
        raise ValueError(f"pair distance {d} too large")
    sel = labels >= 0
    if mask is not None:
        sel &= np.asarray(mask) > 0
    idx = np.flatnonzero(sel)
    planes = np.zeros((n, h + 2 * d, w), np.uint8)
    planes.reshape(-1)[labels.ravel()[idx] * ((h + 2 * d) * w) + idx + d * w] = 1
    k = 2 * d + 1
    flat = planes.reshape(n * (h + 2 * d), w)
    if k * k <= 255:  # counts fit in 8 bits: a separable filter of ones is exact and 2× faster
        ones = np.ones(k, np.float32)
        out = cv2.sepFilter2D(flat, cv2.CV_8U, ones, ones, borderType=cv2.BORDER_CONSTANT)
    else:
        out = cv2.boxFilter(flat, cv2.CV_16U, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    return out.reshape(n, h + 2 * d, w)


def neighbour_counts(labels: np.ndarray, mask: np.ndarray | None, n: int, d: int) -> np.ndarray:
    """(H, W, N): :func:`neighbour_planes` without the padding, pixel-major."""
    h = labels.shape[0]
    return np.ascontiguousarray(neighbour_planes(labels, mask, n, d)[:, d : d + h].transpose(1, 2, 0))


def cooccurrence(labels: np.ndarray, mask: np.ndarray | None, n: int, d: int, normalise: bool = True) -> np.ndarray:
    """(N, N) histogram of label pairs of distinct pixels within distance d, both inside ``mask``;
    ``H[a, b]`` counts ordered pairs (a at p, b at q), so H is symmetric. Sums to 1 if normalised."""
    C = neighbour_counts(labels, mask, n, d)
    sel = labels >= 0 if mask is None else (labels >= 0) & (np.asarray(mask) > 0)
    lab = labels[sel]
    Cs = C[sel].astype(np.float64)
    H = np.zeros((n, n))
    np.add.at(H, lab, Cs)  # rows: label of p; columns: counts of labels around p
    H[np.arange(n), np.arange(n)] -= np.bincount(lab, minlength=n)  # a pixel is not its own pair
    if normalise:
        total = H.sum()
        if total > 0:
            H /= total
    return H


def chi2(h1: np.ndarray, h2: np.ndarray) -> float:
    """χ² distance Σ (a − b)² / (a + b) over bins where a + b > 0 (0 = identical, 2 = disjoint)."""
    a = np.asarray(h1, float).ravel()
    b = np.asarray(h2, float).ravel()
    s = a + b
    nz = s > 0
    return float(np.sum((a[nz] - b[nz]) ** 2 / s[nz]))


def train_rfch(
    images: list[np.ndarray], masks: list[np.ndarray], params: RFCHParams
) -> RFCHModel:
    """Learn centres from the object's pixels in all training views and their summed histogram."""
    if not images:
        raise ValueError("RFCH training needs at least one view")
    rng = np.random.default_rng(params.seed)
    descs = [descriptor_planes(im, params.scales) for im in images]
    samples = []
    per_view = max(1, params.max_samples // len(images))
    for D, m in zip(descs, masks):
        px = D[:, np.asarray(m) > 0].T
        if len(px):
            samples.append(px[rng.choice(len(px), min(per_view, len(px)), replace=False)])
    if not samples:
        raise ValueError("RFCH training: the object covers no pixel in any view")
    X = np.concatenate(samples)
    mean = X.mean(axis=0)
    # each dimension in units of its spread on the object; the chromaticities' spread is floored:
    # grey photos have none (r = g = ⅓ exactly), and a grey-trained model must still label a
    # grey object seen by a colour camera (chromaticity within a few hundredths of ⅓)
    floor = np.full(X.shape[1], 1e-6)
    floor[:2] = CHROMA_STD_FLOOR
    std = np.maximum(X.std(axis=0), floor)
    Xs = ((X - mean) / std).astype(np.float32)
    n = min(params.n_clusters, len(Xs))
    cv2.setRNGSeed(params.seed)
    _, _, centres = cv2.kmeans(
        Xs, n, None, (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4), 3, cv2.KMEANS_PP_CENTERS
    )
    H = np.zeros((n, n))
    sizes = []
    for D, m in zip(descs, masks):
        lab = label_planes(D, centres, mean, std)
        H += cooccurrence(lab, m, n, params.distance, normalise=False)
        ys, xs = np.nonzero(np.asarray(m) > 0)
        if len(xs):
            sizes.append((int(np.ptp(xs) + 1), int(np.ptp(ys) + 1)))
    H /= max(H.sum(), 1e-12)
    sizes_a = np.array(sizes)
    return RFCHModel(
        centres.astype(np.float32), H, tuple(float(s) for s in params.scales), n, int(params.distance),
        mean.astype(np.float32), std.astype(np.float32),
        tuple(int(v) for v in sizes_a.min(axis=0)), tuple(int(v) for v in sizes_a.max(axis=0)),
    )

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


def grey_world(image: np.ndarray) -> np.ndarray:
    """float32 BGR in [0, ~1] with every channel's mean scaled to 0.5: removes the illuminant's
    colour and overall brightness (grey-world assumption)."""
    img = np.asarray(image, np.float32)
    if img.ndim == 2:
        img = img[..., None].repeat(3, axis=2)
    img = img[..., :3]
    means = img.reshape(-1, 3).mean(axis=0)
    return img * (0.5 / np.maximum(means, 1e-6))


def pixel_descriptors(image: np.ndarray, scales: tuple[float, ...]) -> np.ndarray:
    """(H, W, 2 + 2·len(scales)) float32: r, g chromaticity, then per scale σ the gradient magnitude
    and the scale-normalised Laplacian (σ²∇²) of the grey-world intensity."""
    img = grey_world(image)
    s = img.sum(axis=2) + 1e-6
    chans = [img[..., 2] / s, img[..., 1] / s]  # r, g (OpenCV is BGR)
    intensity = s / 3.0
    for sigma in scales:
        blur = cv2.GaussianBlur(intensity, (0, 0), sigma)
        gx = cv2.Sobel(blur, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(blur, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        chans.append(np.sqrt(gx * gx + gy * gy) * sigma)
        chans.append(cv2.Laplacian(blur, cv2.CV_32F, ksize=3, scale=0.25) * sigma * sigma)
    return np.stack(chans, axis=-1).astype(np.float32)


def quantise(descriptors: np.ndarray, centres: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Label (H, W) int32 of the nearest centre for each pixel descriptor (H, W, D)."""
    h, w, dim = descriptors.shape
    x = ((descriptors.reshape(-1, dim) - mean) / std).astype(np.float32)
    c = centres.astype(np.float32)
    d2 = (x * x).sum(1, keepdims=True) - 2.0 * x @ c.T + (c * c).sum(1)[None]
    return np.argmin(d2, axis=1).astype(np.int32).reshape(h, w)


def label_image(image: np.ndarray, model: RFCHModel) -> np.ndarray:
    """The cluster label of every pixel of ``image`` under ``model`` (training and query alike)."""
    return quantise(pixel_descriptors(image, model.scales), model.centres, model.desc_mean, model.desc_std)


def neighbour_planes(labels: np.ndarray, mask: np.ndarray | None, n: int, d: int) -> np.ndarray:
    """(N, H, W) uint16: for each label, how many pixels of it lie within distance d of each pixel
    (Chebyshev, itself included), counting only pixels inside ``mask``.

    All N indicator planes are stacked into one tall image, with ``d`` zero rows between planes
    so the box never reaches across, and filtered by a single 8-bit → 16-bit box filter: ten
    times faster than filtering float planes four channels at a time.
    """
    h, w = labels.shape
    if (2 * d + 1) ** 2 > 65535:
        raise ValueError(f"pair distance {d} too large")
    planes = np.zeros((n, h + 2 * d, w), np.uint8)
    member = labels[None] == np.arange(n)[:, None, None]
    if mask is not None:
        member &= (np.asarray(mask) > 0)[None]
    planes[:, d : d + h] = member
    k = 2 * d + 1
    out = cv2.boxFilter(planes.reshape(n * (h + 2 * d), w), cv2.CV_16U, (k, k), normalize=False,
                        borderType=cv2.BORDER_CONSTANT)
    return out.reshape(n, h + 2 * d, w)[:, d : d + h]


def neighbour_counts(labels: np.ndarray, mask: np.ndarray | None, n: int, d: int) -> np.ndarray:
    """(H, W, N) float32: for each pixel, how many pixels of each label lie within distance d
    (Chebyshev, itself included), counting only pixels inside ``mask``."""
    return np.ascontiguousarray(neighbour_planes(labels, mask, n, d).transpose(1, 2, 0), dtype=np.float32)


def cooccurrence(labels: np.ndarray, mask: np.ndarray | None, n: int, d: int, normalise: bool = True) -> np.ndarray:
    """(N, N) histogram of label pairs of distinct pixels within distance d, both inside ``mask``;
    ``H[a, b]`` counts ordered pairs (a at p, b at q), so H is symmetric. Sums to 1 if normalised."""
    C = neighbour_counts(labels, mask, n, d)
    sel = np.ones(labels.shape, bool) if mask is None else np.asarray(mask) > 0
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
    descs = [pixel_descriptors(im, params.scales) for im in images]
    samples = []
    per_view = max(1, params.max_samples // len(images))
    for D, m in zip(descs, masks):
        px = D[np.asarray(m) > 0]
        if len(px):
            samples.append(px[rng.choice(len(px), min(per_view, len(px)), replace=False)])
    if not samples:
        raise ValueError("RFCH training: the object covers no pixel in any view")
    X = np.concatenate(samples)
    mean = X.mean(axis=0)
    std = np.maximum(X.std(axis=0), 1e-6)  # each dimension in units of its spread on the object
    Xs = ((X - mean) / std).astype(np.float32)
    n = min(params.n_clusters, len(Xs))
    cv2.setRNGSeed(params.seed)
    _, _, centres = cv2.kmeans(
        Xs, n, None, (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4), 3, cv2.KMEANS_PP_CENTERS
    )
    H = np.zeros((n, n))
    sizes = []
    for D, m in zip(descs, masks):
        lab = quantise(D, centres, mean, std)
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

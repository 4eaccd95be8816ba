"""SIFT keypoints and descriptors: the one extraction function used by training and by queries.

Training and recognition must describe images identically, so both call :func:`extract_features`
with the parameters stored in the model's manifest.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Features:
    """Keypoints (n, 2) float32 pixels, descriptors (n, 128) float32, SIFT sizes and angles (n,)."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    sizes: np.ndarray
    angles: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)

    def subset(self, keep: np.ndarray) -> "Features":
        return Features(self.keypoints[keep], self.descriptors[keep], self.sizes[keep], self.angles[keep])


def to_gray(image: np.ndarray) -> np.ndarray:
    """8-bit grey image from a BGR, BGRA or grey array."""
    if image.ndim == 2:
        return image if image.dtype == np.uint8 else cv2.convertScaleAbs(image)
    code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(image, code)


def root_sift(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT (Arandjelović & Zisserman 2012): L1-normalise then square-root; L2 distance then
    compares descriptors by the Hellinger kernel, which matches SIFT better than Euclidean."""
    d = np.asarray(descriptors, np.float32)
    d = d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(d).astype(np.float32)


# Run time's images (queries, views learned while tracking) are brightened until their 99th
# percentile reaches this grey level (:func:`stretched`); training's photos are taken as they are.
RUN_TIME_STRETCH = 230.0


def stretched(gray: np.ndarray, target: float, mask: np.ndarray | None = None) -> np.ndarray:
    """``gray`` (8-bit) scaled by ``target / p₉₉`` when its 99th percentile ``p₉₉`` (inside
    ``mask``, non-zero, if given) is below ``target``; else ``gray`` itself (never darkened).

    Why: SIFT's contrast threshold is absolute (a share of the full grey scale), so the same
    object in a dimmer light, or a dark object, gives fewer keypoints — the zoo walks' lamp
    switched off (gain 0.6) left the tracker's re-anchoring and re-finding with too few. SIFT's
    descriptors are normalised, so a gain changes which keypoints are found, not how they match.
    On the 24 zoo walks as live streams, brightening queries and learned views so: frames lost
    while ≥ 30 % visible 3463 → 3253, poses beyond 5 %/5° 4 → 1 (bench/RESULTS.md, session 38).

    >>> g = np.array([[10, 50], [100, 115]], np.uint8)
    >>> stretched(g, 230.0).tolist(), stretched(g, 100.0) is g
    ([[20, 100], [201, 231]], True)
    """
    region = gray[np.asarray(mask) > 0] if mask is not None else gray
    if not region.size:
        return gray
    p = percentile_99(region)
    if p <= 0 or target / p <= 1.0:
        return gray
    return cv2.convertScaleAbs(gray, alpha=target / p)


def percentile_99(values: np.ndarray) -> float:
    """``np.percentile(values, 99)`` of 8-bit ``values`` (the same float, numpy's linear method
    term for term), from their histogram: a count instead of a partial sort (0.3 instead of
    3.7 ms on a 640×480 frame).

    >>> v = np.arange(200, dtype=np.uint8)
    >>> bool(percentile_99(v) == np.percentile(v, 99)), percentile_99(v)
    (True, 197.01)
    """
    n = values.size
    cum = np.cumsum(np.bincount(np.asarray(values, np.uint8).ravel(), minlength=256))
    virtual = (n - 1) * 0.99
    lo = int(np.floor(virtual))
    hi = min(lo + 1, n - 1)
    a = float(np.searchsorted(cum, lo, side="right"))  # the lo-th smallest value (0-based)
    b = float(np.searchsorted(cum, hi, side="right"))
    t = virtual - lo
    diff = b - a
    return b - diff * (1 - t) if t >= 0.5 else a + diff * t


def extract_features(
    image: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    max_features: int = 1500,
    erode_px: int = 0,
    use_root_sift: bool = False,
    contrast_threshold: float = 0.04,
    stretch_to: float | None = None,
) -> Features:
    """SIFT on ``image`` inside ``mask`` (non-zero = allowed), eroded by ``erode_px`` so that no
    keypoint sits on the silhouette, where its descriptor would describe the background too.
    ``stretch_to``: brighten a dim image first (:func:`stretched`, judged inside ``mask``)."""
    gray = to_gray(image)
    allowed = None if mask is None else np.asarray(mask) > 0
    if stretch_to:
        gray = stretched(gray, stretch_to, allowed)
    m = None
    if allowed is not None:
        m = allowed.astype(np.uint8) * 255
        if erode_px > 0:
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1,) * 2)
            m = cv2.erode(m, k)
        if not np.any(m):
            return _empty()
    sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=contrast_threshold)
    kps, desc = sift.detectAndCompute(gray, m)
    if desc is None or not kps:
        return _empty()
    pts = np.array([k.pt for k in kps], dtype=np.float32).reshape(-1, 2)
    desc = desc.astype(np.float32)
    if use_root_sift:
        desc = root_sift(desc)
    sizes = np.array([k.size for k in kps], dtype=np.float32)
    angles = np.array([k.angle for k in kps], dtype=np.float32)
    # SIFT may return one location twice with two orientations; both are kept (they match differently)
    return Features(pts, desc, sizes, angles)


def _empty() -> Features:
    return Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32),
                    np.zeros(0, np.float32), np.zeros(0, np.float32))

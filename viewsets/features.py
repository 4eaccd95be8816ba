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


def extract_features(
    image: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    max_features: int = 1500,
    erode_px: int = 0,
    use_root_sift: bool = False,
    contrast_threshold: float = 0.04,
) -> Features:
    """SIFT on ``image`` inside ``mask`` (non-zero = allowed), eroded by ``erode_px`` so that no
    keypoint sits on the silhouette, where its descriptor would describe the background too."""
    gray = to_gray(image)
    m = None
    if mask is not None:
        m = (np.asarray(mask) > 0).astype(np.uint8) * 255
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

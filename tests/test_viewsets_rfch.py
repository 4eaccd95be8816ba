"""RFCH: the pair histogram against brute force, normalisation, determinism, invariances."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from quatrack.viewsets.mesh import load_mesh
from quatrack.viewsets.render import render
from quatrack.viewsets.rfch import RFCHParams, chi2, cooccurrence, label_image, train_rfch
from quatrack.viewsets.spec import load_spec

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cookie-box"


def brute_force(labels, mask, n, d):
    H = np.zeros((n, n))
    ys, xs = np.nonzero(mask)
    for y, x in zip(ys, xs):
        for y2, x2 in zip(ys, xs):
            if (y, x) != (y2, x2) and abs(y - y2) <= d and abs(x - x2) <= d:
                H[labels[y, x], labels[y2, x2]] += 1
    return H


@pytest.mark.parametrize("d", [1, 2, 3])
def test_cooccurrence_equals_brute_force(d):
    rng = np.random.default_rng(d)
    labels = rng.integers(0, 5, size=(12, 15)).astype(np.int32)
    mask = rng.random((12, 15)) > 0.3
    H = cooccurrence(labels, mask, 5, d, normalise=False)
    np.testing.assert_allclose(H, brute_force(labels, mask, 5, d))
    Hn = cooccurrence(labels, mask, 5, d)
    assert Hn.sum() == pytest.approx(1.0) and np.allclose(Hn, Hn.T)


def test_chi2_bounds():
    rng = np.random.default_rng(0)
    a = rng.random(20); a /= a.sum()
    b = np.zeros(20); b[0] = 1.0
    c = np.zeros(20); c[1] = 1.0
    assert chi2(a, a) == 0.0
    assert chi2(b, c) == pytest.approx(2.0)
    assert 0 < chi2(a, b) < 2


@pytest.fixture(scope="module")
def photo_and_mask():
    spec = load_spec(EXAMPLE / "object.json")
    v = spec.views[0]
    img = cv2.imread(str(v.image_path))
    return img, render(load_mesh(spec.mesh_path), v.camera, v.pose).mask


def test_model_histogram_normalised_and_deterministic(photo_and_mask):
    img, mask = photo_and_mask
    m1 = train_rfch([img], [mask], RFCHParams())
    m2 = train_rfch([img.copy()], [mask.copy()], RFCHParams())
    assert m1.histogram.shape == (m1.n_clusters, m1.n_clusters) and m1.n_clusters == RFCHParams().n_clusters and m1.histogram.sum() == pytest.approx(1.0)
    assert np.all(m1.histogram >= 0)
    np.testing.assert_array_equal(m1.centres, m2.centres)
    np.testing.assert_array_equal(m1.histogram, m2.histogram)
    np.testing.assert_array_equal(label_image(img, m1), label_image(img, m2))


def test_object_window_closer_than_background_windows(photo_and_mask):
    img, mask = photo_and_mask
    m = train_rfch([img], [mask], RFCHParams())
    lab = label_image(img, m)
    ys, xs = np.nonzero(mask)
    # a half-size window at the object's centre, against every half-size window off the object
    cx, cy = int(xs.mean()), int(ys.mean())
    w, h = (xs.max() - xs.min()) // 2, (ys.max() - ys.min()) // 2
    x0, y0 = cx - w // 2, cy - h // 2

    def window_chi2(x, y):
        return chi2(cooccurrence(lab[y : y + h, x : x + w], None, m.n_clusters, m.distance), m.histogram)

    obj = window_chi2(x0, y0)
    H, W = mask.shape
    backgrounds = []
    for x in range(0, W - w + 1, 20):
        for y in range(0, H - h + 1, 20):
            if np.count_nonzero(mask[y : y + h, x : x + w]) < 0.2 * w * h:
                backgrounds.append(window_chi2(x, y))
    assert len(backgrounds) >= 10 and obj < min(backgrounds)


def test_labels_survive_an_illuminant_change(photo_and_mask):
    """Grey-world + chromaticity: a coloured, dimmer light leaves most labels as they were."""
    img, mask = photo_and_mask
    m = train_rfch([img], [mask], RFCHParams())
    tinted = np.clip(img.astype(np.float32) * np.array([1.15, 0.95, 0.75]) * 0.8, 0, 255).astype(np.uint8)
    same = label_image(img, m) == label_image(tinted, m)
    assert same[mask > 0].mean() > 0.8

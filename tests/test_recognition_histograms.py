"""The fast localisation pieces against brute force: nearest centre, neighbour counts, cell
histograms (all bins, listed bins + pooled, sampled centres), and the window search's boxes."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from quatrack.recognition.window_search import (
    WindowSearchParams, _cell_histograms_numpy, _Integral, _score_windows, cell_histograms, chi2_rows, compress,
)
from quatrack.viewsets.rfch import nearest_centres, neighbour_counts


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 40), st.integers(1, 6))
def test_nearest_centres_is_the_argmin(seed, k, dim):
    rng = np.random.default_rng(seed)
    X = rng.normal(2.0, 3.0, size=(dim, 500)).astype(np.float32)
    C = rng.normal(0.0, 1.0, size=(k, dim)).astype(np.float32)
    mean, std = rng.normal(size=dim).astype(np.float32), rng.uniform(0.5, 2.0, dim).astype(np.float32)
    lab, d2 = nearest_centres(X, C, mean, std, block=128)  # several blocks and a partial one
    xs = (X.T - mean) / std
    D = ((xs[:, None, :].astype(np.float64) - C[None]) ** 2).sum(-1)
    best = D.min(1)
    # the label is a nearest centre (ties within float32 rounding either way)
    assert np.all(D[np.arange(len(lab)), lab] <= best + 1e-4 * (1 + best))
    np.testing.assert_allclose(d2, best, rtol=1e-4, atol=1e-3)


def brute_counts(labels, n, d):
    H, W = labels.shape
    out = np.zeros((H, W, n), int)
    for y in range(H):
        for x in range(W):
            win = labels[max(y - d, 0) : y + d + 1, max(x - d, 0) : x + d + 1]
            out[y, x] = np.bincount(win[win >= 0], minlength=n)
    return out


@pytest.mark.parametrize("d", [1, 3, 8])  # 8: (2d+1)² > 255, the 16-bit path
def test_neighbour_counts_brute_force(d):
    rng = np.random.default_rng(d)
    labels = rng.integers(-1, 4, size=(20, 23)).astype(np.int32)
    labels[:12, :12] = 2  # dense enough to reach the maximum count
    np.testing.assert_array_equal(neighbour_counts(labels, None, 4, d), brute_counts(labels, 4, d))


def brute_cells(labels, n, d, cell, stride=1):
    """Pairs (p, q), p ≠ q, both labelled, |p − q|∞ ≤ d, p sampled and inside a whole cell."""
    H, W = labels.shape
    rows, cols = H // cell, W // cell
    out = np.zeros((rows, cols, n * n))
    N = brute_counts(labels, n, d)
    o = stride // 2
    for y in range(o, rows * cell, stride):
        for x in range(o, cols * cell, stride):
            a = labels[y, x]
            if a < 0:
                continue
            counts = N[y, x].copy()
            counts[a] -= 1
            out[y // cell, x // cell, a * n : (a + 1) * n] += counts
    return out


@pytest.mark.parametrize("histograms", [cell_histograms, _cell_histograms_numpy], ids=["compiled", "numpy"])
@pytest.mark.parametrize("stride", [1, 2])
def test_cell_histograms_brute_force(stride, histograms):
    rng = np.random.default_rng(stride)
    n, d, cell = 5, 2, 4
    labels = rng.integers(-1, n, size=(19, 26)).astype(np.int32)  # ragged edge: partial cells
    ref = brute_cells(labels, n, d, cell, stride)
    np.testing.assert_allclose(histograms(labels, n, d, cell, stride=stride), ref)
    # listed bins + everything else pooled: the same pairs, coarser binning
    bins = np.sort(rng.choice(n * n, 7, replace=False))
    got = histograms(labels, n, d, cell, bins, stride)
    np.testing.assert_allclose(got, compress(ref, bins), atol=1e-4)
    # pairs of one label (a, a) listed and not: p must not count itself in its own bin
    own = np.array([0, 3, 6, 7, 18, 21])  # (0,0) (0,3) (1,1) (1,2) (3,3) (4,1)
    np.testing.assert_allclose(histograms(labels, n, d, cell, own, stride), compress(ref, own), atol=1e-4)
    with pytest.raises(ValueError):
        histograms(labels, n, d, cell, bins[::-1])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 12), st.sampled_from([1, 3, 8]), st.integers(1, 3), st.booleans())
def test_compiled_cell_histograms_give_the_numpy_answer(seed, n, d, stride, listed):
    """The compiled pass (whole-number counts: any order of additions gives the same bits)
    against its numpy original, on label maps with unlabelled pixels, listed bins or all, and a
    distance whose counts need 16 bits (d = 8)."""
    rng = np.random.default_rng(seed)
    labels = rng.integers(-1, n, size=(int(rng.integers(16, 40)), int(rng.integers(16, 40)))).astype(np.int32)
    bins = np.sort(rng.choice(n * n, int(rng.integers(1, n * n + 1)), replace=False)) if listed else None
    cell = int(rng.integers(2, 9))
    np.testing.assert_array_equal(cell_histograms(labels, n, d, cell, bins, stride),
                                  _cell_histograms_numpy(labels, n, d, cell, bins, stride))


def test_window_boxes_and_chi2_brute_force():
    rng = np.random.default_rng(0)
    C = rng.integers(0, 5, size=(6, 9, 4)).astype(np.float32)
    m = np.array([0.1, 0.2, 0.3, 0.4], np.float32)
    params = WindowSearchParams(ring=0.34, min_ring_inside=0.0, ring_weight_power=0.0)
    I = _Integral.of(C, pad=3)
    y, x, w, h = (np.array(v) for v in ([0, 2, 3], [0, 4, 1], [3, 5, 2], [2, 4, 3]))
    score, c_in, c_ring = _score_windows(I, m, y, x, w, h, params)

    def chi2(hist):
        hn = hist / hist.sum()
        return float(((hn - m) ** 2 / (hn + m)).sum())

    for i in range(3):
        inner = C[y[i] : y[i] + h[i], x[i] : x[i] + w[i]].sum((0, 1))
        rh, rw = max(1, round(0.34 * h[i])), max(1, round(0.34 * w[i]))  # the ring, clipped to the grid
        outer = C[max(y[i] - rh, 0) : y[i] + h[i] + rh, max(x[i] - rw, 0) : x[i] + w[i] + rw].sum((0, 1))
        assert c_in[i] == pytest.approx(chi2(inner), rel=1e-5)
        assert c_ring[i] == pytest.approx(chi2(outer - inner), rel=1e-5)
        assert score[i] == pytest.approx(c_in[i] - c_ring[i], rel=1e-5)
    assert chi2_rows(np.zeros((1, 4), np.float32), m)[0] == 2.0  # an empty window is as far as can be


def test_chi2_rows_with_empty_model_bins():
    m = np.array([0.5, 0.5, 0.0, 0.0], np.float32)
    h = np.array([[1, 1, 0, 0], [0, 0, 3, 1], [1, 0, 0, 1]], np.float32)
    got = chi2_rows(h.copy(), m)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, [0.0, 2.0, 1.0], atol=1e-6)  # last: 0 + .25/.5 + 0 + .25/.5

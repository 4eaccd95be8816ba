"""Float images' range (``recognition.images.to_bgr8``, the one place every caller — locate, the
tracker, REST and WebSocket uploads — converts them): 0..1 when the largest value is at most 1.1
(clipped), 0..255 from 2 (up to 280.5, clipped), 0..1 clipped and warned of once in between,
refused beyond. A 0..2 image was read as 0..255: all but black, and nothing found in it."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from quatrack.recognition import images as I
from quatrack.recognition.images import FloatRangeWarning, ImageError, to_bgr8


@pytest.fixture
def fresh(monkeypatch):
    """As in a new process: the warning not given yet."""
    monkeypatch.setattr(I, "_float_warned", False)


def _frame(top: float, dtype=np.float32, shape=(60, 80, 3)) -> np.ndarray:
    img = np.random.default_rng(5).uniform(0, top, shape).astype(dtype)
    img[0, 0, 0] = top
    return img


def _quiet(fn):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return fn()


@pytest.mark.parametrize("top", [0.0, 0.5, 1.0, 1.08])
def test_zero_to_one_is_scaled_by_255_an_overshoot_clipped(fresh, top):
    img = _frame(top, np.float64)
    assert np.array_equal(_quiet(lambda: to_bgr8(img)), np.clip(img * 255.0, 0, 255).astype(np.uint8))


@pytest.mark.parametrize("top", [2.0, 40.0, 255.0, 270.0])
def test_zero_to_255_is_taken_as_it_is(fresh, top):
    img = _frame(top)
    assert np.array_equal(_quiet(lambda: to_bgr8(img)), np.clip(img, 0, 255).astype(np.uint8))


def test_zero_to_two_is_read_as_zero_to_one_clipped_and_warned_of_once(fresh):
    img = _frame(1.9)
    with pytest.warns(FloatRangeWarning) as caught:
        out = to_bgr8(img)
    assert np.array_equal(out, np.clip(img * 255.0, 0, 255).astype(np.uint8))
    assert out.mean() > 100  # (read as 0..255 it was all but black: a mean of ~1)
    assert len(caught) == 1 and caught[0].filename == __file__  # (named at the caller's line)
    text = str(caught[0].message)
    assert "reach 1.9" in text and "read as 0..1, clipped at 1" in text and "Warned once" in text, text
    assert np.array_equal(_quiet(lambda: to_bgr8(img)), out)  # once: a stream would repeat it every frame


@pytest.mark.parametrize("top", [281.0, 4095.0, 65535.0])
def test_values_beyond_0_255_are_refused_naming_the_largest(fresh, top):
    with pytest.raises(ImageError, match=rf"a float image's values reach {top:g}: neither 0\.\.1 nor 0\.\.255"):
        to_bgr8(_frame(top))


def test_nan_and_infinities_keep_their_reading(fresh):
    img = _frame(0.5)
    img[1, 1], img[2, 2], img[3, 3] = np.nan, np.inf, -np.inf
    out = _quiet(lambda: to_bgr8(img))
    assert out[1, 1].tolist() == [0, 0, 0] and out[2, 2].tolist() == [255, 255, 255] and out[3, 3].tolist() == [0, 0, 0]


@pytest.mark.parametrize("fill", [np.nan, np.inf, -np.inf])
def test_a_frame_mostly_not_finite_is_refused(fresh, fill):
    # a float32 frame full of NaN was read as black and answered lost, "no object-like window"
    img = _frame(0.5)
    img[:40] = fill  # (2/3 of the rows)
    with pytest.raises(ImageError, match=r"^a float image whose values are 67 % NaN or infinite \(at most 50 % are "
                                         r"taken, read as 0, \+inf as 1\); if they are meant as black, replace them "
                                         r"by 0 \(np\.nan_to_num\)$"):
        to_bgr8(img)
    with pytest.raises(ImageError, match="100 % NaN or infinite"):
        to_bgr8(np.full((48, 64, 3), np.nan, np.float32))

"""10- and 12-bit camera data stored as uint16 (recognition/images.py): the default stays
full-range 16-bit (top 8 bits, bit for bit as before); data that looks like 10/12 bits is warned
of once, and ``bits=`` states the depth."""

import warnings

import numpy as np
import pytest

from quatrack.recognition import images as I
from quatrack.recognition.images import BitDepthWarning, ImageError, prepare_image, to_bgr8
from quatrack.tracking.camera import PinholeCamera


@pytest.fixture
def fresh(monkeypatch):
    """As in a new process: the warning not given yet."""
    monkeypatch.setattr(I, "_depth_warned", False)


def _frame(top: int, shape=(120, 160)) -> np.ndarray:
    rng = np.random.default_rng(11)
    img = rng.integers(0, top + 1, shape).astype(np.uint16)
    img[0, 0] = top
    return img


def _no_warning(fn):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = fn()
    assert not [w for w in caught if issubclass(w.category, BitDepthWarning)], [str(w.message) for w in caught]
    return out


@pytest.mark.parametrize("top, depth, shift", [(4095, 12, 4), (1023, 10, 6)])
def test_low_depth_data_is_converted_as_before_and_warned_of_once_with_what_to_do(fresh, top, depth, shift):
    img = _frame(top)
    with pytest.warns(BitDepthWarning) as caught:
        out = to_bgr8(img)
    assert np.array_equal(out, np.repeat((img >> 8).astype(np.uint8)[..., None], 3, axis=2))  # the default, unchanged
    assert len(caught) == 1 and caught[0].filename == __file__  # (named at the caller's line)
    text = str(caught[0].message)
    assert f"at most {top}" in text and f"bits={depth}" in text and f"image << {shift}" in text, text
    _no_warning(lambda: to_bgr8(img))  # once: a stream would repeat it every frame


def test_the_warning_names_the_callers_line_whichever_function_took_the_image(monkeypatch):
    # (through prepare_image it named a line of images.py: the user could not tell which call)
    cam = PinholeCamera(200.0, 200.0, 80.0, 60.0, width=160, height=120)
    for call in (lambda: to_bgr8(_frame(4095)), lambda: prepare_image(_frame(4095), cam)):
        monkeypatch.setattr(I, "_depth_warned", False)
        with pytest.warns(BitDepthWarning) as caught:
            call()
        assert [w.filename for w in caught] == [__file__]


@pytest.mark.parametrize("img", [
    np.full((40, 40), 4095, np.uint16),  # tiny: too few pixels to judge
    np.zeros((120, 160), np.uint16),  # black whatever its depth
    _frame(65535),  # full range
    _frame(4096),  # beyond 12 bits
    np.full((120, 160), 255, np.uint8),  # not 16-bit
], ids=["tiny", "black", "16-bit", "13-bit", "8-bit"])
def test_what_cannot_be_low_depth_data_is_not_warned_of(fresh, img):
    _no_warning(lambda: to_bgr8(img))


def test_bits_states_the_depth(fresh):
    img = _frame(4095, (120, 160, 3))
    out = _no_warning(lambda: to_bgr8(img, bits=12))
    assert np.array_equal(out, to_bgr8(img << 4)) and out.max() == 255  # as scaled to 16 bits first
    with pytest.warns(BitDepthWarning):
        default = to_bgr8(img)
    assert np.array_equal(to_bgr8(img, bits=16), default)
    ten = _frame(1023)
    assert np.array_equal(to_bgr8(ten, bits=10)[..., 0], (ten >> 2).astype(np.uint8))
    eight = _frame(255)
    assert np.array_equal(to_bgr8(eight, bits=8)[..., 0], eight.astype(np.uint8))
    as_8bit = np.full((40, 40), 200, np.uint8)  # other pixel types: bits does not apply
    assert np.array_equal(to_bgr8(as_8bit, bits=12), to_bgr8(as_8bit))
    cam = PinholeCamera(200.0, 200.0, 80.0, 60.0, width=160, height=120)
    prepared = _no_warning(lambda: prepare_image(img, cam, bits=12))
    assert np.array_equal(prepared.image, out)


def test_values_beyond_the_stated_bits_are_refused(fresh):
    # 12-bit data already scaled to 16 bits (MSB-aligned), said to be 12-bit: it would be all white
    with pytest.raises(ImageError, match=r"pixel value of 65520 does not fit bits=12 \(at most 4095\).*leave bits out"):
        to_bgr8(_frame(4095) << 4, bits=12)


@pytest.mark.parametrize("bits", [0, 7, 17, 12.0, True, "12"])
def test_a_bit_depth_that_is_not_one_is_refused(bits):
    with pytest.raises(ValueError, match="bits must be a whole number from 8 to 16"):
        to_bgr8(_frame(4095), bits=bits)

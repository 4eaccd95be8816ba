"""Input images: decode, check and normalise what users send, before any vision runs.

Everything downstream sees one kind of image: 8-bit BGR, at most ``max_pixels`` pixels. A
larger image is downscaled (the camera is scaled with it, so poses stay in the original camera's
frame); anything that cannot be a photo of the object is refused with :class:`ImageError`.
"""

from __future__ import annotations

import os
import struct
import sys
import warnings
from dataclasses import dataclass, replace

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.camera import check_lens, resized_for, stated_size_doubt, within_pixels
from quatrack.viewsets.errors import SpecError
from quatrack.viewsets.imagefile import FORMAT_NAMES, sniff, truncated

MIN_SIDE = 32
DEFAULT_MAX_PIXELS = 4_000_000  # beyond this an image is downscaled (e.g. 8000×6000 → 2309×1732)
MAX_DECODE_PIXELS = 100_000_000  # refuse to even decode images larger than this
# a uint16 image of at least LOW_DEPTH_MIN_PIXELS pixels whose values all lie below LOW_DEPTH_MAX
# (the range of 12-bit data) is, read as full-range 16-bit (its top 8 bits, ≤ 15 of 255), all but
# black: most likely 10- or 12-bit camera data, which to_bgr8 warns of once (BitDepthWarning)
LOW_DEPTH_MAX = 4096
LOW_DEPTH_MIN_PIXELS = 64 * 64
# A float image's range, from its largest value (_float_to_8): 0..1 up to FLOAT_SLACK above 1 (a
# resampled image's overshoot, clipped); 0..255 from FLOAT_255_MIN up to FLOAT_SLACK above 255;
# between the two (read as 0..255 it would be black to within 1 %: 0..2 was) 0..1, clipped, and
# warned of once (FloatRangeWarning); above, neither (ImageError)
FLOAT_SLACK = 0.1
FLOAT_255_MIN = 2.0
# The share of a float image's values that may be NaN or ±inf (read as 0, or 1 for +inf: a few
# dead or masked pixels); beyond it the image is refused (ImageError): a frame full of NaN was
# read as black and answered "not found"
FLOAT_MAX_NONFINITE = 0.5

__all__ = ["DEFAULT_MAX_PIXELS", "MAX_DECODE_PIXELS", "MIN_SIDE", "BitDepthWarning", "FloatRangeWarning", "ImageError",
           "ImageSizeError", "PreparedImage",
           "decode_image", "header_size", "prepare_image", "read_image", "size_mismatch", "sniff", "to_bgr8", "too_small",
           "truncated"]


class ImageError(ValueError):
    """The image cannot be used: unreadable, empty, too small, or not matching its camera."""


class ImageSizeError(ImageError):
    """An image of another size than its camera states. Why a type of its own: a caller that
    knows a better remedy than the library's (the command line cannot ``pass camera.scaled``)
    replaces :attr:`hint` without parsing the message.

    ``str(err) == err.base + err.hint``; ``camera_size`` and ``image_size`` are ``(w, h)``;
    ``hint`` is :func:`resize_hint`'s ("" when the image is not the camera's resized).

    >>> from quatrack.tracking.camera import PinholeCamera
    >>> err = size_mismatch(PinholeCamera(500, 500, 320, 240, width=640, height=480), 320, 240)
    >>> err.image_size, err.hint
    ((320, 240), ' (its images resized by 0.5? pass camera.scaled(0.5, 320, 240))')
    """

    def __init__(self, base: str, hint: str = "", camera_size=None, image_size=None):
        super().__init__(base + hint)
        self.base, self.hint, self.camera_size, self.image_size = base, hint, camera_size, image_size

    def __reduce__(self):  # (pickled whole: a worker process's error keeps its parts)
        return type(self), (self.base, self.hint, self.camera_size, self.image_size)


class BitDepthWarning(UserWarning):
    """A 16-bit image that looks like 10- or 12-bit data read as full-range 16-bit (almost black)."""


class FloatRangeWarning(UserWarning):
    """A float image whose largest value is neither within 0..1 nor that of a 0..255 image."""


_depth_warned = False  # (BitDepthWarning is given once a process: a stream would repeat it every frame)
_float_warned = False  # (FloatRangeWarning too)


@dataclass(frozen=True)
class PreparedImage:
    """An 8-bit BGR image ready for recognition, with the camera that fits it.

    ``scale`` maps pixels of the original image to this one (``uv_here = scale·(uv + ½) − ½``).
    """

    image: np.ndarray
    camera: PinholeCamera
    scale: float


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    i = 2
    n = len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # standalone markers
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
            if i + 9 > n:
                return None
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        i += 2 + length
    return None


def _png_size(data: bytes) -> tuple[int, int] | None:
    if len(data) < 24 or data[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", data[16:24])


def _webp_size(data: bytes) -> tuple[int, int] | None:
    chunk = data[12:16]
    if chunk == b"VP8X" and len(data) >= 30:
        w = 1 + int.from_bytes(data[24:27], "little")
        h = 1 + int.from_bytes(data[27:30], "little")
        return w, h
    if chunk == b"VP8 " and len(data) >= 30:
        w, h = struct.unpack("<HH", data[26:30])
        return w & 0x3FFF, h & 0x3FFF
    if chunk == b"VP8L" and len(data) >= 25:
        b = int.from_bytes(data[21:25], "little")
        return (b & 0x3FFF) + 1, ((b >> 14) & 0x3FFF) + 1
    return None


def header_size(data: bytes, fmt: str) -> tuple[int, int] | None:
    """(width, height) from the header, or None when the header is unreadable."""
    try:
        return {"jpeg": _jpeg_size, "png": _png_size, "webp": _webp_size}[fmt](data)
    except struct.error:
        return None


def _png_damaged_chunk(data: bytes) -> str | None:
    """The type of the first chunk of a PNG whose CRC does not match its bytes, or None (a
    chunk running past the end is left to the decoder)."""
    import zlib

    view, pos = memoryview(data), 8
    while pos + 12 <= len(data):
        n = int.from_bytes(view[pos:pos + 4], "big")
        end = pos + 12 + n
        if end > len(data):
            return None
        if zlib.crc32(view[pos + 4:end - 4]) != int.from_bytes(view[end - 4:end], "big"):
            return "".join(c if c.isalpha() else "?" for c in bytes(view[pos + 4:pos + 8]).decode("latin-1"))
        if view[pos + 4:pos + 8] == b"IEND":
            return None
        pos = end
    return None


def decode_image(data: bytes) -> np.ndarray:
    """Decode JPEG/PNG/WebP/... bytes (any bit depth, grey or colour; an alpha channel is dropped)
    to an array, turned upright by its EXIF orientation as training's ``cv2.imread`` turns the
    photos (``IMREAD_UNCHANGED`` ignored it: a phone's portrait photo came sideways, so the
    camera of its registration did not fit it)."""
    if not data:
        raise ImageError("the image is empty (0 bytes)")
    fmt = sniff(data)
    size = header_size(data, fmt) if fmt else None
    if size is not None and size[0] * size[1] > MAX_DECODE_PIXELS:
        # (read from the header: a 120-megapixel file took ~700 MB to decode before it was refused)
        raise ImageError(f"the image is too large ({size[0]}×{size[1]} px; at most {MAX_DECODE_PIXELS} pixels)")
    if fmt is not None and truncated(data, fmt):
        # (libpng would say "PNG input buffer is incomplete" on stderr, libjpeg "Premature end of
        # JPEG file", beside this message; and OpenCV decoded a JPEG cut short, its end grey)
        raise ImageError(f"the image cannot be decoded (a {FORMAT_NAMES[fmt]} without its end: truncated)")
    if fmt == "png" and (bad := _png_damaged_chunk(data)) is not None:
        # (libpng would say "libpng error: bad adaptive filter value" on stderr, beside this message)
        raise ImageError(f"the image cannot be decoded (a damaged PNG: its {bad} chunk fails its checksum)")
    buf = np.frombuffer(data, dtype=np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if img is None or img.size == 0:
        raise ImageError("the image cannot be decoded (not an image, or truncated)")
    return img


def read_image(path: str) -> np.ndarray:
    """Read an image file with the same checks as :func:`decode_image`."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise ImageError(f"cannot read image {path}: {exc.strerror or exc}") from None
    try:
        return decode_image(data)
    except ImageError as exc:
        raise ImageError(f"{path}: {exc}") from None


def resize_hint(camera, w: int, h: int) -> str:
    """The end of a size-mismatch message: how to pass a camera for images that are its own
    resized (the same aspect ratio: :func:`~quatrack.viewsets.camera.resized_for`), else ""."""
    _, note = resized_for(camera, w, h)
    if note is None:
        return ""
    return f" (its images resized by {w / camera.width:.3g}? pass camera.scaled({w / camera.width:.3g}, {w}, {h}))"


def size_mismatch(camera, w: int, h: int, what: str = "image") -> ImageSizeError:
    """The error refusing a ``w``×``h`` ``what`` (an image, a frame) for a camera sized otherwise.
    When the camera's own numbers say its stated size is the wrong one
    (:func:`~quatrack.viewsets.camera.stated_size_doubt`), that is said and no resizing is
    hinted: scaled, such a camera halves or doubles the focal length, and the object is found
    at the wrong depth (a REST client that followed the hint: 47 % off, reported found)."""
    base = f"the camera is for {camera.width}×{camera.height} px images but the {what} is {w}×{h} px"
    doubt = stated_size_doubt(camera, w, h)
    if doubt is not None:
        return ImageSizeError(f"{base} ({doubt})", "", (camera.width, camera.height), (w, h))
    return ImageSizeError(base, resize_hint(camera, w, h), (camera.width, camera.height), (w, h))


def too_small(w: int, h: int) -> str:
    """The message refusing a ``w``×``h`` image below :data:`MIN_SIDE` (an empty one too)."""
    return f"the image is too small ({w}×{h} px; at least {MIN_SIDE} px a side)"


def _check_bits(bits) -> None:
    if bits is not None and (isinstance(bits, (bool, np.bool_)) or not isinstance(bits, (int, np.integer))
                             or not 8 <= bits <= 16):
        raise ValueError(f"bits must be a whole number from 8 to 16 (the significant bits of uint16 pixels, "
                         f"e.g. 12 for a 12-bit camera), got {bits!r}"[:160])


_HERE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def _caller_level() -> int:
    """``warnings.warn``'s stacklevel, for a call from the function that called this one, of the
    first frame outside quatrack.recognition: the warning names the line of the caller's code
    that handed the image in (``to_bgr8``, ``prepare_image``, ``locate`` or ``Tracker.step``), not
    a line of ours."""
    frame, level = sys._getframe(1), 1
    while frame.f_back is not None and os.path.abspath(frame.f_code.co_filename).startswith(_HERE):
        frame, level = frame.f_back, level + 1
    return level


def _uint16_to_8(img: np.ndarray, bits: int | None) -> np.ndarray:
    """``uint16`` pixels of ``bits`` significant bits (None: full-range 16-bit) as 8-bit: their top
    8 bits. Without ``bits``, an image that looks like 10- or 12-bit data (:data:`LOW_DEPTH_MAX`)
    is warned of once (:class:`BitDepthWarning`): read as 16-bit it came out almost black, in
    silence, and nothing was found in it. With ``bits``, a value beyond them is refused: the data
    is not what ``bits`` says (12-bit data already scaled to 16 bits: leave ``bits`` out)."""
    global _depth_warned
    if bits is None:
        if not _depth_warned and img.shape[0] * img.shape[1] >= LOW_DEPTH_MIN_PIXELS:
            top = int(img.max())
            if 0 < top < LOW_DEPTH_MAX:
                _depth_warned = True
                depth, shift = (10, 6) if top < 1024 else (12, 4)
                warnings.warn(
                    f"a 16-bit image whose values all lie below {LOW_DEPTH_MAX} (at most {top}) is read as full-range "
                    f"16-bit (its top 8 bits) and comes out almost black: {depth}-bit camera data? State the depth "
                    f"(quatrack.recognition.images.to_bgr8(image, bits={depth}), then pass the 8-bit image on) or "
                    f"scale it to 16 bits first (image << {shift}). Warned once.", BitDepthWarning,
                    stacklevel=_caller_level())
        return (img >> 8).astype(np.uint8)
    top = int(img.max()) if img.size else 0
    if top >= 1 << bits:
        raise ImageError(f"a pixel value of {top} does not fit bits={bits} (at most {(1 << bits) - 1}): the data "
                         f"has more significant bits (already scaled to 16 bits? then leave bits out)")
    return (img >> (bits - 8)).astype(np.uint8)


def _float_to_8(img: np.ndarray) -> np.ndarray:
    """Float pixels as 8-bit, their range told by the largest value (NaN and -inf as 0, +inf as
    1; more than :data:`FLOAT_MAX_NONFINITE` of them non-finite: :class:`ImageError`): up to 1.1,
    0..1 (scaled by 255; above 1, a resampled image's overshoot, clipped); from
    2 to 280.5, 0..255 (clipped). Between 1.1 and 2 the image is 0..1 with values above it (HDR
    data, an exposure gain): read as 0..255 it came out black, so it is read as 0..1, clipped,
    and warned of once (:class:`FloatRangeWarning`). Above 280.5 it is neither (16-bit data as
    floats?): :class:`ImageError` naming the value. Values below 0 are clipped to 0."""
    global _float_warned
    bad = img.size - int(np.count_nonzero(np.isfinite(img)))
    if bad > FLOAT_MAX_NONFINITE * img.size:
        # (a frame full of NaN was read as black and answered "not found: no object-like window")
        raise ImageError(f"a float image whose values are {100 * bad / img.size:.0f} % NaN or infinite (at most "
                         f"{100 * FLOAT_MAX_NONFINITE:.0f} % are taken, read as 0, +inf as 1); if they are meant as "
                         f"black, replace them by 0 (np.nan_to_num)")
    finite = np.nan_to_num(img, nan=0.0, posinf=1.0, neginf=0.0)
    top = float(finite.max())
    if top > 255 * (1 + FLOAT_SLACK):
        raise ImageError(f"a float image's values reach {top:.6g}: neither 0..1 nor 0..255 (at most "
                         f"{255 * (1 + FLOAT_SLACK):g}); scale it to one of them (N-bit data: image / (2**N - 1) for 0..1)")
    if FLOAT_255_MIN <= top:
        return np.clip(finite, 0, 255).astype(np.uint8)
    if top > 1 + FLOAT_SLACK and not _float_warned:
        _float_warned = True
        warnings.warn(f"a float image whose values reach {top:.3g} is read as 0..1, clipped at 1 (as 0..255 it "
                      f"would be all but black); scale it to 0..1 (image / image.max()) or to 0..255 (at least "
                      f"{FLOAT_255_MIN:g}) to say which. Warned once.", FloatRangeWarning, stacklevel=_caller_level())
    return np.clip(finite * 255.0, 0, 255).astype(np.uint8)


def to_bgr8(image: np.ndarray, *, bits: int | None = None) -> np.ndarray:
    """8-bit, 3-channel BGR from grey, BGRA, 16-bit or float images: ``uint16`` as full-range
    16-bit (its top 8 bits), floats as 0..1 (up to 1.1, clipped), as 0..255 when the largest
    value is 2 or more (up to 280.5; beyond, refused), in between as 0..1 clipped, warned of
    once (:class:`FloatRangeWarning`). Colour is taken as OpenCV's BGR order: an RGB image cannot
    be told apart and passes as it is.

    ``bits`` (8–16): the significant bits of ``uint16`` pixels (10- or 12-bit camera data stored
    as 16-bit: ``bits=12`` maps 0..4095 to 0..255); ignored for other pixel types. Without it a
    ``uint16`` image whose values all lie below 4096 is warned of once (:class:`BitDepthWarning`).

    >>> twelve = np.full((64, 64), 4095, np.uint16)
    >>> int(to_bgr8(twelve, bits=12).max()), int(to_bgr8(twelve << 4).max())
    (255, 255)
    """
    _check_bits(bits)
    if image is None or isinstance(image, (str, bytes, os.PathLike)):
        raise ImageError(f"expected an image array (numpy), got {type(image).__name__}"
                         + ("" if image is None else ": read the file first (cv2.imread)"))
    img = np.asarray(image)  # (any array-like: a PIL image too)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
        raise ImageError(f"unsupported image shape {img.shape}: expected grey (H, W) or (H, W, 1), BGR or BGRA "
                         f"(H, W, 3|4)" + (" (channels first? image.transpose(1, 2, 0))"
                                           if img.ndim == 3 and img.shape[0] in (1, 3, 4) else ""))
    if img.size == 0:  # (OpenCV's "!_src.empty()" assertion, or numpy's "zero-size array", before)
        raise ImageError(too_small(img.shape[1], img.shape[0]))
    if img.dtype == np.uint16:
        img = _uint16_to_8(img, bits)
    elif img.dtype in (np.float32, np.float64):
        img = _float_to_8(img)
    elif img.dtype != np.uint8:
        raise ImageError(f"unsupported pixel type {img.dtype}: expected uint8, uint16, or float32/float64 in 0..1 "
                         f"(convert with image.astype(np.uint8) when the values are 0..255)")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(img)


def prepare_image(image: np.ndarray, camera: PinholeCamera, max_pixels: int = DEFAULT_MAX_PIXELS, *,
                  bits: int | None = None) -> PreparedImage:
    """Check ``image`` against ``camera`` and bring it to 8-bit BGR within ``max_pixels``
    (``bits``: the significant bits of ``uint16`` pixels, as :func:`to_bgr8` takes them).

    The camera must describe this image: if it states a size, the image must have it.
    """
    img = to_bgr8(image, bits=bits)
    h, w = img.shape[:2]
    if min(h, w) < MIN_SIDE:
        raise ImageError(too_small(w, h))
    if w * h > MAX_DECODE_PIXELS:
        raise ImageError(f"the image is too large ({w}×{h} px; at most {MAX_DECODE_PIXELS} pixels)")
    if camera.width is not None and camera.height is not None and (camera.width, camera.height) != (w, h):
        raise size_mismatch(camera, w, h)
    if camera.width is None or camera.height is None:  # (a camera sized by its images: its lens checked at
        camera = replace(camera, width=w, height=h)  # their size, as a sized camera's is when it is read)
        try:
            check_lens(camera)
        except SpecError as exc:
            raise ImageError(str(exc)) from None
    return PreparedImage(*within_pixels(img, replace(camera, width=w, height=h), max_pixels, MIN_SIDE))

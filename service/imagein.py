"""Untrusted image bytes → an array, refusing what must not reach the decoder.

The pixel count is read from the file's header *before* decoding, so a 20-byte PNG that claims
50 000 × 50 000 pixels (a decompression bomb) costs nothing. OpenCV decodes a truncated JPEG
silently (grey bottom rows), so a JPEG must end with its EOI marker. Only JPEG, PNG and WebP are
accepted: the formats the contract names, with small and well-tested decoders.
"""

from __future__ import annotations

import struct

import numpy as np

from quatrack.recognition.images import ImageError, decode_image

from .errors import ApiError

FORMATS = {"jpeg": "image/jpeg", "png": "image/png", "webp": "image/webp"}


def sniff(data: bytes) -> str | None:
    """The format from the magic bytes (never from a client's content type)."""
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    return None


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


def decode_upload(data: bytes, max_pixels: int) -> np.ndarray:
    """Decode a JPEG/PNG/WebP upload or raise :class:`ApiError` (4xx) saying what is wrong."""
    if not data:
        raise ApiError(400, "bad_image", "the image is empty (0 bytes)")
    fmt = sniff(data)
    if fmt is None:
        raise ApiError(415, "unsupported_image", "not a JPEG, PNG or WebP image")
    size = header_size(data, fmt)
    if size is None:
        raise ApiError(400, "bad_image", f"the {fmt.upper()} header is unreadable (truncated or corrupt)")
    w, h = size
    if w * h > max_pixels:
        raise ApiError(413, "image_too_large", f"the image has {w}×{h} pixels; at most {max_pixels} are accepted")
    if fmt == "jpeg" and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise ApiError(400, "bad_image", "the JPEG is truncated (no end-of-image marker)")
    try:
        img = decode_image(data)
    except ImageError as exc:
        raise ApiError(400, "bad_image", str(exc)) from None
    if img.shape[1] * img.shape[0] > max_pixels:  # a header that lied
        raise ApiError(413, "image_too_large", f"the image has more than {max_pixels} pixels")
    return img

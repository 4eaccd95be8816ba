"""Untrusted image bytes → an array, refusing what must not reach the decoder.

The pixel count is read from the file's header *before* decoding, so a 20-byte PNG that claims
50 000 × 50 000 pixels (a decompression bomb) costs nothing. OpenCV decodes a truncated JPEG
silently (grey bottom rows), so a JPEG must have its EOI marker after its scan (the one test of
training, ``locate`` and the service: ``recognition.images.truncated``). Only JPEG, PNG and WebP
are accepted: the formats the contract names, with small and well-tested decoders.
"""

from __future__ import annotations

import numpy as np

from quatrack.recognition.images import ImageError, decode_image, header_size, sniff, truncated
from quatrack.viewsets.camera import resized_for

from .errors import ApiError

FORMATS = {"jpeg": "image/jpeg", "png": "image/png", "webp": "image/webp"}

__all__ = ["FORMATS", "decode_upload", "header_size", "size_mismatch", "sniff"]


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
    if fmt == "jpeg" and truncated(data, fmt):  # (a PNG's or a WebP's: decode_image says so)
        raise ApiError(400, "bad_image", "the JPEG is truncated (no end-of-image marker)")
    try:
        img = decode_image(data)
    except ImageError as exc:
        raise ApiError(400, "bad_image", str(exc)) from None
    if img.shape[1] * img.shape[0] > max_pixels:  # a header that lied
        raise ApiError(413, "image_too_large", f"the image has more than {max_pixels} pixels")
    return img


def size_mismatch(cam, w: int, h: int) -> str | None:
    """The message refusing a ``w``×``h`` image for a camera sized otherwise, in a client's terms
    (REST and WebSocket alike), else None: the library's
    (:func:`~quatrack.recognition.images.size_mismatch`, which also says when the camera's own
    numbers show its stated size is the wrong one), with its hint for the camera's own images
    resized — ``pass camera.scaled(0.5, 640, 480)``, Python a REST client has no use for —
    replaced by the intrinsics to send for this size
    (:func:`~quatrack.viewsets.camera.resized_for`)."""
    from quatrack.recognition.images import size_mismatch as refusal

    if cam.width is None or cam.height is None or (cam.width, cam.height) == (w, h):
        return None
    err = refusal(cam, w, h)
    if not err.hint:
        return str(err)
    scaled, _ = resized_for(cam, w, h)
    return (f"{err.base} (its images resized by {w / cam.width:.3g}? send the camera for this size: "
            f"fx={scaled.fx:.6g}, fy={scaled.fy:.6g}, cx={scaled.cx:.6g}, cy={scaled.cy:.6g}, width={w}, height={h})")

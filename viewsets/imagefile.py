"""Encoded image files as bytes, before any decoder sees them: their format from the magic
bytes, and whether they are whole.

Here, below both, so that training (``viewsets.train``, a photo), recognition
(``recognition.images.decode_image``, which re-exports these) and the service (an upload) ask one
question one way. OpenCV's decoders are lenient where a user needs to be told: a JPEG cut short
decodes, its missing part grey.
"""

from __future__ import annotations

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
FORMAT_NAMES = {"jpeg": "JPEG", "png": "PNG", "webp": "WebP"}


def sniff(data: bytes) -> str | None:
    """The format from the magic bytes (never from a client's content type)."""
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[:8] == _PNG_SIGNATURE:
        return "png"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    return None


def truncated(data: bytes, fmt: str | None = None) -> bool:
    """Whether an encoded JPEG, PNG or WebP lacks its end (a copy, a download or an upload cut
    short); False for whole files and for other formats. ``fmt``: :func:`sniff`'s answer, sniffed
    when not given. The one test of training's photos, ``decode_image`` and the service's
    uploads (each said it differently: a JPEG had to *end* with its EOI marker for the service,
    so trailing bytes after it were "truncated", and ``decode_image`` did not look at JPEGs).
    OpenCV decodes a truncated JPEG anyway, its missing part grey, with only libjpeg's
    "Premature end of JPEG file" on stderr.

    - JPEG: the segments before the first scan (SOS) are walked by their lengths, so the EOI of
      an EXIF thumbnail (inside APP1) does not count; an EOI must follow the first scan.
    - PNG: the chunks are walked by their lengths; the file is whole when its IEND chunk is
      reached inside the data (a chunk running past the end, or no IEND: truncated).
    - WebP: the RIFF header's size (``8 + size`` bytes in all) must be there.

    >>> import cv2, numpy as np
    >>> ok, jpg = cv2.imencode(".jpg", np.zeros((16, 16, 3), np.uint8))
    >>> truncated(jpg.tobytes()), truncated(jpg.tobytes()[:-2]), truncated(jpg.tobytes() + b"trailer")
    (False, True, False)
    """
    fmt = sniff(data) if fmt is None else fmt
    if fmt == "jpeg":
        i, n = 2, len(data)
        while i + 4 <= n and data[i] == 0xFF:  # the segments before the first scan (SOS)
            marker = data[i + 1]
            if marker == 0xDA:
                return data.find(b"\xff\xd9", i) < 0
            if marker == 0xFF:  # (fill byte)
                i += 1
                continue
            if marker in (0x01, *range(0xD0, 0xD8)):  # (standalone markers: no length)
                i += 2
                continue
            i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
        return True
    if fmt == "png":
        pos, n = 8, len(data)
        while pos + 12 <= n:
            end = pos + 12 + int.from_bytes(data[pos:pos + 4], "big")
            if end > n:
                return True
            if data[pos + 4:pos + 8] == b"IEND":
                return False
            pos = end
        return True
    if fmt == "webp":
        return len(data) < 12 or len(data) < 8 + int.from_bytes(data[4:8], "little")
    return False

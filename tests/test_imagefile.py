"""One test of whether an encoded image is whole (``viewsets.imagefile.truncated``, re-exported by
``recognition.images``): training's photos, ``decode_image`` (``locate``, ``track --images``) and
the service's uploads asked it three ways — a PNG's IEND anywhere in its bytes, a JPEG ending with
FFD9 (the service) or with an EOI after its scan (training), no JPEG test at all in
``decode_image``, and no WebP test anywhere."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from quatrack.recognition.images import ImageError, decode_image, truncated
from quatrack.viewsets import imagefile


def _photo(seed: int = 0, size=(48, 64)) -> np.ndarray:
    img = np.random.default_rng(seed).integers(0, 255, (*size, 3), np.uint8)
    return cv2.GaussianBlur(img, (5, 5), 0)


def _encoded(ext: str, img=None) -> bytes:
    ok, buf = cv2.imencode(ext, _photo() if img is None else img)
    assert ok
    return buf.tobytes()


def _sos(jpeg: bytes) -> int:
    """Offset of the first scan's SOS marker, by the segments' lengths."""
    i = 2
    while jpeg[i + 1] != 0xDA:
        i += 2 + struct.unpack(">H", jpeg[i + 2:i + 4])[0]
    return i


def _with_exif_thumbnail(jpeg: bytes, before_scan: bool = False) -> tuple[bytes, int]:
    """``jpeg`` with an APP1 (EXIF) segment holding a whole thumbnail JPEG — its own SOI…EOI —
    right after SOI (or just before the scan, after the frame header), and the offset where that
    segment ends (the thumbnail's EOI just before)."""
    thumb = _encoded(".jpg", _photo(1, (16, 16)))
    body = b"Exif\x00\x00" + b"MM\x00\x2a\x00\x00\x00\x08" + thumb  # (a TIFF header, then the thumbnail)
    app1 = b"\xff\xe1" + struct.pack(">H", 2 + len(body)) + body
    at = _sos(jpeg) if before_scan else 2
    return jpeg[:at] + app1 + jpeg[at:], at + len(app1)


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def test_whole_files_are_whole_and_each_format_cut_short_is_truncated():
    for ext in (".jpg", ".png", ".webp"):
        data = _encoded(ext)
        assert not truncated(data), ext
        for cut in (len(data) // 3, len(data) // 2, len(data) - 1):
            assert truncated(data[:cut]), (ext, cut)
    assert not truncated(b"GIF89a...") and not truncated(b"")  # (not ours to judge: the decoder says)


def test_a_jpeg_is_whole_by_the_eoi_after_its_scan_not_by_its_last_bytes():
    data = _encoded(".jpg")
    assert truncated(data[:-2]) and truncated(data[:-1])
    assert not truncated(data + b"\x00\x00") and not truncated(data + b"camera maker's trailer")
    exif, end_of_app1 = _with_exif_thumbnail(data)
    assert cv2.imdecode(np.frombuffer(exif, np.uint8), cv2.IMREAD_COLOR).shape == (48, 64, 3)  # (a valid JPEG)
    assert not truncated(exif)
    # cut right after the thumbnail: the file ends with FFD9 (the thumbnail's), but has no scan of its own
    assert exif[:end_of_app1].endswith(b"\xff\xd9") and truncated(exif[:end_of_app1])
    assert truncated(exif[:end_of_app1 + 40]) and truncated(exif[:-2])
    late, end_of_app1 = _with_exif_thumbnail(data, before_scan=True)
    assert not truncated(late) and truncated(late[:end_of_app1])


def test_a_png_is_whole_by_its_iend_chunk_not_by_the_letters_iend():
    data = _encoded(".png")
    iend = data.rindex(b"IEND") - 4
    assert truncated(data[:iend]) and not truncated(data + b"trailing")
    # "IEND" inside a chunk's data (here a tEXt chunk) is not the end: cut before the real one
    tagged = data[:33] + _chunk(b"tEXt", b"Comment\x00IEND") + data[33:]
    assert not truncated(tagged)
    assert truncated(tagged[:tagged.rindex(b"IEND") - 4])


def test_a_webp_is_whole_by_its_riff_size():
    data = _encoded(".webp")
    assert struct.unpack("<I", data[4:8])[0] + 8 == len(data)
    assert truncated(data[:-1]) and truncated(data[:20]) and not truncated(data + b"\x00\x00")


@pytest.mark.parametrize("ext, name", [(".jpg", "JPEG"), (".png", "PNG"), (".webp", "WebP")])
def test_decode_image_refuses_every_truncated_format(ext, name, capfd):
    # a JPEG cut short decoded (its bottom grey), with libjpeg's "Premature end of JPEG file" on stderr
    data = _encoded(ext)
    assert decode_image(data).shape == (48, 64, 3)
    with pytest.raises(ImageError, match=f"a {name} without its end: truncated"):
        decode_image(data[: len(data) * 2 // 3])
    err = capfd.readouterr().err
    assert "Premature" not in err and "libpng" not in err


def test_the_service_keeps_its_message_and_takes_a_jpeg_with_a_trailer():
    from quatrack.service.errors import ApiError
    from quatrack.service.imagein import decode_upload

    data = _encoded(".jpg")
    assert decode_upload(data + b"camera maker's trailer", 10**6).shape == (48, 64, 3)  # (was refused: "truncated")
    exif, end_of_app1 = _with_exif_thumbnail(data, before_scan=True)  # (the frame header before it, readable)
    assert decode_upload(exif, 10**6).shape == (48, 64, 3)
    for cut in (exif[:end_of_app1], data[:-2]):  # (the first ends with the thumbnail's FFD9: it got through)
        with pytest.raises(ApiError) as e:
            decode_upload(cut, 10**6)
        assert e.value.status_code == 400 and e.value.message == "the JPEG is truncated (no end-of-image marker)", e.value.message


def test_training_recognition_and_the_service_share_one_test():
    from quatrack.recognition import images
    from quatrack.service import imagein
    from quatrack.viewsets import train

    assert images.truncated is imagefile.truncated is imagein.truncated is train.truncated
    assert images.sniff is imagefile.sniff is imagein.sniff

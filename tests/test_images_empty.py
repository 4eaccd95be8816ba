"""An empty image array (0 rows or columns, any pixel type) is refused as a too-small image, an
ImageError, not OpenCV's assertion or numpy's reduction error (recognition/images.py)."""

import numpy as np
import pytest

from quatrack.recognition.images import ImageError, prepare_image, to_bgr8
from quatrack.tracking.camera import PinholeCamera


@pytest.mark.parametrize("shape, dtype, size", [
    ((0, 0), np.uint8, "0×0"), ((0, 0), np.float32, "0×0"), ((10, 0), np.uint16, "0×10"),
    ((0, 5, 4), np.uint8, "5×0"), ((0, 640, 3), np.uint8, "640×0"), ((0, 0, 1), np.float64, "0×0"),
])
def test_an_empty_image_is_refused_as_too_small(shape, dtype, size):
    # (grey, BGRA, uint16: cv2.error "!_src.empty() in function 'cvtColor'"; float: ValueError
    # "zero-size array to reduction operation maximum which has no identity")
    message = rf"the image is too small \({size} px; at least 32 px a side\)"
    with pytest.raises(ImageError, match=message):
        to_bgr8(np.zeros(shape, dtype))
    with pytest.raises(ImageError, match=message):
        prepare_image(np.zeros(shape, dtype), PinholeCamera(500.0, 500.0, 320.0, 240.0))

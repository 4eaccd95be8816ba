"""A size mismatch is a typed error whose parts a caller can use (the CLI's own remedy)."""
import pickle

import pytest

from quatrack.recognition.images import ImageError, ImageSizeError, prepare_image, size_mismatch
from quatrack.tracking.camera import PinholeCamera

CAM = PinholeCamera(500.0, 500.0, 320.0, 240.0, width=640, height=480)


def test_the_message_is_its_base_and_hint_and_survives_pickling():
    err = size_mismatch(CAM, 1280, 960, "frame")
    assert isinstance(err, ImageError)
    assert str(err) == err.base + err.hint
    assert err.camera_size == (640, 480) and err.image_size == (1280, 960)
    assert "pass camera.scaled(2, 1280, 960)" in err.hint
    back = pickle.loads(pickle.dumps(err))
    assert (str(back), back.base, back.hint, back.camera_size, back.image_size) == \
        (str(err), err.base, err.hint, err.camera_size, err.image_size)


def test_an_image_of_another_shape_gets_no_resize_hint():
    err = size_mismatch(CAM, 640, 640)
    assert err.hint == "" and str(err) == err.base


def test_prepare_image_raises_the_typed_error():
    import numpy as np

    with pytest.raises(ImageSizeError) as info:
        prepare_image(np.zeros((240, 320, 3), np.uint8), CAM)
    assert info.value.image_size == (320, 240)


def test_a_camera_whose_numbers_doubt_its_stated_size_is_told_so_not_to_scale():
    wrong = PinholeCamera(500.0, 500.0, 319.5, 239.5, width=1280, height=960)  # (640×480 numbers)
    err = size_mismatch(wrong, 640, 480)
    assert err.hint == "" and "are its width and height wrong?" in str(err) and "scaled(" not in str(err)

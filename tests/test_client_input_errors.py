"""Errors the Python client finds in its own arguments are :class:`QuatrackError` (its subclass
``InputError``) with the server's code for the same problem, raised before any request: a
missing camera file was the object-model layer's ``SpecError``, a bad object name its
``StoreError`` (``c.pose(frame, "nofile.json")``, ``object="../etc"``), which code catching
``QuatrackError``, as the README's example does, missed. Each is still the exception it was.
No server listens at the client's address: a request made would be ``unreachable``."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from quatrack.client import AsyncClient, Client, InputError, QuatrackError, stream
from quatrack.service.server import free_port
from quatrack.testing.scenes import EXAMPLE
from quatrack.viewsets.errors import SpecError, StoreError

CAMERA = str(EXAMPLE / "camera.json")
IMAGE = np.zeros((48, 64, 3), np.uint8)


@pytest.fixture
def url():
    return f"http://127.0.0.1:{free_port()}"


def _check(exc, code, also, text):
    assert isinstance(exc, InputError) and isinstance(exc, QuatrackError) and isinstance(exc, ValueError)
    assert isinstance(exc, also), type(exc).__mro__  # (catchable as before)
    assert (exc.code, exc.status) == (code, None) and text in exc.message and str(exc) == f"{code}: {exc.message}"


def test_a_camera_file_that_cannot_be_read_is_bad_camera_before_any_request(url, tmp_path):
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with Client(url, object="cookie-box") as c:
        with pytest.raises(QuatrackError) as e:
            c.pose(IMAGE, "nofile.json")
        _check(e.value, "bad_camera", SpecError, "cannot read camera file nofile.json: no such file")
        with pytest.raises(QuatrackError) as e:  # (was "unreachable": it connected before reading the camera)
            next(c.track([IMAGE], "nofile.json"))
        _check(e.value, "bad_camera", SpecError, "cannot read camera file nofile.json: no such file")
        with pytest.raises(SpecError) as e:
            c.pose_all(IMAGE, broken)
        _check(e.value, "bad_camera", SpecError, f"{broken}: not valid JSON")
        with pytest.raises(TypeError) as e:
            c.pose(IMAGE, 42)
        _check(e.value, "bad_camera", TypeError, "camera: a dict, a PinholeCamera or the path of a camera file, not int")


def test_an_object_name_the_store_cannot_hold_is_invalid_object_name(url):
    with Client(url) as c:
        for bad in ("../etc", "a?b=1"):
            with pytest.raises(QuatrackError) as e:
                c.pose(IMAGE, CAMERA, object=bad)
            _check(e.value, "invalid_object_name", StoreError, f"invalid object name {bad!r}")
        with pytest.raises(QuatrackError) as e:
            next(c.track([IMAGE], CAMERA, object="../etc"))
        _check(e.value, "invalid_object_name", StoreError, "invalid object name '../etc'")
        with pytest.raises(QuatrackError) as e:  # (no name, here or to Client)
            c.mesh_edges()
        _check(e.value, "invalid_object_name", ValueError, "which object? give object=NAME")


def test_images_times_urls_and_rates_the_client_cannot_take(url, tmp_path):
    with Client(url, object="cookie-box") as c:
        with pytest.raises(OSError) as e:
            c.pose(tmp_path / "nofile.jpg", CAMERA)
        _check(e.value, "bad_image", OSError, f"image {tmp_path / 'nofile.jpg'}: cannot read it (No such file")
        with pytest.raises(QuatrackError) as e:
            c.pose([1, 2, 3], CAMERA)
        _check(e.value, "bad_image", TypeError, "image: bytes, a file path or a numpy array, not list")
    with pytest.raises(QuatrackError) as e:
        Client._frame_parts(("soon", IMAGE))
    _check(e.value, "bad_message", ValueError, "a frame's time_s (the first of its pair) must be a number of seconds")
    with pytest.raises(QuatrackError) as e:
        Client("127.0.0.1:8000")
    _check(e.value, "bad_url", ValueError, "give the server's address")
    with pytest.raises(QuatrackError) as e:
        asyncio.run(stream(url.replace("http", "ws") + "/v1/objects/cookie-box/track", CAMERA, [], fps=0))
    _check(e.value, "invalid_input", ValueError, "fps: frames per second above 0")


def test_the_async_client_raises_the_same(url):
    async def run():
        async with AsyncClient(url, object="cookie-box") as c:
            with pytest.raises(QuatrackError) as e:
                await c.pose(IMAGE, "nofile.json")
            _check(e.value, "bad_camera", SpecError, "cannot read camera file nofile.json: no such file")
            with pytest.raises(QuatrackError) as e:
                await anext(c.track([IMAGE], "nofile.json"))
            _check(e.value, "bad_camera", SpecError, "cannot read camera file nofile.json: no such file")
            with pytest.raises(QuatrackError) as e:
                await c.pose(IMAGE, CAMERA, object="../etc")
            _check(e.value, "invalid_object_name", StoreError, "invalid object name '../etc'")

    asyncio.run(run())

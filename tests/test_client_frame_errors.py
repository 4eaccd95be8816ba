"""A frame the server cannot track (damaged, not an image) among good ones: ``Client.track``,
``AsyncClient.track`` and ``stream()`` answer it in its place and go on; session errors still
raise. Against a real server on a loopback port."""

from __future__ import annotations

import asyncio

import cv2
import pytest

from quatrack.client import AsyncClient, Client, FrameError, QuatrackError, stream
from quatrack.recognition import trackio
from quatrack.service.schemas import TrackMessage
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import EXAMPLE, example_store

CAMERA = EXAMPLE / "camera.json"
DAMAGED, NOT_AN_IMAGE = 2, 3


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store())) as srv:
        yield srv


@pytest.fixture(scope="module")
def frames():
    """6 timed JPEG frames of box.mp4: one damaged (as an MJPEG camera sometimes sends), one no image."""
    with trackio.open_frames(video=str(EXAMPLE / "box.mp4"), max_frames=6) as src:
        out = [(t, cv2.imencode(".jpg", image)[1].tobytes()) for _, t, image in src]
    t, jpg = out[DAMAGED]
    out[DAMAGED] = (t, jpg[:300] + b"\0" * 300)
    out[NOT_AN_IMAGE] = (out[NOT_AN_IMAGE][0], b"garbage")
    return out


def _check(msgs: list, frames: list) -> None:
    assert len(msgs) == len(frames)  # (it raised at the damaged frame: 2 answers of 6)
    assert all(isinstance(m, TrackMessage) for m in msgs)
    bad = {i: m for i, m in enumerate(msgs) if isinstance(m, FrameError)}
    assert sorted(bad) == [DAMAGED, NOT_AN_IMAGE]
    assert bad[DAMAGED].code == "bad_image" and bad[DAMAGED].frame == DAMAGED
    assert bad[NOT_AN_IMAGE].code == "unsupported_image" and bad[NOT_AN_IMAGE].frame is None
    # the input's place, also for the frame refused on arrival (the server gives it no number)
    assert [m.index for m in bad.values()] == [DAMAGED, NOT_AN_IMAGE]
    for i, m in bad.items():
        assert m.status == "lost" and m.pose is None and m.time_s == pytest.approx(frames[i][0])
        assert m.reason.startswith(m.code + ": ") and m.message
    good = [m for i, m in enumerate(msgs) if i not in bad]
    assert [m.status for m in good][-1] == "tracking" and good[-1].pose is not None  # (the session went on)


def test_client_track_answers_a_bad_frame_in_its_place_and_goes_on(server, frames):
    with Client(server.url, object="cookie-box") as c:
        _check(list(c.track(frames, CAMERA)), frames)


def test_async_client_track_answers_a_bad_frame_in_its_place_and_goes_on(server, frames):
    async def run():
        async with AsyncClient(server.url, object="cookie-box") as c:
            return [m async for m in c.track(frames, CAMERA)]

    _check(asyncio.run(run()), frames)


def test_stream_files_a_bad_frame_as_an_error_and_goes_on(server, frames):
    url = f"{server.ws_url}/v1/objects/cookie-box/track"
    res = asyncio.run(stream(url, str(CAMERA), [(i, t, data) for i, (t, data) in enumerate(frames)]))
    assert sorted(res.poses) == [i for i in range(len(frames)) if i not in (DAMAGED, NOT_AN_IMAGE)]
    assert sorted(res.error_index) == [DAMAGED, NOT_AN_IMAGE]


def test_a_session_error_still_raises(server, frames):
    with Client(server.url, object="no-such-box") as c:
        with pytest.raises(QuatrackError) as e:
            list(c.track(frames, CAMERA))
    assert e.value.code == "unknown_object"

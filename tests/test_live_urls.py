"""``--video URL`` of a recorded video (``http://host/box.mp4``, ``file:///.../box.mp4``) against a
live stream's URL: which is timed like a file, which by the clock, and how each ends.

The captures are fake (:class:`FakeURLCapture`), the live clock stands still: nothing depends on
the machine's speed.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from quatrack.recognition import trackio


class FakeURLCapture:
    """A capture of ``n`` frames whose container states ``count`` frames at ``fps`` and gives each
    frame the container time ``stamps[k]`` (ms); reads fail after the last frame."""

    n, count, fps = 12, 12, 10.0
    stamps: list[float] | None = None

    def __init__(self, target, *timeout) -> None:
        self.k = 0

    def isOpened(self) -> bool:
        return True

    def read(self):
        if self.k >= self.n:
            return False, None
        self.k += 1
        return True, np.full((24, 32, 3), self.k, np.uint8)

    def get(self, prop) -> float:
        if prop == cv2.CAP_PROP_FRAME_COUNT:
            return float(self.count)
        if prop == cv2.CAP_PROP_FPS:
            return self.fps
        if prop == cv2.CAP_PROP_POS_MSEC:
            stamps = self.stamps if self.stamps is not None else [100.0 * k for k in range(self.n)]
            return stamps[self.k - 1] if self.k else 0.0
        return 0.0

    def release(self) -> None:
        pass


@pytest.fixture
def fake(monkeypatch):
    monkeypatch.setattr(trackio, "open_capture", FakeURLCapture)
    monkeypatch.setattr(trackio.LiveCapture, "clock", staticmethod(lambda: 5.0))  # (the clock stands still)
    return FakeURLCapture


@pytest.mark.parametrize("url", ["http://127.0.0.1:8000/box.mp4", "file:///data/box.mp4"])
def test_a_url_of_a_recorded_video_is_timed_by_its_timestamps_and_ends_as_a_file(fake, url):
    # (it was live: every frame timed by the clock, here 1 µs apart, and the file's end "the stream ended")
    src = trackio.open_frames(video=url)
    times = [t for _, t, _ in src]
    assert not src.live and src.ended is None
    assert times == pytest.approx([0.1 * k for k in range(fake.n)])


def test_a_url_of_a_recorded_video_in_decoding_order_is_timed_by_index_over_rate(fake, monkeypatch):
    # box.mp4's B-frames carry their decoding order's times: a file's frames are then index / rate
    monkeypatch.setattr(fake, "stamps", [0.0, 101.0, 67.0, 134.0, 34.0, 234.0, 201.0, 267.0, 167.0, 367.0, 301, 334])
    src = trackio.open_frames(video="http://127.0.0.1:8000/box.mp4")
    times = [t for _, t, _ in src]
    assert not src.live and src.ended is None
    assert times == pytest.approx([k / fake.fps for k in range(fake.n)])


@pytest.mark.parametrize("count, stamps", [(0, None), (-1, None), (12, [0.0] * 12)])
def test_a_url_without_a_frame_count_or_container_times_stays_live(fake, monkeypatch, count, stamps):
    monkeypatch.setattr(fake, "count", count)
    monkeypatch.setattr(fake, "stamps", stamps)
    src = trackio.open_frames(video="rtsp://10.0.0.2/stream")
    times = [t for _, t, _ in src]
    assert src.live and len(times) == fake.n
    assert times[-1] < 1e-3  # (the clock's: it stood still)
    if count <= 0:
        assert src.ended is not None and "ended" in src.ended

"""The progress line of a live run: the recent rate, and ``waiting for frames N s`` while no frame
comes (it froze on the last rate for up to the stall timeout). Fake clocks and cameras; the one
real wait is LiveCapture's own 0.1 s slice, which the test does not time."""

from __future__ import annotations

import io
import threading

import numpy as np

from quatrack.recognition import trackio


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _last_line(out: Tty) -> str:
    return out.getvalue().split("\r")[-1]


def test_the_line_says_it_waits_while_no_frame_comes_and_shows_the_recent_rate():
    clock, out = Clock(), Tty()
    p = trackio.Progress("tracking", stream=out, clock=clock)
    for _ in range(10):  # 10 frames/s for 1 s
        clock.now += 0.1
        p.update("tracking")
    assert "10 frames, 10.0 fps" in _last_line(out)
    clock.now += 0.1  # the source starts waiting (its first tick) ...
    p.tick()
    assert "10 frames, 10.0 fps" in _last_line(out)
    clock.now += 5.0  # ... and the stream stalls
    p.tick()
    assert "10 frames, waiting for frames 5 s" in _last_line(out)
    clock.now += 20.0
    for _ in range(5):  # then 2 frames/s: the mean since the start said 0.6
        clock.now += 0.5
        p.update("tracking")
    assert "15 frames, 2.0 fps" in _last_line(out)


class BlockedCamera:
    """A camera whose second read blocks until :attr:`go` is set."""

    go = threading.Event()

    def __init__(self, target, *timeout) -> None:
        self.k = 0

    def isOpened(self) -> bool:
        return True

    def read(self):
        self.k += 1
        if self.k > 1:
            assert self.go.wait(60)
        return True, np.zeros((8, 8, 3), np.uint8)

    def get(self, prop) -> float:
        return 0.0

    def release(self) -> None:
        pass


def test_a_live_source_calls_on_wait_while_a_read_blocks(monkeypatch):
    monkeypatch.setattr(BlockedCamera, "go", threading.Event())
    monkeypatch.setattr(trackio, "open_capture", BlockedCamera)
    src = trackio.open_frames(video="0", max_frames=2)
    waited = []

    def on_wait() -> None:  # (the read goes on once it was seen waiting)
        waited.append(1)
        BlockedCamera.go.set()

    src.on_wait(on_wait)
    assert len(list(src)) == 2 and waited

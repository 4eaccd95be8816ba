"""A live source's time: ``time_s`` is when the capture thread grabbed the frame, and the overlay
of a live run plays at the pace the frames came at (``quatrack track --video 0 --overlay``).

The camera is fake (:class:`PacedCamera`): each read waits for its next frame on a fake clock
shared with the test, which also stands for the consumer's own time (building the tracker,
tracking a frame). Nothing depends on the machine's speed.
"""

from __future__ import annotations

import cv2
import numpy as np

from quatrack.recognition import trackio


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class PacedCamera:
    """A camera giving a frame every ``period`` s of ``clock`` (a read waits for the next one; a
    frame that came while nobody read is stale: the latest is given), claiming ``claimed`` fps."""

    clock: FakeClock | None = None
    period = 0.1
    claimed = 30.0

    def __init__(self, target, *timeout) -> None:
        self.next = 0.0

    def isOpened(self) -> bool:
        return True

    def read(self):
        clock = PacedCamera.clock
        if clock.now < self.next:
            clock.now = self.next  # (waits for the frame)
        k = int(round(clock.now / self.period, 9))
        self.next = (k + 1) * self.period
        return True, np.full((48, 64, 3), k % 256, np.uint8)

    def get(self, prop) -> float:
        return self.claimed if prop == cv2.CAP_PROP_FPS else 0.0

    def release(self) -> None:
        pass


def _paced(monkeypatch) -> FakeClock:
    clock = FakeClock()
    monkeypatch.setattr(PacedCamera, "clock", clock)
    monkeypatch.setattr(trackio, "open_capture", PacedCamera)
    monkeypatch.setattr(trackio.LiveCapture, "clock", staticmethod(clock), raising=False)
    return clock


def test_a_live_frame_is_timed_when_grabbed_not_when_taken(monkeypatch):
    # the first frame is read as the source opens; the tracker is built after (here: 2 s), and
    # each frame takes the consumer 0.5 s. The frames were timed when taken: frame 0 at the end
    # of those 2 s, so frame 1, grabbed 2.5 s after it, came 0.5 s after it
    clock = _paced(monkeypatch)
    src = trackio.open_frames(video="0", max_frames=4)
    src._clock = clock  # (the clock the frames were timed by when taken)
    clock.now += 2.0  # building the tracker
    times = []
    for _, t, _ in src:
        times.append(t)
        clock.now += 0.5  # tracking the frame
    assert np.allclose(times, [0.0, 2.5, 3.0, 3.5]), times

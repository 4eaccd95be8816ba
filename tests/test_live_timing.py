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


def _video_frames(path) -> list[int]:
    """The grey level of each frame of a video (the frames written are uniform greys)."""
    cap = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, f = cap.read()
        if not ok:
            return out
        out.append(int(round(f.mean())))


def test_a_timed_overlay_shows_each_frame_from_its_time_to_the_next(tmp_path):
    path = tmp_path / "o.mp4"
    video = trackio.VideoOut(str(path), 10.0, timed=True)
    # 4 frames over 1 s at a claimed 10 frames/s: shown 3, 2, 5 and 1 video frames; two within
    # one video frame (0.52, 0.54): the later one is shown
    for t, grey in ((0.0, 40), (0.3, 80), (0.52, 120), (0.54, 160), (1.0, 200)):
        video.write(np.full((48, 64, 3), grey, np.uint8), t)
    video.close()
    got = _video_frames(path)
    assert len(got) == video.frames == 11 and cv2.VideoCapture(str(path)).get(cv2.CAP_PROP_FPS) == 10.0
    assert [abs(g - w) <= 3 for g, w in zip(got, [40] * 3 + [80] * 2 + [160] * 5 + [200])] == [True] * 11, got


def test_an_untimed_overlay_writes_one_video_frame_per_frame(tmp_path):
    path = tmp_path / "o.mp4"
    video = trackio.VideoOut(str(path), 10.0)
    for t, grey in ((0.0, 40), (0.9, 80)):
        video.write(np.full((48, 64, 3), grey, np.uint8), t)
    video.close()
    assert len(_video_frames(path)) == 2


class PacedBox(PacedCamera):
    """:class:`PacedCamera` with box.mp4's frames (the example's camera tracks them)."""

    def __init__(self, target, *timeout) -> None:
        super().__init__(target)
        from quatrack.testing.scenes import EXAMPLE

        self.cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))

    def read(self):
        super().read()  # (the pace)
        return self.cap.read()


def test_track_overlays_a_live_source_at_the_pace_its_frames_came(monkeypatch, tmp_path):
    # a camera claiming 30 frames/s whose frames come 5 a second (its own pace, or the tracker's):
    # 6 frames over 1 s were a 0.2 s overlay
    from quatrack.cli import main
    from quatrack.testing.scenes import EXAMPLE, example_store

    _paced(monkeypatch)
    monkeypatch.setattr(PacedCamera, "period", 0.2)
    monkeypatch.setattr(trackio, "open_capture", PacedBox)
    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    assert main(["track", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"), "--video", "0",
                 "--store", str(example_store()), "--out", str(out), "--overlay", str(overlay), "--max-frames", "6",
                 "--quiet"]) == 0
    times = [float(line.split(",")[1]) for line in out.read_text().splitlines()[1:]]
    assert np.allclose(times, [0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    cap = cv2.VideoCapture(str(overlay))
    n, fps = cap.get(cv2.CAP_PROP_FRAME_COUNT), cap.get(cv2.CAP_PROP_FPS)
    assert fps == 30.0 and n == 31, (n, fps)  # (1 s, and the last frame shown for its own 1/30 s)

"""A live source's frame that fails to decode (a corrupt JPEG part of an MJPEG stream) is timed by
its own read, not by the next frame's. The camera and the clock are fake."""

from __future__ import annotations

import pytest

from quatrack.recognition import trackio

from test_live_credentials import ScriptedCamera


def test_a_corrupt_live_frame_is_timed_by_its_own_read(monkeypatch):
    monkeypatch.setattr(ScriptedCamera, "now", 0.0)
    monkeypatch.setattr(ScriptedCamera, "script", ["frame", "frame", "fail", "fail", "frame"])
    monkeypatch.setattr(trackio, "open_capture", ScriptedCamera)
    monkeypatch.setattr(trackio.LiveCapture, "clock", staticmethod(lambda: ScriptedCamera.now))
    src = trackio.open_frames(video="rtsp://10.0.0.2/live", max_frames=5)
    got = [(i, t) for i, t, _ in src]
    # reads return 0.1 s apart: the failed ones at 0.3 and 0.4 (they were both stamped 0.5, the next frame's)
    assert [i for i, _ in got] == [0, 1, 4] and [t for _, t in got] == pytest.approx([0.0, 0.1, 0.4])
    assert [(i, round(t, 6)) for i, t, _ in src.skipped] == [(2, 0.2), (3, 0.3)]

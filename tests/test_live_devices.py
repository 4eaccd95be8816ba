"""``--video /dev/video0`` (a character device) is a camera and a FIFO a stream: both live, as a
camera index and a URL are (they were refused as "no such file"). The capture is fake."""

from __future__ import annotations

import os

import pytest

from quatrack.recognition import trackio

from test_live_credentials import ScriptedCamera


@pytest.fixture
def camera(monkeypatch):
    monkeypatch.setattr(ScriptedCamera, "now", 0.0)
    monkeypatch.setattr(ScriptedCamera, "script", ["frame"] * 3)
    monkeypatch.setattr(trackio, "open_capture", ScriptedCamera)
    monkeypatch.setattr(trackio.LiveCapture, "clock", staticmethod(lambda: ScriptedCamera.now))
    return ScriptedCamera


def test_a_character_device_is_a_live_camera(camera):
    assert trackio.capture_target("/dev/null") == "/dev/null"  # (a character device on every Linux)
    src = trackio.open_frames(video="/dev/null")
    times = [t for _, t, _ in src]
    assert src.live and times == pytest.approx([0.0, 0.1, 0.2])  # (by the fake clock, as a camera)
    assert src.ended is not None and src.ended.startswith("the camera ended")


def test_a_fifo_is_a_live_stream(camera, tmp_path):
    fifo = tmp_path / "frames.mjpeg"
    os.mkfifo(fifo)
    src = trackio.open_frames(video=str(fifo))
    assert src.live and len(list(src)) == 3
    assert src.ended is not None and src.ended.startswith("the stream ended")


def test_a_missing_path_is_still_no_such_file(tmp_path):
    with pytest.raises(trackio.SourceError, match="no such file"):
        trackio.capture_target(str(tmp_path / "video7"))

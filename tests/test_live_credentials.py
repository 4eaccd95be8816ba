"""A camera URL's password (``rtsp://user:pass@host/...``) is never shown: not in an error, a
stderr line, a thread's name or a row's ``reason``. The camera is fake (:class:`ScriptedCamera`)."""

from __future__ import annotations

import json

import cv2
import pytest

from quatrack.cli import main
from quatrack.recognition import trackio
from quatrack.testing.scenes import EXAMPLE, example_store

SECRET = "s3cret-pw"
URL = f"rtsp://admin:{SECRET}@10.0.0.2:554/live"


class ScriptedCamera:
    """A live source reading box.mp4's frames as ``script`` says, one item per read: ``"frame"``
    (the next frame), ``"fail"`` (a read that fails, as a corrupt JPEG part does); after the
    script every read fails (the stream ended). Each read takes ``period`` s of :attr:`now`, the
    fake clock the test gives :class:`LiveCapture`."""

    script: list[str] = ["frame"] * 4
    period = 0.1
    now = 0.0
    opened = True

    def __init__(self, target, *timeout) -> None:
        self.cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
        self.k = 0

    def isOpened(self) -> bool:
        return self.opened

    def read(self):
        ScriptedCamera.now += self.period
        item = self.script[self.k] if self.k < len(self.script) else "fail"
        self.k += 1
        if item == "frame":
            return self.cap.read()
        return False, None

    def get(self, prop) -> float:
        return 0.0

    def release(self) -> None:
        self.cap.release()


@pytest.fixture
def camera(monkeypatch):
    monkeypatch.setattr(ScriptedCamera, "now", 0.0)
    monkeypatch.setattr(trackio, "open_capture", ScriptedCamera)
    monkeypatch.setattr(trackio.LiveCapture, "clock", staticmethod(lambda: ScriptedCamera.now))
    return ScriptedCamera


def test_a_url_that_cannot_be_opened_is_named_without_its_password(camera, monkeypatch):
    monkeypatch.setattr(camera, "opened", False)
    with pytest.raises(trackio.SourceError) as e:
        trackio.open_frames(video=URL)
    assert SECRET not in str(e.value) and "admin:***@10.0.0.2" in str(e.value)


def test_a_streams_rows_and_lines_never_show_its_password(camera, monkeypatch, tmp_path, capsys):
    # a corrupt frame (its row's reason names the source), then the stream ends (a line names it)
    monkeypatch.setattr(camera, "script", ["frame", "frame", "fail", "frame"])
    out = tmp_path / "poses.jsonl"
    assert main(["track", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"), "--video", URL,
                 "--store", str(example_store()), "--out", str(out), "--format", "jsonl"]) == 0
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    said = capsys.readouterr()
    assert len(rows) == 4 and "admin:***@" in rows[2]["reason"]
    assert "admin:***@" in said.err  # (the stream's end)
    assert SECRET not in out.read_text() + said.out + said.err


def test_masked_keeps_all_but_the_password():
    assert trackio.masked("http://u:p@w@cam:8080/a?b=@") == "http://u:***@cam:8080/a?b=@"
    assert trackio.masked("rtsp://token@cam/x") == "rtsp://***@cam/x"
    assert trackio.masked("rtsp://cam/a@b") == "rtsp://cam/a@b" and trackio.masked("box.mp4") == "box.mp4"


def test_demo_refusing_a_camera_url_does_not_show_its_password(tmp_path, capsys):
    rc = main(["demo", "--url", "http://127.0.0.1:9", "--video", URL, "--camera", str(EXAMPLE / "camera.json"),
               "--out-dir", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "admin:***@10.0.0.2" in err and SECRET not in err

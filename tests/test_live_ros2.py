"""docs/examples/ros2_republish.py with a live source: a stream that ends says so on stderr and
exits non-zero (it ended silently, exit 0), and a live source's stamps are the clock's by default
(they started at the 1970 epoch). A real server and a real MJPEG stream on loopback; the example
runs in-process, ``--dry-run`` (no ROS needed)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import EXAMPLE, example_store

from test_live_sources import MJPEGServer

SCRIPT = Path(__file__).resolve().parent.parent / "docs" / "examples" / "ros2_republish.py"


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store())) as srv:
        yield srv


def _republish(monkeypatch, *args: str) -> int:
    spec = importlib.util.spec_from_file_location("ros2_republish", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setattr("sys.argv", ["ros2_republish.py", *args])
    return module.main()


@pytest.mark.parametrize("after", ["close", "stall"])
def test_a_stream_that_ends_or_stalls_says_so_and_exits_non_zero(server, monkeypatch, capsys, after):
    with MJPEGServer(4, after=after) as cam:
        rc = _republish(monkeypatch, "--url", server.url, "--mesh-unit", "cm", "--video", cam.url,
                        "--camera", str(EXAMPLE / "camera.json"), "--stall-timeout", "1.5", "--dry-run")
    said = capsys.readouterr()
    msgs = [json.loads(line) for line in said.out.splitlines()]
    assert rc == 1 and f"ros2_republish: --video {cam.url}: the stream " in said.err, said.err
    assert ("stalled" if after == "stall" else "ended") in said.err
    assert len(msgs) == 4 and all(m["header"]["stamp"]["sec"] > 1_000_000_000 for m in msgs)  # (the clock's)


def test_frame_time_stamps_a_live_source_by_its_frames(server, monkeypatch, capsys):
    with MJPEGServer(3) as cam:
        _republish(monkeypatch, "--url", server.url, "--mesh-unit", "cm", "--video", cam.url,
                   "--camera", str(EXAMPLE / "camera.json"), "--frame-time", "--dry-run")
    msgs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(msgs) == 3 and msgs[0]["header"]["stamp"] == {"sec": 0, "nanosec": 0}


def test_a_missing_video_is_one_line(server, monkeypatch, capsys, tmp_path):
    rc = _republish(monkeypatch, "--url", server.url, "--mesh-unit", "cm", "--video", str(tmp_path / "no.mp4"),
                    "--dry-run")
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("ros2_republish: error: --video ") and err.count("\n") == 1

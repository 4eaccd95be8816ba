"""``quatrack demo``'s defaults are the bundled example's video *and* camera *and* object: another
``--video`` without ``--camera`` was streamed with the bundled camera (every pose of the user's
box 28 % of its size off, exit 0, no word), and another ``--object`` without ``--video`` was
tracked in the bundled cookie-box video ("20 lost", no hint). Both are refused before anything
is sent or written; the bundled video given by its path still needs no ``--camera``."""

from __future__ import annotations

import argparse
import shutil

import pytest

from quatrack import demo
from quatrack.cli import main
from quatrack.service.server import free_port
from quatrack.testing.scenes import EXAMPLE
from quatrack.viewsets.camera import load_camera


def _run(tmp_path, capsys, *extra):
    rc = main(["demo", "--url", f"http://127.0.0.1:{free_port()}", "--store", str(tmp_path / "store"),
               "--out-dir", str(tmp_path / "out"), "--quiet", *extra])
    return rc, capsys.readouterr().err.strip()


def test_another_video_without_its_camera_is_refused_before_anything_is_sent(tmp_path, capsys):
    video = tmp_path / "walk.mp4"  # (a copy: not the bundled file, whatever it shows)
    shutil.copy(EXAMPLE / "box.mp4", video)
    rc, err = _run(tmp_path, capsys, "--object", "my-box", "--video", str(video))
    assert rc == 2 and err.startswith(f"quatrack demo: error: --video {video}: give --camera") and "\n" not in err, err
    assert "no server answers" not in err and not (tmp_path / "out").exists()  # (nothing connected, nothing written)


def test_another_object_without_a_video_is_refused_with_a_hint(tmp_path, capsys):
    rc, err = _run(tmp_path, capsys, "--object", "my-box")
    assert rc == 2 and "\n" not in err, err
    assert err.startswith("quatrack demo: error: --object my-box: the default video") and "shows the bundled cookie-box" \
        in err and "give --video and --camera of my-box" in err, err
    assert "no server answers" not in err and not (tmp_path / "out").exists()


def _plan(tmp_path, *argv):
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    args = parser.parse_args(["--url", "http://127.0.0.1:9", "--store", str(tmp_path / "store"),
                              "--out-dir", str(tmp_path / "out"), *argv])
    return demo._check(args)


@pytest.mark.parametrize("argv", [[], ["--video", str(EXAMPLE / "box.mp4")],
                                  ["--object", "my-cookies", "--video", str(EXAMPLE / "box.mp4")]])
def test_the_bundled_video_goes_with_the_bundled_camera(tmp_path, argv):
    # no option (the demo as it was), the bundled video by its path, or the bundled box under another name
    plan = _plan(tmp_path, *argv)
    assert plan.camera.fx == load_camera(EXAMPLE / "camera.json").fx and not (tmp_path / "out").exists()


def test_another_video_with_its_camera_is_taken(tmp_path):
    video, camera = tmp_path / "walk.mp4", tmp_path / "cam.json"
    shutil.copy(EXAMPLE / "box.mp4", video)
    camera.write_text('{"width": 640, "height": 480, "fx": 600, "fy": 600, "cx": 319.5, "cy": 239.5}')
    plan = _plan(tmp_path, "--object", "my-box", "--video", str(video), "--camera", str(camera))
    assert plan.video == str(video) and plan.camera.fx == 600

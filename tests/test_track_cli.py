"""``quatrack track`` on live sources and in every output format.

A camera index needs a device, which CI has not: ``--video 0`` is tested with the frame-source
module's capture factory replaced by a looped file source (box.mp4's frames, endlessly, with no
frame rate, as a webcam reports), so the CLI path is the real one from ``--video 0`` on.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from quatrack.testing.scenes import EXAMPLE, example_store
from quatrack.cli import main
from quatrack.recognition import trackio

from test_output import LoopedCamera


def _track(tmp_path, *extra):
    return main(["track", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"),
                 "--store", str(example_store()), "--quiet", *extra])


@pytest.fixture
def camera(monkeypatch):
    monkeypatch.setattr(trackio, "open_capture", LoopedCamera)
    LoopedCamera.opened_with.clear()
    return LoopedCamera


def test_camera_index_with_max_frames_in_json_lines(camera, tmp_path):
    out = tmp_path / "poses.jsonl"
    assert _track(tmp_path, "--video", "0", "--max-frames", "6", "--format", "jsonl", "--out", str(out)) == 0
    assert camera.opened_with == [0]
    msgs = [json.loads(line) for line in out.read_text().splitlines()]
    assert [m["frame"] for m in msgs] == list(range(6))
    assert msgs[0]["status"] == "init" and all(m["status"] == "tracking" for m in msgs[1:])
    times = [m["time_s"] for m in msgs]
    assert times[0] == 0.0 and all(b > a for a, b in zip(times, times[1:]))  # the clock: increasing
    for m in msgs[1:]:
        assert len(m["covariance"]) == 6 and len(m["velocity"]["v"]) == 3 and abs(np.linalg.norm(m["pose"]["q_wxyz"]) - 1) < 1e-6


def test_ctrl_c_ends_a_live_run_with_a_complete_csv(monkeypatch, tmp_path, capsys):
    class Interrupted(LoopedCamera):
        def read(self):
            if self.k >= 4 or len(self.frames) >= 5:  # the user presses Ctrl-C at the 6th frame
                raise KeyboardInterrupt
            return super().read()

    monkeypatch.setattr(trackio, "open_capture", Interrupted)
    out = tmp_path / "poses.csv"
    overlay = tmp_path / "overlay.mp4"
    rc = _track(tmp_path, "--video", "0", "--out", str(out), "--overlay", str(overlay))
    err = capsys.readouterr().err
    assert rc == 0 and "stopped (Ctrl-C) after 5 frames" in err
    rows = list(csv.reader(out.open()))
    assert rows[0] == list(trackio.CSV_COLUMNS) and [int(r[0]) for r in rows[1:]] == [0, 1, 2, 3, 4]
    assert all(len(r) == 17 for r in rows) and rows[1][2] == "init"
    assert overlay.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["overlay.mp4", "poses.csv"]  # no temporary left


def test_ctrl_c_before_the_first_frame_leaves_no_empty_overlay(monkeypatch, tmp_path, capsys):
    # Ctrl-C during the first frame's recognition: a 0-byte overlay.mp4 (no player opens it) was
    # renamed into place, over any earlier one; now the overlay is not written, the CSV has its header
    from quatrack.recognition.video import Tracker

    def interrupted(self, image, time_s):
        raise KeyboardInterrupt

    monkeypatch.setattr(Tracker, "step", interrupted)
    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    rc = _track(tmp_path, "--video", str(EXAMPLE / "box.mp4"), "--out", str(out), "--overlay", str(overlay))
    assert rc == 0 and "stopped (Ctrl-C) after 0 frames" in capsys.readouterr().err
    assert out.read_text().splitlines() == [trackio.CSV_HEADER]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv"]  # no empty video, no temporary


def test_bop_format(camera, tmp_path):
    out = tmp_path / "poses_bop.csv"
    assert _track(tmp_path, "--video", "0", "--fps", "30", "--max-frames", "4", "--out", str(out),
                  "--format", "bop", "--mesh-unit", "cm", "--obj-id", "5") == 0
    lines = out.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time" and len(lines) == 5
    for k, line in enumerate(lines[1:]):
        scene, im, obj, score, R, t, secs = line.split(",")
        assert (scene, im, obj) == ("0", str(k), "5") and float(score) > 10 and float(secs) > 0
        R = np.array([float(x) for x in R.split()]).reshape(3, 3)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
        t_mm = np.array([float(x) for x in t.split()])
        assert 300 < t_mm[2] < 1500  # the box ~65 cm in front of the camera, in millimetres


def test_mesh_unit_with_a_format_that_does_not_convert_is_warned_of(camera, tmp_path, capsys):
    # --format csv --mesh-unit m: the CSV is in the mesh's units (cm here), as the contract says,
    # but nothing told the user, who read the centimetres as metres
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, "--video", "0", "--fps", "30", "--max-frames", "2", "--out", str(out),
                  "--mesh-unit", "m") == 0
    err = capsys.readouterr().err
    assert "--mesh-unit is for --format bop only" in err and "csv" in err
    rows = list(csv.DictReader(out.open()))
    assert 30 < float(rows[0]["tz"]) < 150  # the box ~65 cm away, in the mesh's centimetres
    assert _track(tmp_path, "--video", "0", "--fps", "30", "--max-frames", "1", "--out", str(out),
                  "--format", "bop", "--mesh-unit", "cm") == 0
    assert "--mesh-unit" not in capsys.readouterr().err


@pytest.mark.parametrize("extra, message", [
    (["--format", "bop"], "--mesh-unit"),
    (["--max-frames", "0"], "--max-frames"),
    (["--video", "rtsp://127.0.0.1:9/none"], "cannot be opened as a stream"),
    (["--relocate-every", "0"], "--relocate-every"),
    (["--relocate-every", "nan"], "--relocate-every"),
])
def test_bad_live_options_are_one_line_errors(tmp_path, capsys, extra, message):
    out = tmp_path / "poses.csv"
    args = extra if "--video" in extra else ["--video", str(EXAMPLE / "box.mp4"), *extra]
    rc = _track(tmp_path, *args, "--out", str(out))
    err = capsys.readouterr().err.strip()
    assert rc == 2 and message in err and "\n" not in err and not out.exists()


def test_a_stream_url_on_loopback(tmp_path):
    """A real URL source: box.mp4 served over HTTP on loopback, opened by OpenCV/FFmpeg as a stream
    (timed by the clock), stopped by --max-frames."""
    import functools
    import http.server
    import threading

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(EXAMPLE)))
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        out = tmp_path / "poses.csv"
        url = f"http://127.0.0.1:{srv.server_address[1]}/box.mp4"
        assert _track(tmp_path, "--video", url, "--max-frames", "5", "--out", str(out)) == 0
    finally:
        srv.shutdown()
        srv.server_close()
    rows = list(csv.reader(out.open()))[1:]
    assert [r[0] for r in rows] == ["0", "1", "2", "3", "4"] and rows[0][2] == "init"
    assert all(r[2] == "tracking" for r in rows[1:])
    times = [float(r[1]) for r in rows]
    assert times[0] == 0.0 and all(b > a for a, b in zip(times, times[1:]))


def _box_frames(n: int) -> list:
    import cv2

    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    frames = [cap.read()[1] for _ in range(n)]
    cap.release()
    return frames


def test_an_unreadable_image_in_a_sequence_is_a_lost_row_and_the_track_goes_on(tmp_path, capsys):
    """An image sequence given unquoted (the shell's list of files) with two unreadable files in
    the middle and an empty one at the end: every frame has its row, in order, at its own time;
    the unreadable ones say lost and are named on stderr; the track goes on after the gap."""
    import cv2

    seq = tmp_path / "seq"
    seq.mkdir()
    for k, frame in enumerate(_box_frames(8)):
        path = seq / f"{k:04d}.png"
        if k in (0, 3, 4):  # (the first one too: the overlay had no frame for it, one frame short)
            path.write_text("not an image")
        elif k == 7:
            path.write_bytes(b"")
        else:
            assert cv2.imwrite(str(path), frame)
    files = [str(p) for p in sorted(seq.iterdir())]
    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    assert _track(tmp_path, "--images", *files, "--out", str(out), "--overlay", str(overlay)) == 0
    err = capsys.readouterr().err
    rows = list(csv.reader(out.open()))[1:]
    assert [int(r[0]) for r in rows] == list(range(8))
    assert np.allclose([float(r[1]) for r in rows], np.arange(8) / 30.0)
    assert [r[2] for r in rows] == ["lost", "init", "tracking", "lost", "lost", "tracking", "tracking", "lost"]
    for k in (0, 3, 4, 7):
        assert f"frame {k} cannot be read" in err and f"{k:04d}.png" in err
    cap = cv2.VideoCapture(str(overlay))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 8  # one overlay frame per row
    cap.release()


def test_an_image_of_another_size_in_a_sequence_is_a_lost_row_and_the_track_goes_on(tmp_path, capsys):
    """A stray image of another size in the middle of a sequence ended the run (exit 2, nothing
    written); it is now skipped as an unreadable one is. The camera wrong for the first frame
    stays a one-line error at once."""
    import cv2

    frames = _box_frames(5)
    for k, frame in enumerate(frames):
        assert cv2.imwrite(str(tmp_path / f"{k:04d}.png"), cv2.resize(frame, (320, 240)) if k == 2 else frame)
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, "--images", str(tmp_path / "*.png"), "--out", str(out)) == 0
    err = capsys.readouterr().err
    rows = list(csv.reader(out.open()))[1:]
    assert [int(r[0]) for r in rows] == list(range(5)) and [r[2] for r in rows][2:] == ["lost", "tracking", "tracking"]
    assert "frame 2 cannot be read" in err and "0002.png" in err and "320×240" in err
    assert cv2.imwrite(str(tmp_path / "0000.png"), cv2.resize(frames[0], (320, 200)))  # (another aspect ratio:
    assert _track(tmp_path, "--images", str(tmp_path / "*.png"), "--out", str(tmp_path / "again.csv")) == 2  # 4:3 is scaled)
    err = capsys.readouterr().err.strip()
    assert "0000.png: the camera is for 640×480 px images but the frame is 320×200 px" in err and "\n" not in err
    assert not (tmp_path / "again.csv").exists()


def test_a_sequence_with_no_readable_image_is_a_one_line_error(tmp_path, capsys):
    for name in ("a.png", "b.png"):
        (tmp_path / name).write_text("not an image")
    out = tmp_path / "poses.csv"
    rc = _track(tmp_path, "--images", str(tmp_path / "*.png"), "--out", str(out))
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "no frame can be read" in err and "\n" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png"]  # no output, no temporary


@pytest.mark.parametrize("option", ["--out", "--overlay", "--plot"])
def test_an_output_that_is_the_input_is_refused_before_anything_is_written(tmp_path, capsys, option):
    frame = tmp_path / ("frame.mp4" if option == "--overlay" else "frame.png")
    frame.write_bytes(b"the user's only copy")
    rest = [] if option == "--out" else ["--out", str(tmp_path / "poses.csv")]
    rc = _track(tmp_path, "--images", str(tmp_path / "frame.*"), option, str(frame), *rest)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "is the input" in err and "\n" not in err, err
    assert frame.read_bytes() == b"the user's only copy"
    assert sorted(p.name for p in tmp_path.iterdir()) == [frame.name]


@pytest.mark.parametrize("option", ["--camera", "--init-pose"])
def test_an_output_on_the_camera_or_the_initial_pose_file_is_refused(tmp_path, capsys, option):
    # `--out` given the calibration (or --init-pose) file replaced it with the poses, silently
    import shutil

    given = tmp_path / "given.json"
    if option == "--camera":
        shutil.copy(EXAMPLE / "camera.json", given)
    else:
        given.write_text(json.dumps({"q_wxyz": [1, 0, 0, 0], "t": [0, 0, 50]}))
    before = given.read_bytes()
    rc = _track(tmp_path, "--video", str(EXAMPLE / "box.mp4"), "--max-frames", "2", option, str(given),
                "--out", str(given))
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.endswith("is the input; give another file name (it would be overwritten)"), err
    assert given.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["given.json"]


def test_an_output_on_an_image_of_a_quoted_tilde_glob_is_refused(tmp_path, capsys, monkeypatch):
    # --images '~/frames/*.png' (quoted: the tool expands it) with --out ~/frames/0001.png: the
    # check globbed '~' literally, matched nothing, and the CSV replaced the frame
    import cv2

    monkeypatch.setenv("HOME", str(tmp_path))
    for k, image in enumerate(_box_frames(2)):
        assert cv2.imwrite(str(tmp_path / f"{k:04d}.png"), image)
    frame = tmp_path / "0001.png"
    before = frame.read_bytes()
    rc = _track(tmp_path, "--images", "~/*.png", "--out", str(frame))
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "is the input" in err and frame.read_bytes() == before, err


def test_two_outputs_on_one_file_and_a_folder_as_output_are_refused(tmp_path, capsys):
    video = ["--video", str(EXAMPLE / "box.mp4"), "--max-frames", "2"]
    same = tmp_path / "x.png"
    assert _track(tmp_path, *video, "--out", str(same), "--plot", str(same)) == 2
    assert "also --out" in capsys.readouterr().err
    folder = tmp_path / "poses.csv"
    folder.mkdir()
    assert _track(tmp_path, *video, "--out", str(folder)) == 2
    assert "is a folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv"]  # nothing tracked, nothing written


def test_sigterm_ends_a_run_as_ctrl_c_does(monkeypatch, tmp_path, capsys):
    # timeout, docker stop and systemd send SIGTERM: the process died at once, the learned views
    # were lost and a temporary output was left beside the output
    import os
    import signal

    class Terminated(LoopedCamera):
        def read(self):
            if self.k >= 4 or len(self.frames) >= 5:  # SIGTERM arrives at the 6th frame
                os.kill(os.getpid(), signal.SIGTERM)
            return super().read()

    monkeypatch.setattr(trackio, "open_capture", Terminated)
    out = tmp_path / "poses.csv"
    before = signal.getsignal(signal.SIGTERM)
    rc = _track(tmp_path, "--video", "0", "--out", str(out))
    err = capsys.readouterr().err
    # (it said "stopped (Ctrl-C)": the user pressed nothing, a service manager stopped it)
    assert rc == 0 and "stopped (SIGTERM) after 5 frames; outputs complete" in err and "Ctrl-C" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv"]  # complete, no temporary left
    assert [r[0] for r in csv.reader(out.open())][1:] == ["0", "1", "2", "3", "4"]
    assert signal.getsignal(signal.SIGTERM) is before  # (the handler is the caller's again)


def test_a_tilde_in_quoted_or_equals_paths_is_the_home_folder(tmp_path, capsys, monkeypatch):
    # the shell leaves '~/box.mp4' (quoted) and --out=~/poses.csv as they are: track said
    # "--video ~/box.mp4: no such file", then "--out ~/poses.csv: the folder .../~ does not exist"
    import shutil

    from quatrack.testing.scenes import example_store

    home = tmp_path / "home"
    (home / "in").mkdir(parents=True)
    shutil.copy(EXAMPLE / "box.mp4", home / "in" / "box.mp4")
    shutil.copy(EXAMPLE / "camera.json", home / "in" / "camera.json")
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(tmp_path)
    rc = main(["track", "--object", "cookie-box", "--camera", "~/in/camera.json", "--store", str(example_store()),
               "--quiet", "--video", "~/in/box.mp4", "--max-frames", "2", "--out=~/poses.csv",
               "--overlay=~/overlay.mp4", "--plot=~/plot.png"])
    assert rc == 0, capsys.readouterr().err
    assert sorted(p.name for p in home.iterdir()) == ["in", "overlay.mp4", "plot.png", "poses.csv"]
    assert len((home / "poses.csv").read_text().splitlines()) == 3 and not (tmp_path / "~").exists()
    frame = home / "in" / "frame.png"
    import cv2

    assert cv2.imwrite(str(frame), _box_frames(1)[0])
    rc = main(["locate", "--object", "cookie-box", "--camera", "~/in/camera.json", "--store", str(example_store()),
               "~/in/frame.png", "--json"])
    line = json.loads(capsys.readouterr().out)
    assert rc == 0 and line["found"] and line["image"] == str(frame)


def _overlay_size_and_count(path) -> tuple[int, int, int]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    return frames[0].shape[1], frames[0].shape[0], len(frames)


@pytest.mark.parametrize("fps, written", [("0.001", "0.002"), ("77.777", "77.8")])
def test_an_overlay_at_a_rate_mp4_cannot_store_is_written_at_the_nearest_it_can(tmp_path, capsys, fps, written):
    # --fps 0.001 (a time-lapse) or 77.777 with --overlay: OpenCV's "Could not open codec mpeg4" lines,
    # then "--overlay: cannot write an MP4 video here", exit 2 and no poses
    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    rc = _track(tmp_path, "--video", str(EXAMPLE / "box.mp4"), "--max-frames", "3", "--fps", fps,
                "--out", str(out), "--overlay", str(overlay))
    err = capsys.readouterr().err
    assert rc == 0, err
    assert err.strip() == (f"quatrack track: note: --overlay plays at {written} frames/s: MP4 cannot store {fps} "
                           f"(the poses' time_s is unchanged)"), err
    times = [float(r[1]) for r in list(csv.reader(out.open()))[1:]]
    assert np.allclose(times, np.arange(3) / float(fps), rtol=0, atol=1e-6)  # (the CSV has 6 decimals)
    assert _overlay_size_and_count(overlay) == (640, 480, 3)


def test_an_absurd_frame_rate_is_a_one_line_error(tmp_path, capsys):
    # --fps 1e-308: time_s of frame 2 was infinite, the run failed there with the tracker's error
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, "--video", str(EXAMPLE / "box.mp4"), "--fps", "1e-308", "--out", str(out)) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("quatrack track: error: --fps must be a positive number (from 1e-06 to 1000)"), err
    assert "\n" not in err and not out.exists()


def test_an_overlay_of_odd_sized_frames_keeps_every_pixel(tmp_path, capsys):
    # 639×479 frames came out as a 638×478 overlay, rescaled, without a word; MP4 stores even sizes
    # only, so they are padded by a black column and row, and a note says so
    import cv2

    camera = json.loads((EXAMPLE / "camera.json").read_text())
    camera.update(width=639, height=479)
    (tmp_path / "camera.json").write_text(json.dumps(camera))
    for k, frame in enumerate(_box_frames(3)):
        assert cv2.imwrite(str(tmp_path / f"{k:04d}.png"), frame[:479, :639])
    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    rc = main(["track", "--object", "cookie-box", "--camera", str(tmp_path / "camera.json"), "--store",
               str(example_store()), "--quiet", "--images", str(tmp_path / "*.png"), "--out", str(out),
               "--overlay", str(overlay)])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert ("--overlay is 640×480: MP4 stores even sizes only, so the 639×479 frames have a black column at the "
            "right and a row at the bottom (pixel coordinates unchanged)") in err
    assert _overlay_size_and_count(overlay) == (640, 480, 3)
    cap = cv2.VideoCapture(str(overlay))
    frame = cap.read()[1]
    cap.release()
    assert frame[:, -1].mean() < 12 and frame[-1].mean() < 12  # the padding: black (MPEG-4 blurs it a little)
    assert frame[100:400, 300:600].mean() > 40  # the picture where it was
    assert [r[2] for r in list(csv.reader(out.open()))[1:]] == ["init", "tracking", "tracking"]


def _mjpg_avi(path, frames, damaged=()) -> None:
    """An MJPG AVI of ``frames`` with the JPEG data of the frames in ``damaged`` zeroed (a failing
    disk, a dropped USB packet): the container keeps each frame's place, the frame cannot be decoded."""
    import cv2

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, frames[0].shape[1::-1])
    for frame in frames:
        writer.write(frame)
    writer.release()
    data = bytearray(path.read_bytes())
    chunks, at = [], 0
    while (at := data.find(b"00dc", at + 1)) > 0:
        size = int.from_bytes(data[at + 4:at + 8], "little")
        if data[at + 8:at + 10] == b"\xff\xd8":  # (a frame's chunk; "00dc" also appears in the index)
            chunks.append((at + 8, size))
    assert len(chunks) == len(frames)
    for k in damaged:
        start, size = chunks[k]
        data[start:start + size] = bytes(size)
    path.write_bytes(data)


def test_a_frame_of_a_video_that_cannot_be_decoded_is_a_lost_row_and_the_track_goes_on(tmp_path, capsys):
    # OpenCV's read() says False for a frame whose data cannot be decoded, and goes on at the next
    # call: the first damaged frame ended the run, the rest of the video silently not tracked (and a
    # damaged first frame was "no frame can be decoded")
    video = tmp_path / "damaged.avi"
    _mjpg_avi(video, _box_frames(8), damaged=(0, 3, 4))
    out, overlay = tmp_path / "poses.jsonl", tmp_path / "overlay.mp4"
    assert _track(tmp_path, "--video", str(video), "--format", "jsonl", "--out", str(out),
                  "--overlay", str(overlay)) == 0
    err = capsys.readouterr().err
    msgs = [json.loads(line) for line in out.read_text().splitlines()]
    assert [m["frame"] for m in msgs] == list(range(8))
    assert np.allclose([m["time_s"] for m in msgs], np.arange(8) / 30.0)
    assert [m["status"] for m in msgs] == ["lost", "init", "tracking", "lost", "lost", "tracking", "tracking", "tracking"]
    for k in (0, 3, 4):
        assert msgs[k]["pose"] is None and "cannot be decoded" in msgs[k]["reason"]
        assert f"frame {k} cannot be read, written as lost: --video {video}: its data cannot be decoded" in err
    assert _overlay_size_and_count(overlay) == (640, 480, 8)  # one overlay frame per row


def test_a_video_whose_frames_all_fail_to_decode_is_a_one_line_error(tmp_path, capsys):
    video = tmp_path / "damaged.avi"
    _mjpg_avi(video, _box_frames(3), damaged=(0, 1, 2))
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, "--video", str(video), "--out", str(out)) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"quatrack track: error: --video {video}: no frame can be decoded" and not out.exists()


def test_a_video_frame_of_another_size_is_a_lost_row(monkeypatch, tmp_path, capsys):
    # a stream that changes resolution mid-run: exit 2 and nothing written, as a stray image of
    # another size in a sequence was; now its row says lost, as that image's does
    import cv2

    class Resized(LoopedCamera):
        def read(self):
            ok, frame = super().read()
            return ok, cv2.resize(frame, (320, 240)) if len(self.frames) == 3 and self.k == 0 else frame

    monkeypatch.setattr(trackio, "open_capture", Resized)
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, "--video", "0", "--max-frames", "5", "--out", str(out)) == 0
    err = capsys.readouterr().err
    assert [r[2] for r in list(csv.reader(out.open()))[1:]] == ["init", "tracking", "lost", "tracking", "tracking"]
    assert "frame 2 cannot be read" in err and "320×240" in err, err


def test_locate_expands_a_quoted_glob_as_track_does(tmp_path, capsys):
    # locate 'frames/*.png' (quoted, as track --images takes it): "cannot read image frames/*.png"
    import cv2

    for k, frame in enumerate(_box_frames(2)):
        assert cv2.imwrite(str(tmp_path / f"{k:04d}.png"), frame)
    rc = main(["locate", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"), "--store",
               str(example_store()), "--json", str(tmp_path / "*.png"), str(tmp_path / "none*.jpg")])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["image"] for line in lines] == [str(tmp_path / "0000.png"), str(tmp_path / "0001.png"),
                                                 str(tmp_path / "none*.jpg")]
    assert lines[0]["found"] and lines[1]["found"] and lines[2]["error"].endswith("no file matches") and rc == 1


def test_frames_numbered_without_leading_zeros_are_warned_of(tmp_path, capsys):
    # frame_1 … frame_10: by name (the contract's order) frame_10 comes second, and the track jumped
    # back and forth through the sequence without a word
    import cv2

    frame = _box_frames(1)[0]
    for n in (1, 2, 10):
        assert cv2.imwrite(str(tmp_path / f"frame_{n}.png"), frame)
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, "--images", str(tmp_path / "frame_*.png"), "--max-frames", "1", "--out", str(out)) == 0
    err = capsys.readouterr().err.strip()
    assert err == (f"quatrack track: warning: --images are read in order of name, so {tmp_path / 'frame_10.png'} "
                   f"comes before {tmp_path / 'frame_2.png'}: number the files with leading zeros (0002 for 2), "
                   f"or give them in order"), err
    for n in (1, 2, 10):
        (tmp_path / f"frame_{n}.png").rename(tmp_path / f"frame_{n:04d}.png")
    assert _track(tmp_path, "--images", str(tmp_path / "frame_*.png"), "--max-frames", "1", "--out", str(out)) == 0
    assert capsys.readouterr().err == ""


def test_an_image_list_file(tmp_path, capsys):
    # --images frames.txt (one file per line, as many tools write them) was read as an image: "no frame
    # can be read"; relative lines are relative to the list, a missing one is a lost row
    import cv2

    (tmp_path / "f").mkdir()
    for k, frame in enumerate(_box_frames(3)):
        assert cv2.imwrite(str(tmp_path / "f" / f"{k}.png"), frame)
    listing = tmp_path / "frames.txt"
    listing.write_text(f"# frames\nf/0.png\n\n{tmp_path / 'f' / '1.png'}\nf/missing.png\nf/2.png\n")
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, "--images", str(listing), "--out", str(out)) == 0
    err = capsys.readouterr().err
    assert [r[2] for r in list(csv.reader(out.open()))[1:]] == ["init", "tracking", "lost", "tracking"]
    assert "frame 2 cannot be read" in err and "missing.png" in err
    # an output on a listed image is refused as on a globbed one
    assert _track(tmp_path, "--images", str(listing), "--out", str(tmp_path / "f" / "2.png")) == 2
    assert "is the input" in capsys.readouterr().err


def test_an_empty_video_file_says_so(tmp_path, capsys):
    (tmp_path / "rec.mp4").write_bytes(b"")
    assert _track(tmp_path, "--video", str(tmp_path / "rec.mp4"), "--out", str(tmp_path / "p.csv")) == 2
    assert capsys.readouterr().err.strip() == f"quatrack track: error: --video {tmp_path / 'rec.mp4'}: the file is empty (0 bytes)"

"""`quatrack track`'s outputs: where they are written (links, devices, /proc), which names they
take, and what a Ctrl-C leaves. The trial of `track` found each of these."""

from __future__ import annotations

import os

from quatrack.recognition import trackio


def _write(path, text: str) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)


def test_a_link_to_a_file_is_written_at_the_file_and_the_link_kept(tmp_path):
    # `--out link.csv` replaced the link by a regular file; the file it led to was never written
    real, link = tmp_path / "real.csv", tmp_path / "link.csv"
    _write(real, "old\n")
    link.symlink_to(real)
    with trackio.atomic_path(link, "--out") as tmp:
        assert os.path.dirname(tmp) == str(tmp_path) and not os.path.islink(tmp)
        _write(tmp, "new\n")
    assert link.is_symlink() and real.read_text() == "new\n"
    dangling = tmp_path / "dangling.csv"  # (a link to a file not there yet: the file is made)
    dangling.symlink_to(tmp_path / "made.csv")
    with trackio.atomic_path(dangling, "--out") as tmp:
        _write(tmp, "x\n")
    assert dangling.is_symlink() and (tmp_path / "made.csv").read_text() == "x\n"


def test_a_link_to_an_open_file_of_proc_is_written_in_place(tmp_path):
    # `--out /dev/stdout` with stdout redirected to a file, as root: /dev/stdout (a link to
    # /proc/self/fd/1) was replaced by a regular file, for every process, and the poses lost.
    # Here a link of our own to /proc/self/fd/N, N a file we opened: the real /dev/stdout untouched
    redirected = tmp_path / "redirected.txt"
    fd = os.open(redirected, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        stdout = tmp_path / "stdout"
        stdout.symlink_to(f"/proc/self/fd/{fd}")
        with trackio.atomic_path(stdout, "--out") as tmp:
            assert tmp == str(stdout)
            _write(tmp, "poses\n")
        assert stdout.is_symlink() and redirected.read_text() == "poses\n"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["redirected.txt", "stdout"]
    finally:
        os.close(fd)


def test_a_pipe_of_proc_is_written_in_place_and_an_empty_overlay_there_is_not_unlinked(tmp_path):
    r, w = os.pipe()
    try:
        path = f"/proc/self/fd/{w}"
        assert trackio.written_where(path) == (path, True)
        link = tmp_path / "poses.csv"
        link.symlink_to(path)
        with trackio.atomic_path(link, "--out") as tmp:
            assert tmp == str(link)
            _write(tmp, "row\n")
        assert link.is_symlink() and os.read(r, 100) == b"row\n"
    finally:
        os.close(r)
        os.close(w)
    empty = tmp_path / "empty.mp4"  # (an overlay with no frame on a redirected stdout: the link was unlinked)
    fd = os.open(empty, os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        link = tmp_path / "overlay.mp4"
        link.symlink_to(f"/proc/self/fd/{fd}")
        with trackio.atomic_path(link, "--overlay") as tmp:
            trackio.VideoOut(tmp, 30.0).close()  # (no frame: a file of its own is removed, this is not)
        assert link.is_symlink() and empty.exists()
    finally:
        os.close(fd)


def test_an_output_on_the_list_file_given_to_images_is_refused(tmp_path, capsys):
    # `--images frames.txt --out frames.txt`: the list was replaced by the poses (the images it
    # lists, and --video, were refused already)
    from test_image_arguments import _frames
    from test_track_cli import _track

    _frames(tmp_path, ["0000.png"])
    listing = tmp_path / "frames.txt"
    listing.write_text("0000.png\n")
    assert _track(tmp_path, "--images", str(listing), "--out", str(listing)) == 2
    assert f"--out {listing}: is the input; give another file name" in capsys.readouterr().err
    assert listing.read_text() == "0000.png\n"


def test_an_output_name_of_up_to_255_bytes_is_written(tmp_path):
    # the temporary ".NAME.XXXXXXXX.ext" was over 255 bytes: a 250-byte name the filesystem takes
    # failed with "File name too long"
    for name in ("p" * 246 + ".csv", "é" * 123 + ".mp4", "x" * 255):
        target = tmp_path / name
        assert len(os.fsencode(name)) >= 250
        with trackio.atomic_path(target, "--out") as tmp:
            assert tmp.endswith(os.path.splitext(name)[1] or "")
            _write(tmp, "rows\n")
        assert target.read_text() == "rows\n"
    assert len(list(tmp_path.iterdir())) == 3


def test_the_threads_a_run_started_are_gone_when_it_returns_on_every_path(monkeypatch):
    # Ctrl-C during the first frame aborted the process ("terminate called without an active
    # exception", exit 134): the FLANN forest's thread was still inside OpenCV, or just leaving
    # it, as the interpreter shut down; the same after an RTSP URL that cannot be opened (its
    # capture thread still releasing). run() now waits for the threads it started, to the end
    # of their native exit, whatever ends it.
    import threading
    import time

    import pytest

    from quatrack import track_cli

    started = []

    def body(args):
        t = threading.Thread(target=time.sleep, args=(0.3,), daemon=True)
        t.start()
        started.append(t)
        raise args

    monkeypatch.setattr(track_cli, "_run", body)
    for ending in (KeyboardInterrupt(), track_cli.UserError("the stream cannot be opened")):
        with pytest.raises(type(ending)):
            track_cli.run(ending)
        t = started[-1]
        assert not t.is_alive() and not os.path.exists(f"/proc/self/task/{t.native_id}")


def test_a_second_ctrl_c_while_the_outputs_are_finished_is_said_once_and_ignored(monkeypatch, tmp_path, capfd):
    # a second Ctrl-C 10-20 ms after the first lost every output (exit 130, "interrupted"); here
    # it comes (twice) while the overlay is being finished, after the first stopped the tracking
    import signal

    from test_output import LoopedCamera
    from test_track_cli import _track

    class Interrupted(LoopedCamera):
        def read(self):
            if len(self.frames) >= 3:
                raise KeyboardInterrupt
            return super().read()

    close = trackio.VideoOut.close

    def pressed_again(self):
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
        close(self)

    monkeypatch.setattr(trackio, "open_capture", Interrupted)
    monkeypatch.setattr(trackio.VideoOut, "close", pressed_again)
    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    handler = signal.getsignal(signal.SIGINT)
    rc = _track(tmp_path, "--video", "0", "--out", str(out), "--overlay", str(overlay))
    err = capfd.readouterr().err
    assert rc == 0 and "stopped (Ctrl-C) after 3 frames" in err, err
    assert err.count("finishing the outputs; Ctrl-C again is ignored") == 1
    assert len(out.read_text().splitlines()) == 4 and overlay.stat().st_size > 0
    assert signal.getsignal(signal.SIGINT) is handler  # (put back)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["overlay.mp4", "poses.csv"]


_AGAIN_AFTER_THE_RUN = """
import os, runpy, signal, sys, time
from quatrack import track_cli
from quatrack.recognition.video import Tracker

def step(self, image, time_s):
    raise KeyboardInterrupt  # (the first Ctrl-C, at the first frame)

def then_again(args):
    rc = run(args)
    os.kill(os.getpid(), signal.SIGINT)  # (the second, once the outputs are complete)
    time.sleep(0.05)
    return rc

Tracker.step, run, track_cli.run = step, track_cli.run, then_again
sys.argv = ["quatrack", *sys.argv[1:]]
runpy.run_module("quatrack", run_name="__main__", alter_sys=True)
"""


def test_a_second_ctrl_c_as_the_program_ends_does_not_kill_it(tmp_path):
    # 30 ms-0.4 s after the first, a second Ctrl-C (after "outputs complete") killed the process by
    # the signal instead of exit 0: the handler put back, then the interpreter's exit set the default
    import subprocess
    import sys

    from quatrack.testing.scenes import EXAMPLE, example_store

    out = tmp_path / "poses.csv"
    r = subprocess.run([sys.executable, "-c", _AGAIN_AFTER_THE_RUN, "track", "--object", "cookie-box", "--camera",
                        str(EXAMPLE / "camera.json"), "--store", str(example_store()), "--quiet", "--video",
                        str(EXAMPLE / "box.mp4"), "--out", str(out)],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0 and "stopped (Ctrl-C) after 0 frames" in r.stderr, (r.returncode, r.stderr)
    assert out.read_text().splitlines() == [trackio.CSV_HEADER]


def test_ctrl_c_before_the_first_frame_says_the_overlay_is_not_written(monkeypatch, tmp_path, capsys):
    # the overlay of a run stopped before its first frame is no video (not written), and the line
    # said "outputs complete"
    from quatrack.recognition.video import Tracker
    from quatrack.testing.scenes import EXAMPLE
    from test_track_cli import _track

    def interrupted(self, image, time_s):
        raise KeyboardInterrupt

    monkeypatch.setattr(Tracker, "step", interrupted)
    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    assert _track(tmp_path, "--video", str(EXAMPLE / "box.mp4"), "--out", str(out),
                  "--overlay", str(overlay)) == 0
    err = capsys.readouterr().err
    assert (f"stopped (Ctrl-C) after 0 frames; --overlay {overlay} not written (no frame to show); "
            f"the other outputs complete") in err, err
    assert not overlay.exists() and out.exists()


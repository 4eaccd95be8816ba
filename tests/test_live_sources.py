"""``quatrack track --video URL`` / ``--video 0`` as a network camera meets it: a stream that
stalls, drops, sends a corrupt frame; Ctrl-C or SIGTERM while a read is blocked; ``--max-frames``.

The streams are real: an HTTP MJPEG server (``multipart/x-mixed-replace`` of box.mp4's frames as
JPEG) in a thread on loopback, read by OpenCV's FFmpeg backend as a network camera's would be. The
tests assert on what is read and written, not on how long it takes; where a stall is the subject,
its timeout is the only wait.
"""

from __future__ import annotations

import csv
import http.server
import signal
import socket
import threading

import cv2
import pytest

from quatrack.cli import main
from quatrack.recognition import trackio
from quatrack.testing.scenes import EXAMPLE, example_store

from test_output import LoopedCamera


def _jpegs(n: int) -> list[bytes]:
    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    out = [cv2.imencode(".jpg", cap.read()[1])[1].tobytes() for _ in range(n)]
    cap.release()
    return out


class MJPEGServer:
    """An MJPEG stream of ``n`` frames on loopback. ``after``: what it does once they are sent —
    ``"close"`` (the stream ends), ``"drop"`` (the connection is cut, as a camera losing its
    network), ``"stall"`` (it holds the connection and sends nothing more); ``corrupt``: indices
    of frames sent as broken JPEG data."""

    def __init__(self, n: int = 8, after: str = "close", corrupt: tuple[int, ...] = ()) -> None:
        frames = _jpegs(n)
        self.release = threading.Event()
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    for k, jpg in enumerate(frames):
                        if k in corrupt:
                            jpg = jpg[:200] + b"\0" * 500 + jpg[700:1000]
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                                         % len(jpg) + jpg + b"\r\n")
                    self.wfile.flush()
                    if after == "drop":
                        self.connection.shutdown(socket.SHUT_RDWR)
                    elif after == "stall":
                        server.release.wait(60)
                except OSError:
                    pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/cam.mjpg"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def __enter__(self) -> "MJPEGServer":
        return self

    def __exit__(self, *exc) -> None:
        self.release.set()
        self.httpd.shutdown()
        self.httpd.server_close()


def _track(*extra):
    return main(["track", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"),
                 "--store", str(example_store()), "--quiet", *extra])


def test_a_corrupt_frame_of_a_stream_is_skipped_and_the_stream_goes_on():
    # one broken JPEG part of an MJPEG stream: OpenCV's read fails once and the next frame comes;
    # the source took the first failure for the end, and the rest of the stream was not read
    with MJPEGServer(8, corrupt=(3,)) as srv:
        src = trackio.open_frames(video=srv.url)
        got = [i for i, _, _ in src]
    assert got == [0, 1, 2, 4, 5, 6, 7]
    assert [i for i, _, _ in src.skipped] == [3] and "cannot be decoded" in src.skipped[0][2]
    assert src.ended.startswith("the stream ended: it gives no more frames")


@pytest.mark.parametrize("after, ended", [("drop", "the stream ended: it gives no more frames (closed or dropped"),
                                          ("stall", "the stream stalled: no frame within 1.5 s")])
def test_a_stream_that_drops_or_stalls_ends_the_run_saying_so(tmp_path, capsys, after, ended):
    # the run ended as if the stream were a finished file: exit 0, not a word (a stall after
    # FFmpeg's 30 s, with OpenCV's "Stream timeout triggered" warning on stderr)
    out = tmp_path / "poses.csv"
    with MJPEGServer(4, after=after) as srv:
        rc = _track("--video", srv.url, "--stall-timeout", "1.5", "--out", str(out))
        err = capsys.readouterr().err
    assert rc == 0, err
    assert f"quatrack track: --video {srv.url}: {ended}" in err and "stopped after 4 frames; outputs complete" in err
    assert "WARN" not in err
    rows = list(csv.reader(out.open()))
    assert rows[0] == list(trackio.CSV_COLUMNS) and [r[0] for r in rows[1:]] == ["0", "1", "2", "3"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv"]


def test_a_stream_that_takes_the_connection_and_never_answers_is_a_bounded_one_line_error(tmp_path, capsys):
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    try:
        out = tmp_path / "poses.csv"
        url = f"http://127.0.0.1:{listener.getsockname()[1]}/cam"
        assert _track("--video", url, "--stall-timeout", "1", "--out", str(out)) == 2
    finally:
        listener.close()
    err = capsys.readouterr().err.strip()
    assert err == f"quatrack track: error: --video {url}: cannot be opened as a stream (no answer within 1 s)"
    assert not out.exists()


class BlockedCamera(LoopedCamera):
    """A camera whose 4th read blocks in native code, as a stalled stream's read in FFmpeg does:
    the signal it sends (Ctrl-C, SIGTERM) cannot interrupt that thread while it waits."""

    signum = signal.SIGINT
    unblock = threading.Event()
    returned = False

    def read(self):
        if len(self.frames) == 3 and self.k == 0:
            signal.pthread_sigmask(signal.SIG_BLOCK, {self.signum})  # (native code runs no Python handler)
            try:
                import os

                os.kill(os.getpid(), self.signum)
                try:
                    BlockedCamera.unblock.wait(10)
                finally:  # (returned, or raised: no longer blocked)
                    BlockedCamera.returned = True
            finally:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, {self.signum})
        return super().read()


@pytest.mark.parametrize("signum, cause", [(signal.SIGINT, "Ctrl-C"), (signal.SIGTERM, "SIGTERM")])
def test_ctrl_c_or_sigterm_during_a_blocked_read_stops_at_once_with_complete_outputs(monkeypatch, tmp_path, capsys,
                                                                                    signum, cause):
    # the read blocked the main thread: the signal took effect only once FFmpeg gave up (30 s)
    monkeypatch.setattr(trackio, "open_capture", BlockedCamera)
    monkeypatch.setattr(BlockedCamera, "signum", signum)
    BlockedCamera.unblock.clear()
    BlockedCamera.returned = False
    out = tmp_path / "poses.csv"
    try:
        rc = _track("--video", "0", "--out", str(out))
        still_blocked = not BlockedCamera.returned  # (the run ended while the read was still blocked)
    finally:
        BlockedCamera.unblock.set()
    err = capsys.readouterr().err
    assert rc == 0 and f"stopped ({cause}) after 3 frames; outputs complete" in err, err
    assert still_blocked
    assert [r[0] for r in csv.reader(out.open())][1:] == ["0", "1", "2"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv"]


def test_max_frames_reads_no_frame_past_the_last(monkeypatch):
    # --max-frames N read frame N+1 before stopping: on a stalled stream that was a 30 s wait
    reads = []

    class Counted(LoopedCamera):
        def read(self):
            reads.append(1)
            return super().read()

    monkeypatch.setattr(trackio, "open_capture", Counted)
    src = trackio.open_frames(video="0", max_frames=3)
    assert [i for i, _, _ in src] == [0, 1, 2] and len(reads) == 3


@pytest.mark.parametrize("video", ["0", "rtsp://127.0.0.1:9/cam"])
def test_demo_given_a_camera_or_a_stream_points_to_track(tmp_path, capsys, video):
    # `quatrack demo --video 0` said "--video 0: no such file", as if the camera were a missing file
    rc = main(["demo", "--url", "http://127.0.0.1:9", "--video", video, "--camera", str(EXAMPLE / "camera.json"),
               "--out-dir", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err, err
    assert err.startswith(f"quatrack demo: error: --video {video}: demo streams a video file")
    assert f"use `quatrack track --video {video}`" in err and not (tmp_path / "out").exists()

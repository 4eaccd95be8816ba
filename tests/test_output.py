"""The track-output module (recognition/trackio.py) and the one overlay drawer: frame sources and
their time rule, a fake live camera, CSV/JSON-lines/BOP/ROS rows and their round trips, atomic
writes, the progress line, and a readable overlay label (pixel comparison, no OCR)."""

from __future__ import annotations

import io
import json
import os

import cv2
import numpy as np
import pytest

from quatrack.recognition import trackio
from quatrack.recognition.overlay import draw_label, draw_overlay
from quatrack.recognition.video import TrackStep
from quatrack.tracking import quaternion as quat
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose

EXAMPLE = os.path.join(os.path.dirname(__file__), "..", "examples", "cookie-box")


def _step(frame=3, status="tracking", seed=0) -> TrackStep:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 0.01 + np.eye(6) * 1e-4
    q = quat.canonical(quat.from_rotvec(rng.normal(size=3)))
    return TrackStep(frame=frame, time_s=frame / 30, status=status, t=rng.normal(size=3) + [0, 0, 40],
                     q_wxyz=q, v=rng.normal(size=3), omega=rng.normal(size=3), covariance=cov, inliers=42,
                     timings_ms={"total": 12.5})


# --- frame sources -------------------------------------------------------------------------------

def test_video_file_frames_and_the_rate_rule():
    src = trackio.open_frames(video=os.path.join(EXAMPLE, "box.mp4"), max_frames=5)
    got = list(src)
    assert [i for i, _, _ in got] == [0, 1, 2, 3, 4]
    assert not src.live and abs(src.rate - 29.966) < 0.01  # the container's rate
    assert np.allclose([t for _, t, _ in got], np.arange(5) / src.rate)
    assert trackio.frame_rate(12.0, 29.97) == 12.0
    assert trackio.frame_rate(None, float("nan")) == trackio.frame_rate(None, 0.0) == trackio.frame_rate(None, 5000) == 30.0


def test_images_sorted_by_name(tmp_path):
    for k in (2, 10, 1):
        cv2.imwrite(str(tmp_path / f"f{k:02d}.png"), np.full((8, 8, 3), k, np.uint8))
    src = trackio.open_frames(images=str(tmp_path / "*.png"), fps=10)
    got = list(src)
    assert [int(img[0, 0, 0]) for _, _, img in got] == [1, 2, 10]
    assert [t for _, t, _ in got] == [0.0, 0.1, 0.2]
    assert src.where(2).endswith("f10.png")
    with pytest.raises(trackio.SourceError, match="is a folder; give a glob of its images, e.g. '.*\\*.png'"):
        trackio.open_frames(images=str(tmp_path))  # (was "no file matches")
    # a library caller's fps or max_frames of the wrong kind: math.isfinite's "must be real number,
    # not str" / "'<' not supported", naming neither
    with pytest.raises(trackio.SourceError, match=r"--fps must be a positive number .*got '30'"):
        trackio.open_frames(images=str(tmp_path / "*.png"), fps="30")
    with pytest.raises(trackio.SourceError, match=r"--max-frames must be at least 1 .*got '5'"):
        trackio.open_frames(images=str(tmp_path / "*.png"), max_frames="5")
    assert len(list(trackio.open_frames(images=str(tmp_path / "*.png"), fps=np.float32(10), max_frames=np.int64(2)))) == 2


@pytest.mark.parametrize("video, message", [("missing.mp4", "no such file"), ("7", "cannot be opened as a camera"),
                                            ("frames", "is a folder; for its images give --images '.*frames/\\*.png'")])
def test_bad_sources_are_one_line_errors(tmp_path, monkeypatch, video, message):
    class Closed:
        def isOpened(self):
            return False

        def release(self):
            pass

    monkeypatch.setattr(trackio, "open_capture", lambda target, *timeout: Closed())
    (tmp_path / "frames").mkdir()
    with pytest.raises(trackio.SourceError, match=message):
        trackio.open_frames(video=str(tmp_path / video) if not video.isdigit() else video)


def test_a_camera_that_cannot_be_opened_is_one_line_without_opencv_warnings(tmp_path):
    # `track --video 7` without such a camera: OpenCV's "[ WARN:0@0.5] global cap_v4l.cpp ... can't
    # open camera by index" lines came on stderr before the error
    import subprocess
    import sys

    script = ("from quatrack.recognition import trackio\n"
              "try:\n    trackio.open_frames(video='97')\n"
              "except trackio.SourceError as exc:\n    print(exc)\n")
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert p.stdout.strip() == "--video 97: cannot be opened as a camera" and "WARN" not in p.stderr, p.stderr


class LoopedCamera:
    """A stand-in for a camera: ``cv2.VideoCapture(0)`` needs a device, so the frames of
    box.mp4 are served in a loop, endlessly, as a camera would; it records what it was opened on."""

    opened_with: list = []

    def __init__(self, target, *timeout):
        LoopedCamera.opened_with.append(target)
        self.cap = cv2.VideoCapture(os.path.join(EXAMPLE, "box.mp4"))
        self.frames = []
        self.k = 0

    def isOpened(self):
        return True

    def read(self):
        if len(self.frames) < 10:
            ok, f = self.cap.read()
            self.frames.append(f)
            return ok, f
        self.k += 1
        return True, self.frames[self.k % 10]

    def get(self, prop):
        return 0.0  # cameras often report no rate

    def release(self):
        self.cap.release()


def test_a_camera_index_is_live_and_timed_by_the_clock(monkeypatch):
    monkeypatch.setattr(trackio, "open_capture", LoopedCamera)
    LoopedCamera.opened_with.clear()
    ticks = iter([100.0, 100.04, 100.09, 100.2])  # (read as each frame is grabbed: LiveCapture.clock)
    monkeypatch.setattr(trackio.LiveCapture, "clock", staticmethod(lambda: next(ticks, 0.0)))
    src = trackio.open_frames(video="0", max_frames=4)
    got = list(src)
    assert LoopedCamera.opened_with == [0] and src.live
    assert len(got) == 4 and np.allclose([t for _, t, _ in got], [0.0, 0.04, 0.09, 0.2])
    # a URL is passed to OpenCV as given; --fps turns the clock off
    src = trackio.open_frames(video="rtsp://127.0.0.1:8554/cam", fps=10, max_frames=2)
    assert LoopedCamera.opened_with[-1] == "rtsp://127.0.0.1:8554/cam" and not src.live
    assert [t for _, t, _ in src] == [0.0, 0.1]


# --- rows ---------------------------------------------------------------------------------------

def test_csv_rows_tracking_and_lost():
    s = _step()
    cols = trackio.csv_row(s).split(",")
    assert len(cols) == len(trackio.CSV_COLUMNS) == 17
    assert cols[:3] == ["3", "0.100000", "tracking"] and cols[-1] == "42"
    assert np.allclose([float(x) for x in cols[3:6]], s.t, atol=1e-4)
    assert np.allclose([float(x) for x in cols[6:10]], s.q_wxyz, atol=1e-5)
    lost = trackio.csv_row(TrackStep(frame=4, time_s=0.5, status="lost", inliers=3)).split(",")
    assert lost[:3] == ["4", "0.500000", "lost"] and lost[3:16] == [""] * 13 and lost[16] == "3"


def test_message_round_trip_and_jsonl():
    s = _step()
    msg = json.loads(trackio.jsonl_row(s))
    assert msg["type"] == "pose" and msg["status"] == "tracking" and len(msg["covariance"]) == 6
    # the WebSocket pose message's keys (the contract's list and the extension's), each line
    contract = {"frame", "status", "pose", "velocity", "covariance", "inliers", "latency_ms"}
    assert contract | {"type", "time_s", "skipped", "reason", "timings_ms"} <= set(msg), set(msg)
    back = trackio.step_from_message(msg)
    assert np.allclose(back.t, s.t) and np.allclose(back.q_wxyz, s.q_wxyz)
    assert np.allclose(back.v, s.v) and np.allclose(back.omega, s.omega) and np.allclose(back.covariance, s.covariance)
    assert trackio.csv_row(back) == trackio.csv_row(s)
    none = trackio.step_from_message(None, frame=9, time_s=0.3)
    assert (none.frame, none.status, none.t) == (9, "lost", None)


def test_the_written_covariance_is_exactly_symmetric():
    # the tracker's covariance is asymmetric by ~1e-17 (the filter's products): jsonl lines, the
    # WebSocket message and the ROS message carried it so, and `C == C.T` failed
    s = _step()
    s.covariance = s.covariance + np.triu(np.full((6, 6), 1e-17), 1)
    C = np.array(json.loads(trackio.jsonl_row(s))["covariance"])
    assert np.array_equal(C, C.T) and np.allclose(C, s.covariance, rtol=0, atol=1e-16)
    R = np.array(trackio.ros_pose_with_covariance(s, "m")["pose"]["covariance"]).reshape(6, 6)
    assert np.array_equal(R, R.T)


@pytest.mark.parametrize("unit, mm", [("mm", 1.0), ("cm", 10.0), ("m", 1000.0)])
def test_bop_row_round_trip(unit, mm):
    s = _step(seed=5)
    line = trackio.bop_row(s, unit, obj_id=7, scene_id=2)
    parts = line.split(",")
    assert len(parts) == len(trackio.BOP_COLUMNS)
    assert parts[:4] == ["2", "3", "7", "42"] and parts[6] == "0.012500"
    R = np.array([float(x) for x in parts[4].split()]).reshape(3, 3)
    assert np.allclose(R, quat.to_matrix(s.q_wxyz), atol=1e-8)  # row-major
    assert np.allclose([float(x) for x in parts[5].split()], s.t * mm)  # millimetres
    back = trackio.pose_from_bop(line, unit)
    assert back.allclose(Pose(s.q_wxyz, s.t), atol=1e-7)
    assert trackio.bop_row(TrackStep(frame=1, time_s=0.0, status="lost"), unit) is None


@pytest.mark.parametrize("unit", ["mm", "cm", "m"])
def test_ros_message_round_trip(unit):
    s = _step(seed=6)
    s.time_s = 12.25
    msg = trackio.ros_pose_with_covariance(s, unit, frame_id="cam")
    o = msg["pose"]["pose"]["orientation"]
    assert [o["x"], o["y"], o["z"], o["w"]] == pytest.approx([*s.q_wxyz[1:], s.q_wxyz[0]])  # ROS order x,y,z,w
    assert msg["header"] == {"stamp": {"sec": 12, "nanosec": 250_000_000}, "frame_id": "cam"}
    k = trackio.UNIT_METRES[unit]
    assert msg["pose"]["pose"]["position"]["z"] == pytest.approx(s.t[2] * k)
    cov = np.array(msg["pose"]["covariance"]).reshape(6, 6)
    assert cov[0, 1] == pytest.approx(s.covariance[0, 1] * k * k) and cov[3, 4] == pytest.approx(s.covariance[3, 4])
    assert cov[0, 4] == pytest.approx(s.covariance[0, 4] * k)  # row-major, position rows scaled once
    pose, cov_back = trackio.pose_from_ros(json.loads(json.dumps(msg)), unit)
    assert pose.allclose(Pose(s.q_wxyz, s.t), atol=1e-9) and np.allclose(cov_back, s.covariance)


def test_a_ros_stamp_whose_fraction_rounds_to_a_second_carries_into_sec():
    # 2.9999999997 s: the fraction rounds to 10⁹ ns, which was wrapped to 0 with sec kept at 2 —
    # the frame stamped a second early, before the frame that came before it
    stamps = []
    for t in (2.9999999990, 2.9999999997, 3.0000000004):
        s = _step(seed=6)
        s.time_s = t
        st = trackio.ros_pose_with_covariance(s, "m")["header"]["stamp"]
        assert 0 <= st["nanosec"] < 1_000_000_000
        stamps.append((st["sec"], st["nanosec"]))
    assert stamps == [(2, 999_999_999), (3, 0), (3, 0)]
    assert stamps == sorted(stamps)


@pytest.mark.parametrize("unit", ["mm", "cm", "m"])
def test_one_step_in_every_format_holds_the_same_numbers(unit):
    # the CSV rounded to 6 significant digits (a pose at 12 m in a mesh in metres: 10 µm off;
    # the quaternion ~1e-6) and BOP to 9: the same run's files disagreed with its JSON lines
    import csv

    s = _step(seed=11)
    s.t = np.array([1.2345678912345, -0.00012345678912, 12.345678912345])  # metres, say
    msg = json.loads(trackio.jsonl_row(s))
    f = io.StringIO()
    w = trackio.RowWriter(f, "csv")
    w.write(s)
    w.write(TrackStep(frame=4, time_s=0.5, status="lost", inliers=2))
    rows = list(csv.DictReader(io.StringIO(f.getvalue())))
    assert [float(rows[0][c]) for c in ("tx", "ty", "tz")] == msg["pose"]["t"] == list(s.t)
    assert [float(rows[0][c]) for c in ("qw", "qx", "qy", "qz")] == msg["pose"]["q_wxyz"]
    assert [float(rows[0][c]) for c in ("vx", "vy", "vz")] == msg["velocity"]["v"]
    assert [float(rows[0][c]) for c in ("wx", "wy", "wz")] == msg["velocity"]["omega"]
    assert rows[1]["status"] == "lost" and all(rows[1][c] == "" for c in trackio.CSV_COLUMNS[3:16])
    k_mm, k_m = trackio.UNIT_METRES[unit] / 1e-3, trackio.UNIT_METRES[unit]
    bop = dict(zip(trackio.BOP_COLUMNS, trackio.bop_row(s, unit).split(",")))
    assert [float(x) for x in bop["t"].split()] == [x * k_mm for x in msg["pose"]["t"]]  # exactly × the factor
    assert [float(x) for x in bop["R"].split()] == list(quat.to_matrix(np.array(msg["pose"]["q_wxyz"])).ravel())
    ros = trackio.ros_pose_with_covariance(msg, unit)["pose"]["pose"]
    assert [ros["position"][a] for a in "xyz"] == [x * k_m for x in msg["pose"]["t"]]
    assert [ros["orientation"][a] for a in "wxyz"] == msg["pose"]["q_wxyz"]


def test_row_writer_formats():
    f = io.StringIO()
    w = trackio.RowWriter(f, "csv")
    w.write(_step())
    w.write(TrackStep(frame=4, time_s=0.1, status="lost"))
    assert f.getvalue().splitlines()[0] == trackio.CSV_HEADER and len(f.getvalue().splitlines()) == 3
    f = io.StringIO()
    w = trackio.RowWriter(f, "bop", mesh_unit="cm")
    w.write(TrackStep(frame=4, time_s=0.1, status="lost"))
    w.write(_step())
    assert f.getvalue().splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time" and len(f.getvalue().splitlines()) == 2
    with pytest.raises(ValueError, match="--mesh-unit"):
        trackio.RowWriter(io.StringIO(), "bop")


# --- files and progress --------------------------------------------------------------------------

def test_atomic_path_renames_only_on_success(tmp_path):
    target = tmp_path / "out.csv"
    with trackio.atomic_path(target) as tmp:
        open(tmp, "w").write("a\n")
        assert not target.exists() and os.path.dirname(tmp) == str(tmp_path)
    assert target.read_text() == "a\n"
    with pytest.raises(RuntimeError):
        with trackio.atomic_path(target) as tmp:
            open(tmp, "w").write("half")
            raise RuntimeError("boom")
    assert target.read_text() == "a\n" and sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]
    with pytest.raises(trackio.SourceError, match="does not exist"):
        with trackio.atomic_path(tmp_path / "nowhere" / "x.csv"):
            pass
    for name in ("", str(tmp_path / "new") + os.sep):  # (failed at the rename, after the whole run)
        with pytest.raises(trackio.SourceError, match="give a file name"):
            with trackio.atomic_path(name, "--out"):
                pass


def test_atomic_path_in_a_folder_that_cannot_be_written_names_the_option(tmp_path, monkeypatch):
    # a read-only folder: "[Errno 13] Permission denied: '/ro/.x.csv.0nlka4m6.csv'" named the
    # temporary file; the message now names the option, the target and the folder
    import tempfile

    def refuse(**kw):
        raise PermissionError(13, "Permission denied", os.path.join(kw["dir"], ".x.csv.0nlka4m6.csv"))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(trackio.SourceError) as err:
        with trackio.atomic_path(tmp_path / "x.csv", "--out"):
            pass
    assert str(err.value) == f"--out {tmp_path / 'x.csv'}: cannot write in {tmp_path} (Permission denied)"


def test_atomic_path_writes_a_device_or_fifo_in_place(tmp_path):
    # `track --out /dev/null` (only the overlay wanted) replaced /dev/null with a regular file
    # when run as root: the rename of the temporary file went onto the device
    import stat

    fifo = tmp_path / "poses.fifo"
    os.mkfifo(fifo)
    with trackio.atomic_path(fifo, "--out") as tmp:
        assert tmp == str(fifo)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and sorted(p.name for p in tmp_path.iterdir()) == ["poses.fifo"]


def test_progress_line_only_on_a_terminal():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    clock = iter(np.arange(0.0, 10.0, 0.5))
    out = Tty()
    p = trackio.Progress("tracking", stream=out, clock=lambda: float(next(clock)))
    for s in ("init", "tracking", "lost"):
        p.update(s)
    p.close()
    assert "tracking: 3 frames" in out.getvalue() and "init 1, tracking 1, lost 1" in out.getvalue()
    pipe = io.StringIO()
    q = trackio.Progress("tracking", stream=pipe)
    q.update("init")
    q.close()
    assert pipe.getvalue() == ""


# --- the overlay ---------------------------------------------------------------------------------

def test_the_label_is_readable_text_on_an_opaque_box():
    """The label drawn over a busy image must be exactly the same pixels as the text drawn once
    on a black canvas (no outline of another width smearing the glyphs), and cover all of it."""
    text = "#123 4.10s tracking inliers 187 14 ms"
    rng = np.random.default_rng(0)
    busy = rng.integers(0, 256, (80, 640, 3), dtype=np.uint8)
    x0, y0, x1, y1 = draw_label(busy, text, (8, 8), colour=(60, 200, 60))
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.6
    (w, h), base = cv2.getTextSize(text, font, scale, 1)
    assert x1 - x0 >= w and y1 - y0 >= h + base
    ref = np.zeros((y1 - y0, x1 - x0, 3), np.uint8)
    pad = max(2, round(4 * scale))
    cv2.putText(ref, text, (pad, pad + h), font, scale, (60, 200, 60), 1, cv2.LINE_AA)
    crop = busy[y0:y1, x0:x1]
    assert np.array_equal(crop, ref)
    ink = ref.any(axis=2)
    assert ink.sum() > 300 and not ink[0].any() and not ink[-1].any() and not ink[:, 0].any() and not ink[:, -1].any()


def test_overlay_draws_the_wireframe_where_the_pose_projects():
    cam = PinholeCamera(fx=500, fy=500, cx=160, cy=120, width=320, height=240)
    edges = np.array([[[0, 0, 0], [4, 0, 0]], [[4, 0, 0], [4, 3, 0]]], float)
    s = TrackStep(frame=0, time_s=0.0, status="tracking", t=np.array([-2.0, 0.0, 50.0]), q_wxyz=quat.IDENTITY.copy())
    img = draw_overlay(np.zeros((240, 320, 3), np.uint8), cam, None, s, edges)
    u, v = cam.project(np.array([[2.0, 0.0, 50.0], [2.0, 1.5, 50.0]])).T
    green = (img[..., 1] > 150) & (img[..., 2] < 120)
    assert green[int(round(v[0])) - 2:int(round(v[0])) + 3, int(round(u[0]))].any()  # middle of the first edge
    lost = draw_overlay(np.zeros((240, 320, 3), np.uint8), cam, None, TrackStep(frame=1, time_s=0.0, status="lost"), edges)
    assert not lost[40:].any()  # nothing but the label


def test_images_given_as_files_and_globs_keep_their_order_and_skip_what_cannot_be_read(tmp_path):
    """What a shell makes of an unquoted glob (a list of files), or several globs: each expanded
    and sorted, in the order given, each file once; an unreadable file is skipped with its index
    and time, and the frames after it keep theirs."""
    for k in (1, 2, 3):
        cv2.imwrite(str(tmp_path / f"a{k}.png"), np.full((40, 40, 3), k, np.uint8))
    (tmp_path / "b1.png").write_text("not an image")
    cv2.imwrite(str(tmp_path / "b2.png"), np.full((40, 40, 3), 9, np.uint8))
    src = trackio.open_frames(images=[str(tmp_path / "b*.png"), str(tmp_path / "a2.png"), str(tmp_path / "a*.png")],
                              fps=10)
    got = list(src)
    assert [i for i, _, _ in got] == [1, 2, 3, 4] and [t for _, t, _ in got] == [0.1, 0.2, 0.3, 0.4]
    assert [int(img[0, 0, 0]) for _, _, img in got] == [9, 2, 1, 3]  # b1 (skipped), b2, a2, then a1, a3
    assert [(i, t) for i, t, _ in src.skipped] == [(0, 0.0)] and "b1.png" in src.skipped[0][2]
    with pytest.raises(trackio.SourceError, match="no file matches"):
        trackio.open_frames(images=[str(tmp_path / "none*.png"), str(tmp_path / "nothing.png")])
    odd = tmp_path / "frame[1].png"  # a file the shell listed, whose name is also a glob pattern
    cv2.imwrite(str(odd), np.full((40, 40, 3), 7, np.uint8))
    assert [int(img[0, 0, 0]) for _, _, img in trackio.open_frames(images=[str(odd)])] == [7]


def test_the_overlay_draws_on_frames_of_any_depth_the_tracker_takes():
    # a 16-bit, float or BGRA frame (the tracker takes them) was OpenCV's "Assertion failed
    # img.depth() == CV_8U in function 'putText'"
    cam = PinholeCamera(500.0, 500.0, 319.5, 239.5, width=640, height=480)
    edges = np.array([[[-1.0, -1.0, 0.0], [1.0, 1.0, 0.0]]])
    step = TrackStep(0, 0.0, "tracking", t=np.array([0.0, 0.0, 10.0]), q_wxyz=np.array([1.0, 0.0, 0.0, 0.0]))
    ref = draw_overlay(np.zeros((480, 640, 3), np.uint8), cam, None, step, edges=edges)
    for frame in (np.zeros((480, 640, 3), np.uint16), np.zeros((480, 640, 3), np.float32),
                  np.zeros((480, 640, 4), np.uint8)):
        assert np.array_equal(draw_overlay(frame, cam, None, step, edges=edges), ref), frame.dtype
    assert draw_overlay(np.zeros((480, 640), np.uint8), cam, None, step, edges=edges).shape == (480, 640)


def test_the_covariance_rotation_block_is_about_the_camera_axes_as_documented():
    # independent of quatrack's rotation code (scipy): poses fitted to noisy projections scatter
    # as the reported covariance says for δθ with R_true = exp([δθ]×) R (camera axes: what the
    # contract and the ROS message say), not for the object-axes R_true = R exp([δθ]×)
    from scipy.spatial.transform import Rotation

    from quatrack.recognition.pose import refine

    rng = np.random.default_rng(0)
    cam = PinholeCamera(width=640, height=480, fx=600.0, fy=600.0, cx=320.0, cy=240.0)
    X = rng.uniform(-8, 8, size=(30, 3))
    R_true, t_true = Rotation.from_rotvec([0.9, -1.2, 0.5]), np.array([3.0, -2.0, 60.0])
    Xc = R_true.apply(X) + t_true
    uv0 = 600 * Xc[:, :2] / Xc[:, 2:] + [320, 240]
    x, y, z, w = R_true.as_quat()
    camera_axes, object_axes, reported = [], [], []
    for _ in range(400):
        p, q, cov = refine(cam, X, uv0 + rng.normal(0, 0.5, uv0.shape), t_true, np.array([w, x, y, z]))
        R_est = Rotation.from_quat([*q[1:], q[0]])
        camera_axes.append(np.r_[p - t_true, (R_est * R_true.inv()).as_rotvec()])
        object_axes.append(np.r_[p - t_true, (R_true.inv() * R_est).as_rotvec()])
        reported.append(cov)
    C = np.mean(reported, axis=0)
    sd = np.sqrt(np.diag(C))

    def off(errors):  # the largest difference, in units of the reported standard deviations
        return (np.abs(np.cov(np.array(errors).T) - C) / np.outer(sd, sd)).max()

    assert off(camera_axes) < 0.25 and off(object_axes) > 1.0, (off(camera_axes), off(object_axes))

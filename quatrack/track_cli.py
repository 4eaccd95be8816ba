"""``quatrack track``: a video (or an image sequence) → one pose row per frame in a CSV.

Every output (CSV, overlay video, plot) is written to a temporary file next to its target and
renamed into place only when the whole input has been processed, so an error never leaves a
half-written file behind.
"""

from __future__ import annotations

import argparse
import csv
import glob
import json
import os
import sys
import tempfile
from contextlib import ExitStack
from typing import Iterator

import numpy as np

CSV_COLUMNS = ["frame", "time_s", "status", "tx", "ty", "tz", "qw", "qx", "qy", "qz",
               "vx", "vy", "vz", "wx", "wy", "wz", "inliers"]


class TrackInputError(ValueError):
    """Bad input to ``quatrack track``: reported in one line."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--video", metavar="FILE", help="a video file (anything OpenCV/FFmpeg reads)")
    src.add_argument("--images", metavar="GLOB", help="an image sequence, e.g. 'frames/*.png' (quote it; sorted by name)")
    parser.add_argument("--object", required=True, metavar="NAME", help="a trained object (see `quatrack models list`)")
    parser.add_argument("--camera", required=True, metavar="CAMERA", help="camera file of the frames (JSON, or OpenCV YAML)")
    parser.add_argument("--out", required=True, metavar="POSES.csv", help="output CSV, one row per frame")
    parser.add_argument("--store", metavar="DIR", help="model store (default: $QUATRACK_STORE or the user data directory)")
    parser.add_argument("--motion-model", default="ude", choices=["ude", "m1", "m2", "m3"],
                        help="ude: constant velocity on R³×S³ (default); m1/m2: object/camera random walk; "
                             "m3: linear constant velocity (Kragic & Kyrki)")
    parser.add_argument("--motion-noise", metavar="K=V,...", default="",
                        help="override the motion model's noise, e.g. a=2000,alpha=20 (ude) or sigma_p2=100,sigma_phi2=0.3")
    parser.add_argument("--init-pose", metavar="POSE.json",
                        help="start from this pose (object → camera: {rvec,tvec}, {R,t} or {q_wxyz,t}) instead of recognition")
    parser.add_argument("--fps", type=float, default=None, metavar="F",
                        help="frame rate for time_s (default: the video's own rate; 30 for images)")
    parser.add_argument("--overlay", metavar="OUT.mp4", help="also write the video with the wireframe, axes and status")
    parser.add_argument("--plot", metavar="OUT.png", help="also draw position and orientation with 3σ bands over time")
    parser.add_argument("--quiet", action="store_true", help="no summary on stdout")


def _noise(text: str) -> dict:
    out = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, sep, value = item.partition("=")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not np.isfinite(out.get(key.strip(), np.nan)) or out[key.strip()] < 0:
            raise TrackInputError(f"--motion-noise: expected KEY=VALUE with a finite value >= 0, got {item!r}")
    return out


def _load_init_pose(path: str):
    from quatrack.viewsets.spec import parse_pose

    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except OSError as exc:
        raise TrackInputError(f"--init-pose {path}: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise TrackInputError(f"--init-pose {path}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    if isinstance(data, dict) and isinstance(data.get("pose"), dict):
        data = data["pose"]
    return parse_pose(data, f"--init-pose {path}")


def _video_frames(path: str, fps: float | None) -> tuple[Iterator, float]:
    """Frames of a video and the rate used for time_s (per-frame timestamps from OpenCV are not
    reliable: with B-frames they come out of order, so time is frame index / rate)."""
    import cv2

    if not os.path.isfile(path):
        raise TrackInputError(f"--video {path}: no such file")
    cap = cv2.VideoCapture(path)
    if not cap.isOpened():
        raise TrackInputError(f"--video {path}: cannot be opened as a video")
    ok, first = cap.read()
    if not ok or first is None:
        cap.release()
        raise TrackInputError(f"--video {path}: no frame can be decoded")
    rate = fps or cap.get(cv2.CAP_PROP_FPS)
    if not rate or not np.isfinite(rate) or rate <= 0 or rate > 1000:
        rate = 30.0

    def gen():
        try:
            frame = first
            while frame is not None:
                yield frame
                ok, frame = cap.read()
                if not ok:
                    break
        finally:
            cap.release()

    return gen(), float(rate)


def _image_frames(pattern: str, fps: float | None) -> tuple[Iterator, float, list[str]]:
    from quatrack.recognition.images import read_image

    paths = sorted(p for p in glob.glob(os.path.expanduser(pattern)) if os.path.isfile(p))
    if not paths:
        raise TrackInputError(f"--images {pattern!r}: no file matches")
    return (read_image(p) for p in paths), float(fps or 30.0), paths


def _row(step) -> list:
    pose = step.t is not None
    fmt = lambda a: [f"{float(x):.6g}" for x in a] if pose else [""] * len(a)  # noqa: E731
    return ([step.frame, f"{step.time_s:.6f}", step.status] + fmt(step.t if pose else [0] * 3)
            + fmt(step.q_wxyz if pose else [0] * 4) + fmt(step.v if pose else [0] * 3)
            + fmt(step.omega if pose else [0] * 3) + [step.inliers])


def _temp_beside(target: str, suffix: str, stack: ExitStack) -> str:
    """A temporary path in the target's folder (so the final rename is atomic); removed on error."""
    folder = os.path.dirname(os.path.abspath(target))
    if not os.path.isdir(folder):
        raise TrackInputError(f"{target}: the folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(target)}.", suffix=suffix, dir=folder)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would survive the rename
    stack.callback(lambda: os.path.exists(tmp) and os.unlink(tmp))
    return tmp


def run(args: argparse.Namespace) -> int:
    import cv2

    from quatrack.recognition.images import to_bgr8
    from quatrack.recognition.match import index_for
    from quatrack.recognition.overlay import draw_overlay, plot_track
    from quatrack.recognition.video import Tracker, TrackerParams
    from quatrack.recognition.visibility import mesh_edges
    from quatrack.viewsets.camera import load_camera
    from quatrack.viewsets.store import load_model, resolve_store

    if args.fps is not None and not (np.isfinite(args.fps) and 0 < args.fps <= 1000):
        raise TrackInputError("--fps must be a positive number (at most 1000)")
    for opt, path, ext in (("--overlay", args.overlay, ".mp4"), ("--plot", args.plot, ".png")):
        if path and not path.lower().endswith(ext):
            raise TrackInputError(f"{opt} {path}: the file name must end in {ext}")
    params = TrackerParams(motion_model=args.motion_model, motion_noise=_noise(args.motion_noise))
    camera = load_camera(args.camera)
    init = _load_init_pose(args.init_pose) if args.init_pose else None
    model = load_model(resolve_store(args.store), args.object)
    if args.video:
        frames, rate = _video_frames(args.video, args.fps)
        names = None
    else:
        frames, rate, names = _image_frames(args.images, args.fps)

    tracker = Tracker(model, camera, params, index=index_for(model))
    if init is not None:
        from quatrack.tracking import quaternion as quat

        tracker.init_pose(init.t, quat.from_matrix(init.R), 0.0)
    edges = mesh_edges(model.mesh)
    steps = []
    with ExitStack() as stack:
        tmp_csv = _temp_beside(args.out, ".csv", stack)
        writer_video = None
        tmp_video = _temp_beside(args.overlay, ".mp4", stack) if args.overlay else None
        with open(tmp_csv, "w", newline="", encoding="utf-8") as f:
            out = csv.writer(f)
            out.writerow(CSV_COLUMNS)
            for i, image in enumerate(frames):
                try:
                    step = tracker.step(image, i / rate)
                except ValueError as exc:
                    where = names[i] if names else f"frame {i} of {args.video}"
                    raise TrackInputError(f"{where}: {exc}") from None
                out.writerow(_row(step))
                steps.append(step)
                if tmp_video:
                    if writer_video is None:
                        h, w = image.shape[:2]
                        writer_video = cv2.VideoWriter(tmp_video, cv2.VideoWriter_fourcc(*"mp4v"), rate, (w, h))
                        if not writer_video.isOpened():
                            raise TrackInputError(f"--overlay {args.overlay}: cannot write an MP4 video here")
                        stack.callback(writer_video.release)
                    writer_video.write(draw_overlay(to_bgr8(image), camera, model.mesh, step, edges))
        if writer_video is not None:
            writer_video.release()
        if args.plot:
            tmp_png = _temp_beside(args.plot, ".png", stack)
            if not cv2.imwrite(tmp_png, plot_track(steps)):
                raise TrackInputError(f"--plot {args.plot}: cannot write the PNG")
            os.replace(tmp_png, args.plot)
        if tmp_video:
            os.replace(tmp_video, args.overlay)
        os.replace(tmp_csv, args.out)
    if not args.quiet:
        _summary(steps, args.out)
    return 0


def _summary(steps, out: str) -> None:
    counts = {s: sum(1 for x in steps if x.status == s) for s in ("init", "tracking", "lost")}
    first = next((i for i, s in enumerate(steps) if s.status != "lost"), None)
    after = steps[first:] if first is not None else []
    share = 100.0 * sum(1 for s in after if s.status != "lost") / len(after) if after else 0.0
    track_ms = [s.timings_ms.get("total", 0.0) for s in steps if s.status == "tracking"]
    p50 = f"{np.percentile(track_ms, 50):.1f}" if track_ms else "-"
    print(f"tracked {len(steps)} frames -> {out}")
    print(f"  init {counts['init']}, tracking {counts['tracking']}, lost {counts['lost']}; "
          f"pose in {share:.1f} % of frames after the first init; step p50 {p50} ms")
    sys.stdout.flush()

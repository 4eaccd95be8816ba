"""``quatrack track``: a video, an image sequence, a camera or a stream → one pose row per frame.

The steps are plain functions: :func:`_setup` checks the options and builds the tracker,
:func:`_track_frames` runs it over the frames (writing rows, overlay frames and the progress
line as it goes), :func:`_summary` reports. Frame sources, rows, the overlay and atomic writes
come from :mod:`recognition.trackio` and :mod:`recognition.overlay`, shared with ``demo`` and
the client. Every output (poses, overlay video, plot) is written to a temporary file next to its
target and renamed into place only when the run ends — normally, at ``--max-frames`` or on Ctrl-C
(which stops a live source cleanly) — so an error never leaves a half-written file behind. An
image of a sequence that cannot be read does not end the run: its row says ``lost``
(:meth:`Tracker.skip <quatrack.recognition.tracker.machine.Tracker.skip>`), stderr names it,
and the track goes on with the next frame (one bad file in ten thousand costs one row, not the run).

``--learn`` (issue 12): the tracker keeps views of the sides the training photos never showed
(:mod:`quatrack.viewsets.learn`); when the run ends normally or by Ctrl-C they are merged into the
stored model, atomically and under the store's lock (:func:`~quatrack.viewsets.learn.merge_learned`),
and one line says how many and where. A run that ends in an error stores nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from contextlib import ExitStack
from dataclasses import dataclass

import numpy as np

from quatrack.cli import UserError  # one line, exit status 2
from quatrack.recognition.trackio import FORMATS, UNIT_METRES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--video", metavar="SOURCE",
                     help="a video file (anything OpenCV/FFmpeg reads), a camera index such as 0 or device "
                          "such as /dev/video0, a FIFO, or a stream URL (rtsp://, http://, ...)")
    src.add_argument("--images", metavar="GLOB", nargs="+",
                     help="an image sequence, e.g. 'frames/*.png' (sorted by name), or several globs or files "
                          "(an unquoted glob: each expanded and sorted, in the order given), or a list file "
                          "(.txt, .lst: one image a line); an image that cannot be read is skipped: its row says lost")
    parser.add_argument("--object", required=True, metavar="NAME", help="a trained object (see `quatrack models list`)")
    parser.add_argument("--camera", required=True, metavar="CAMERA", help="camera file of the frames (JSON, or OpenCV YAML)")
    parser.add_argument("--out", required=True, metavar="POSES",
                        help="output file, one row per frame (see --format); - for stdout (the summary then goes "
                             "to stderr, as for /dev/stdout or a FIFO)")
    parser.add_argument("--format", default="csv", choices=FORMATS,
                        help="csv: the contract's columns (default); jsonl: one JSON message per frame (pose, "
                             "velocity, covariance); bop: BOP results (scene_id,im_id,obj_id,score,R,t,time; t in mm)")
    parser.add_argument("--mesh-unit", choices=sorted(UNIT_METRES), default=None,
                        help="the unit of the object's mesh; needed by --format bop (BOP's t is in mm); "
                             "csv and jsonl stay in the mesh's units")
    parser.add_argument("--obj-id", type=int, default=1, metavar="N", help="BOP obj_id (default 1)")
    parser.add_argument("--store", metavar="DIR", help="model store (default: $QUATRACK_STORE or the user data directory)")
    parser.add_argument("--motion-model", default="ude", choices=["ude", "m1", "m2", "m3"],
                        help="ude: constant velocity on R³×S³ (default); m1/m2: object/camera random walk; "
                             "m3: linear constant velocity (Kragic & Kyrki)")
    parser.add_argument("--motion-noise", metavar="K=V,...", default="",
                        help="override the motion model's noise, e.g. a=2000,alpha=20 (ude) or sigma_p2=100,sigma_phi2=0.3 (m1, m2, m3)")
    parser.add_argument("--init-pose", metavar="POSE.json",
                        help="start from this pose (object → camera: {rvec,tvec}, {R,t} or {q_wxyz,t}) instead of recognition")
    parser.add_argument("--fps", type=float, default=None, metavar="F",
                        help="frame rate for time_s (default: the video's own rate; 30 for images; "
                             "the clock for a camera or stream)")
    parser.add_argument("--stall-timeout", type=float, default=None, metavar="S",
                        help="a camera or stream that gives no frame for S seconds has stalled: the run ends "
                             "there, saying so, with complete outputs (default 30; also the wait for a stream "
                             "to answer when opened)")
    parser.add_argument("--max-frames", type=int, default=None, metavar="N",
                        help="stop after N frames (Ctrl-C also stops cleanly, with complete outputs)")
    parser.add_argument("--overlay", metavar="OUT.mp4", help="also write the video with the wireframe, axes and status")
    parser.add_argument("--plot", metavar="OUT.png", help="also draw position and orientation with 3σ bands over time")
    parser.add_argument("--learn", action="store_true",
                        help="learn views of the sides the training photos do not show while tracking confidently, "
                             "and add them to the stored model at the end (also after Ctrl-C), so that recognition "
                             "finds the object from those sides too")
    parser.add_argument("--relocate-every", type=float, default=None, metavar="S",
                        help="while the object is lost, search for it at most once per S seconds of the frames' "
                             "time (default: every frame); a failed search costs 0.1-0.6 s of CPU, so on a live "
                             "camera this keeps the other frames flowing")
    parser.add_argument("--quiet", action="store_true", help="no summary on stdout, no progress line")


def _noise(text: str, motion_model: str = "ude") -> dict:
    """``--motion-noise``'s ``K=V,...``: finite values from 0 to
    :data:`~quatrack.recognition.tracker.params.MAX_MOTION_NOISE` (``a=1e300`` passed, and numpy's
    "overflow encountered in multiply" came out twice)."""
    from quatrack.recognition.tracker.params import MAX_MOTION_NOISE, noise_defaults

    out = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, sep, value = item.partition("=")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not np.isfinite(out.get(key.strip(), np.nan)) or out[key.strip()] < 0:
            raise UserError(f"--motion-noise: expected KEY=VALUE with a finite value >= 0, got {item!r}")
        if out[key.strip()] > MAX_MOTION_NOISE:
            raise UserError(f"--motion-noise: {item!r} is too large: give a value from 0 to {MAX_MOTION_NOISE:g} "
                            f"(in the mesh's units; {noise_defaults(motion_model)})")
    return out


def _load_init_pose(path: str):
    from quatrack.viewsets.spec import parse_pose

    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except OSError as exc:
        raise UserError(f"--init-pose {path}: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise UserError(f"--init-pose {path}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    except RecursionError:
        raise UserError(f"--init-pose {path}: not valid JSON (nested too deeply)") from None
    if isinstance(data, dict) and isinstance(data.get("pose"), dict):
        data = data["pose"]
    # (as a spec's poses are read: a quaternion not of length 1 is normalised and said so, an R that is
    # no rotation refused; the quaternion was normalised in silence while a scaled R was refused)
    return parse_pose(data, f"--init-pose {path}",
                      warn=lambda message: print(f"quatrack track: warning: {message}", file=sys.stderr))


#: ``--out -``: the rows on stdout (it wrote a file named "-")
STDOUT = "-"

JOIN_TIMEOUT_S = 10.0  # the longest wait at the end for the run's threads (_join_started)


@dataclass
class _Setup:
    """Everything a run needs, checked before any output is opened."""

    model: object
    camera: object
    tracker: object
    source: object
    store: object = None
    init_pose: str | None = None  # --init-pose's file, when its pose waits for the first frame
    init: object = None  # and its pose (the edges are measured there if the tracker refuses it)


def _check_outputs(args: argparse.Namespace) -> None:
    """No output on an input, on another output or on a folder (:func:`~quatrack.recognition.trackio.check_outputs`)."""
    from quatrack.recognition.trackio import check_outputs, image_paths

    inputs = [("--video", args.video)] if args.video else []
    inputs += [("--camera", args.camera), ("--init-pose", args.init_pose)]  # (--out on either replaced it)
    # (the files open_frames reads: a quoted '~/frames/*.png' matched nothing here, and --out overwrote a frame)
    inputs += [("--images", f) for f in image_paths(args.images or [])]
    inputs += [("--images", f) for f in args.images or []]  # (a list file: --out frames.txt replaced the list)
    out = None if args.out == STDOUT else args.out
    check_outputs(inputs, [("--out", out), ("--overlay", args.overlay), ("--plot", args.plot)])


def _setup(args: argparse.Namespace) -> _Setup:
    from quatrack.recognition.match import index_for
    from quatrack.recognition.trackio import open_frames
    from quatrack.recognition.video import Tracker, TrackerParams
    from quatrack.viewsets.camera import load_camera
    from quatrack.viewsets.store import load_model, resolve_store

    for opt, path, ext in (("--overlay", args.overlay, ".mp4"), ("--plot", args.plot, ".png")):
        if path and not path.lower().endswith(ext):
            raise UserError(f"{opt} {path}: the file name must end in {ext}")
    _check_outputs(args)
    if args.format == "bop" and args.mesh_unit is None:
        raise UserError("--format bop needs --mesh-unit (mm, cm or m): BOP's t is in millimetres")
    if args.obj_id < 0:  # (written as given: a BOP file no evaluation reads)
        raise UserError(f"--obj-id {args.obj_id}: BOP object ids are whole numbers from 0 (the datasets' start at 1)")
    relocate = getattr(args, "relocate_every", None)
    if relocate is not None and not (np.isfinite(relocate) and relocate > 0):
        raise UserError(f"--relocate-every {relocate:g}: give a number of seconds above 0")
    params = TrackerParams(motion_model=args.motion_model, motion_noise=_noise(args.motion_noise, args.motion_model),
                           learn=bool(getattr(args, "learn", False)), relocate_interval_s=relocate)
    camera = load_camera(args.camera)
    init = _load_init_pose(args.init_pose) if args.init_pose else None
    store = resolve_store(args.store)
    model = load_model(store, args.object)
    if params.learn:  # (a store that cannot take the views: said now, not after the whole walk)
        from quatrack.viewsets.learn import check_can_store
        check_can_store(store, args.object)
    source = open_frames(args.video, args.images, args.fps, args.max_frames, getattr(args, "stall_timeout", None))
    tracker = Tracker(model, camera, params, index=index_for(model))
    if init is not None:
        from quatrack.tracking import quaternion as quat

        tracker.init_pose(init.t, quat.from_matrix(init.R), 0.0)
    return _Setup(model, camera, tracker, source, store, args.init_pose if init is not None else None, init)


def _track_frames(s: _Setup, rows, video, progress, steps: list | None = None) -> tuple[list, bool]:
    """Step the tracker over every frame; returns the steps (``steps``, filled as they come:
    the caller counts them when a write fails) and whether Ctrl-C stopped it."""
    from quatrack.recognition.images import to_bgr8
    from quatrack.recognition.overlay import draw_overlay
    from quatrack.recognition.visibility import mesh_edges

    edges = mesh_edges(s.model.mesh)
    steps = [] if steps is None else steps
    last = None  # the overlay's latest frame read: an unreadable one's shows it again, marked lost
    if video is not None and s.camera.width and s.camera.height:  # (before any: a black frame, so that
        last = np.zeros((s.camera.height, s.camera.width, 3), np.uint8)  # overlay frame k stays row k)

    def emit(step, image) -> None:
        rows.write(step)
        steps.append(step)
        progress.update(step.status)
        if video is not None and image is not None:  # (a live source's by its time: VideoOut's timed)
            video.write(draw_overlay(image, s.camera, s.model.mesh, step, edges), step.time_s)

    done = 0  # the skipped frames written so far

    def skipped_until(index: int | None) -> None:
        """Rows for the frames the source skipped (unreadable) before frame ``index`` (None: all)."""
        nonlocal done
        bad = s.source.skipped
        while done < len(bad) and (index is None or bad[done][0] < index):
            _, t, why = bad[done]
            done += 1
            emit(s.tracker.skip(t, f"the frame cannot be read: {why}"), last)

    from quatrack.recognition.images import ImageError

    stepped = False  # a frame of the sequence fitted the camera
    try:
        for i, t, image in s.source:
            skipped_until(i)
            if not stepped and (fit := _camera_resized(s, image)) is not None:
                s = fit  # (the overlay draws with it too: emit reads s)
            try:
                step = s.tracker.step(image, t)
            except ImageError as exc:
                why = _cli_hint(exc)
                if not stepped:  # (the camera wrong for the first frame already)
                    raise UserError(f"{s.source.where(i)}: {why}") from None
                # one image of another size among thousands (a stray thumbnail), or a video frame (a stream
                # changing resolution mid-run), ended the run with nothing written: it is skipped as an
                # unreadable one is
                s.source.skipped.append((i, t, f"{s.source.where(i)}: {why}"))
                skipped_until(i + 1)
                continue
            except ValueError as exc:
                raise UserError(f"{s.source.where(i)}: {exc}") from None
            if not stepped and s.init_pose is not None and step.status == "lost":
                progress.close()  # (its line cleared: the warning gets a line of its own)
                _refused_pose(s.init_pose, step.frame, step.reason, _edges_at(s, image))
            stepped = True
            last = to_bgr8(image) if video is not None else None
            emit(step, last)
        skipped_until(None)
    except KeyboardInterrupt:
        _defer_interrupts()  # (first: the source's release below may take 0.5 s)
        return steps, True
    finally:
        s.source.close()
    return steps, False


def _cli_hint(exc) -> str:
    """``exc`` (an :class:`~quatrack.recognition.images.ImageError`) in the command line's words:
    a frame of another size that is the camera's images resized gets, in place of the library's
    remedy for a Python call (``pass camera.scaled(0.5, 320, 240)``,
    :class:`~quatrack.recognition.images.ImageSizeError`'s ``hint``), the command line's: the
    run's camera fits its first frame, so every frame must have that size."""
    from quatrack.recognition.images import ImageSizeError

    if not isinstance(exc, ImageSizeError) or not exc.hint or None in (exc.camera_size or (None,)):
        return str(exc)
    (cw, ch), (w, h) = exc.camera_size, exc.image_size
    return (exc.base + f" (resized by {w / cw:.3g}? the frames of one run must all be {cw}×{ch} px: resize it, "
            f"or track the {w}×{h} px frames in a run of their own, with a camera file for that size)")


def _camera_resized(s: _Setup, image) -> _Setup | None:
    """The setup with its camera scaled to the first frame when the frames are the camera's
    images resized (:func:`~quatrack.viewsets.camera.resized_for`), said once on stderr; None
    when the camera fits as it is (or not at all: the tracker refuses it, as before). Refused
    (:class:`UserError`) when the camera's own numbers show its stated size is the wrong one
    (:func:`~quatrack.viewsets.camera.stated_size_doubt`), as ``locate`` refuses it."""
    from dataclasses import replace

    from quatrack.viewsets.camera import resized_for, stated_size_doubt

    shape = getattr(image, "shape", None)
    if shape is None or len(shape) < 2:
        return None
    w, h = int(shape[1]), int(shape[0])
    camera, note = resized_for(s.camera, w, h)
    if note is None:
        return None
    if (doubt := stated_size_doubt(s.camera, w, h)) is not None:  # (as locate's: scaled, the object "not found")
        raise UserError(f"--camera: {doubt} (it was not scaled to the frames)")
    sx, sy = w / s.camera.width, h / s.camera.height
    if f"{0.5 * (sx + sy):.3g}" == "1":  # (641×481 frames said "its intrinsics scaled by 1 (a resized video)")
        note = (f"the camera is for {s.camera.width}×{s.camera.height} px images and these are {w}×{h} px, a few "
                f"pixels apart: its intrinsics scaled by {sx:.5g} wide and {sy:.5g} tall; if the frames are padded "
                f"or cropped rather than resized, give a camera file for {w}×{h}")
    print(f"quatrack track: warning: {note}", file=sys.stderr)
    s.tracker.camera = camera  # (before its first step: nothing was computed for the old one)
    return replace(s, camera=camera)


def _edges_at(s: _Setup, image):
    """The model's edges' agreement with ``image`` (the first frame) at ``--init-pose``'s pose
    (:func:`~quatrack.recognition.evidence.edge_agreement`, recognition's edge parameters), or
    None when it cannot be measured (no pose, the object behind the camera)."""
    import cv2

    from quatrack.recognition.evidence import edge_agreement
    from quatrack.recognition.images import to_bgr8
    from quatrack.recognition.pose import PoseParams

    mesh = s.model.mesh
    if s.init is None or np.any(s.init.apply(mesh.vertices)[:, 2] <= 1e-9):
        return None
    try:  # (the grey frame and the camera the tracker judged: Tracker.step's)
        grey = cv2.cvtColor(to_bgr8(image), cv2.COLOR_BGR2GRAY)
        return edge_agreement(grey, mesh, s.tracker.camera, s.init, PoseParams().edges)
    except Exception:  # (a warning's evidence only: never the run's end)
        return None


def _refused_pose(path: str, frame: int, reason: str | None, edges=None) -> None:
    """Say once on stderr that the tracker refused ``--init-pose``'s pose at its first frame, and
    why: only ``--format jsonl`` rows carried the reason; the CSV said ``lost`` and recognition
    took over, so a pose given camera → object went unnoticed.

    The causes are named in the order the evidence gives them. ``edges`` (:func:`_edges_at`) is
    how the model's edges at the pose agree with the frame: well above chance
    (:func:`~quatrack.recognition.evidence.plausible_edges`) the pose is where the frame
    shows the object, and the refusal (typically "only 0 model points matched near the pose") is
    the texture not found there — a cluttered or differently lit background, blur, a weakly
    textured side — so no convention is suspected: the exact pose of a thin bar on grass (edges
    67 %, 45 % by chance) was asked whether it was camera → object or in other units (user
    report, finding 5). Otherwise, or unmeasured, both geometric causes are named: a pose merely
    10° off was once asked only whether it was given camera → object, and a box turned 40° still
    agrees 51 % vs 36 % by chance (too little to be called plausible)."""
    from quatrack.recognition.evidence import plausible_edges
    from quatrack.recognition.pose import PoseParams, edges_agree

    why = (reason or "no reason given").removeprefix("given pose refused: ").removeprefix("given pose: ")
    head = f"quatrack track: warning: --init-pose {path}: the pose was refused at frame {frame}"
    near = (f"within about {INIT_POSE_DEG:g}° and a few % of the object's size, on a side no photo shows")
    p = PoseParams()
    if edges is not None and edges.samples >= p.min_edge_samples and plausible_edges(edges):
        seen = f"the model's edges at the pose lie on the frame's for {edges.agreement:.0%} ({edges.chance:.0%} by chance)"
        if "model points matched" not in why:  # (the points found disagree: the texture, not the pose, is suspect)
            causes = f"{seen}, well above chance, so the pose is plausible: most likely the points matched near it misled"
        elif edges_agree(edges, p):
            causes = (f"{seen}: they confirm the pose, but too little of the object's texture was found near it (the "
                      f"sides it shows weakly textured, the frame blurred or lit otherwise than the photos)")
        else:
            causes = (f"{seen}, well above chance, so the pose is plausible: most likely the frame's texture was not "
                      f"matched near it (a cluttered or differently lit background, blur, a weakly textured side), and "
                      f"the background's clutter leaves the edges too close to chance to start on them alone "
                      f"({p.min_edge_lead:.0%} above chance needed)")
        print(f"{head} ({why}); the object is searched for by recognition instead. {causes[0].upper()}{causes[1:]}; "
              f"less likely, the pose is a little off (it must be {near})", file=sys.stderr)
        return
    seen = ""
    if edges is not None and edges.samples >= p.min_edge_samples:
        seen = (f"; the model's edges at the pose lie on the frame's for {edges.agreement:.0%} ({edges.chance:.0%} "
                f"by chance), too close to chance to confirm it")
    print(f"{head} ({why}); the object is searched for by recognition instead (either the pose is too far from "
          f"where the frame shows the object (it must be {near}), or it is in another convention (camera → object "
          f"instead of object → camera, or not in the mesh's units)){seen}", file=sys.stderr)


#: how close an ``--init-pose`` must be to the object's pose in its first frame, as a trial measured it
#: on a side no training photo shows (the tracker starts there on corners born on the mesh at the given
#: pose, confirmed by its edges): about 5° and a few % of the object's size (README)
INIT_POSE_DEG = 5.0


@dataclass
class _Stop:
    """What stopped the tracking loop early: ``"Ctrl-C"`` unless a signal handler says otherwise."""

    cause: str = "Ctrl-C"


@contextlib.contextmanager
def _terminate_as_interrupt():
    """SIGTERM (``timeout``, ``docker stop``, systemd) ends the tracking loop as Ctrl-C does:
    outputs complete, learned views stored. Without it the process died at once, the views
    were lost and a temporary output file was left beside the output. Yields a :class:`_Stop`
    whose ``cause`` becomes ``"SIGTERM"`` when that signal stopped the run (the closing line
    said "stopped (Ctrl-C)" for a ``docker stop`` as well). Only in the main thread (signal
    handlers cannot be set elsewhere); the previous handler comes back afterwards."""
    import signal
    import threading

    stop = _Stop()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def terminated(signum, frame):
        stop.cause = signal.Signals(signum).name
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, terminated)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _interrupts_put_back(ignored_in_the_program: bool = False):
    """Around a run that may defer Ctrl-C (:func:`_defer_interrupts`): afterwards the previous
    SIGINT handler comes back — or, with ``ignored_in_the_program`` in the ``quatrack`` process
    itself (:func:`_is_the_program`), Ctrl-C stays ignored to the end (the interpreter's exit puts
    a Python handler back to the default, killing; SIG_IGN it keeps). Only in the main thread."""
    import signal
    import threading

    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGINT) if main else None
    try:
        yield
    finally:
        if main and signal.getsignal(signal.SIGINT) is not previous:  # (_defer_interrupts' handler)
            keep = ignored_in_the_program and _is_the_program()
            signal.signal(signal.SIGINT, signal.SIG_IGN if keep else previous)


def run(args: argparse.Namespace) -> int:
    """:func:`_run`, then a wait for the threads it started (:func:`_join_started`), on every path."""
    import threading

    before = set(threading.enumerate())
    with _interrupts_put_back(ignored_in_the_program=True):
        try:
            return _run(args)
        finally:
            _join_started(before)


def _is_the_program() -> bool:
    """Whether this process is the ``quatrack`` command (``python -m quatrack`` or the script),
    not a program calling :func:`quatrack.cli.main`: then Ctrl-C stays ignored after an
    interrupted run until the process exits (put back, a Ctrl-C in the last milliseconds — the
    summary, the interpreter's exit — killed the process by the signal after the outputs were
    complete, instead of exit 0)."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    return getattr(spec, "name", None) == "quatrack.__main__" or os.path.basename(sys.argv[0]) == "quatrack"


def _defer_interrupts(command: str = "track") -> None:
    """From the Ctrl-C (or SIGTERM) that stopped the tracking on, another Ctrl-C is said once and
    otherwise ignored, so the outputs are finished: a second Ctrl-C 10-20 ms after the first lost
    every output (exit 130, "interrupted"); a little later the process died by the signal. Ctrl-\\
    (SIGQUIT) still quits at once. Only in the main thread, as :func:`_terminate_as_interrupt`."""
    import os
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    said = []

    def again(signum, frame) -> None:
        if not said:  # (os.write: a print here may land inside one of the main thread's, and raise)
            said.append(signum)
            os.write(2, f"quatrack {command}: finishing the outputs; Ctrl-C again is ignored until they are "
                        f"complete (Ctrl-\\ quits without them)\n".encode())

    signal.signal(signal.SIGINT, again)


def _join_started(before: set, timeout_s: float = JOIN_TIMEOUT_S) -> None:
    """Wait (at most ``timeout_s`` in all, a live capture's thread 1 s) for the daemon threads
    started since ``before`` — a FLANN forest being built, a live capture's thread letting its
    stream go — to end. Why: a
    daemon thread still inside OpenCV when the interpreter shut down aborted the process as it
    came back ("terminate called without an active exception", exit 134 instead of 0 or 130):
    Ctrl-C during the first frame (the index still building), an RTSP URL that cannot be opened
    (its capture still being released). A second Ctrl-C stops the wait."""
    import os
    import threading
    import time

    from quatrack.recognition.trackio import CAPTURE_THREAD

    deadline = time.monotonic() + timeout_s
    try:
        for t in [t for t in threading.enumerate() if t not in before and t.daemon]:
            # (a live capture's thread blocked in a stalled stream's read may stay there 35 s: Ctrl-C
            # stops at once, so it gets a second to let go; the exit then ends it where it waits)
            until = min(deadline, time.monotonic() + 1.0) if t.name.startswith(CAPTURE_THREAD + " ") else deadline
            t.join(max(0.0, until - time.monotonic()))
            # (joined is not gone: the thread's native exit — OpenCV's per-thread data freed — still runs,
            # and the process exiting under it aborted as well; on Linux its task is seen going)
            task = f"/proc/self/task/{t.native_id}"
            while t.native_id and os.path.exists(task) and time.monotonic() < until:
                time.sleep(0.005)
    except KeyboardInterrupt:
        pass


def _run(args: argparse.Namespace) -> int:
    """:func:`_run_from`, SIGTERM an interrupt from the start: while the model loaded or a stream
    opened it killed the process silently (exit -15)."""
    with ExitStack() as term:
        stop = term.enter_context(_terminate_as_interrupt())
        return _run_from(args, term, stop)


def _run_from(args: argparse.Namespace, term: ExitStack, stop: "_Stop") -> int:
    """The run; SIGTERM is an interrupt (``stop``'s cause) until ``term`` is closed, as the
    tracking ends: from there on the outputs are finished under the previous handler, as before."""
    from quatrack.recognition.overlay import plot_track
    from quatrack.recognition.trackio import Progress, RowWriter, VideoOut, atomic_path, misordered, misordered_given

    s = _setup(args)
    if args.images and (pair := misordered(args.images)) is not None:
        print(f"quatrack track: warning: --images are read in order of name, so {pair[0]} comes before {pair[1]}: "
              f"number the files with leading zeros (0002 for 2), or give them in order", file=sys.stderr)
    elif args.images and (pair := misordered_given(args.images)) is not None:  # (a glob the shell expanded, a list)
        print(f"quatrack track: warning: --images are read in the order given, so {pair[0]} comes before {pair[1]}: "
              f"number the files with leading zeros (0002 for 2), or give them in order", file=sys.stderr)
    if args.mesh_unit is not None and args.format != "bop":  # (ignored in silence: a CSV read as metres was in mm)
        # (it said "in the mesh's own units (mm)", the user's --mesh-unit as if it were the mesh's: the
        # cookie box's mesh is in cm; the model does not know its unit, --mesh-unit only tells bop's t)
        print(f"quatrack track: warning: --mesh-unit is for --format bop only (it says what unit the mesh is in, "
              f"to give BOP's t in mm); the {args.format} output is in the mesh's own units, whatever they are, "
              f"unconverted", file=sys.stderr)
    if args.obj_id != 1 and args.format != "bop":  # (ignored in silence, as --mesh-unit was)
        print(f"quatrack track: warning: --obj-id is for --format bop only; the {args.format} output has no "
              f"object id", file=sys.stderr)
    progress = Progress("tracking", enabled=False if args.quiet else None)
    s.source.on_wait(progress.tick)  # (a stalled stream: "waiting for frames N s", not a frozen rate)
    steps: list = []
    tmp_out = None
    kept = args.out != STDOUT and os.path.isfile(args.out)  # (what a failed write leaves: _write_failed)
    try:
        with ExitStack() as stack:
            stack.callback(s.source.close)
            tmp_out = None if args.out == STDOUT else stack.enter_context(atomic_path(args.out, "--out"))
            video = None
            if args.overlay:
                video = VideoOut(stack.enter_context(atomic_path(args.overlay, "--overlay")), s.source.rate,
                                 timed=s.source.live, target=args.overlay)
            with _rows_file(tmp_out) as f:
                rows = RowWriter(f, args.format, args.mesh_unit, args.obj_id)
                try:
                    steps, interrupted = _track_frames(s, rows, video, progress, steps)
                finally:
                    term.close()
                    progress.close()
                    if video is not None:
                        video.close()
                if video is not None:
                    video.check()  # (a full disk: OpenCV's writer failed in silence)
                bad = s.source.skipped
                if bad and len(bad) == len(steps):  # (nothing written: the outputs are discarded)
                    raise UserError(f"{s.source.label}: no frame can be read ({bad[0][2]})")
            if args.plot:
                _write_plot(args.plot, plot_track(steps))
    except _WriteFailed as exc:  # (the temporary files are gone by now: atomic_path)
        raise UserError(_write_failed(args, exc, len(steps), kept, in_place=tmp_out in (None, args.out))) from None
    if interrupted:
        print(f"quatrack track: stopped ({stop.cause}) after {len(steps)} frames; {_written(args, video)}",
              file=sys.stderr)
    for note in video.notes() if video is not None else ():  # (an odd size padded, a rate MP4 cannot store)
        print(f"quatrack track: note: {note}", file=sys.stderr)
    for k, _, why in s.source.skipped[:5]:
        print(f"quatrack track: frame {k} cannot be read, written as lost: {why}", file=sys.stderr)
    if len(s.source.skipped) > 5:
        print(f"quatrack track: ... {len(s.source.skipped)} frames in all cannot be read", file=sys.stderr)
    if s.source.ended and not interrupted:  # (a stream that stalled or dropped ended the run with exit 0, not a word)
        print(f"quatrack track: {s.source.label}: {s.source.ended}; stopped after {len(steps)} frames; "
              f"{_written(args, video)}", file=sys.stderr)
    if s.tracker.params.learn:
        _store_learned(s, args.object)
    if not args.quiet:
        _summary(steps, args.out, _summary_stream(args.out))
    return 0


def _write_plot(path: str, image) -> None:
    """``--plot``'s PNG, encoded here and written by Python, so that a failure names its cause (a
    full disk: OpenCV's ``imwrite`` printed "libpng error: Write Error" and answered False)."""
    import cv2

    from quatrack.recognition.trackio import atomic_path

    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise UserError(f"--plot {path}: cannot encode the PNG")
    with atomic_path(path, "--plot") as tmp_png:
        try:
            with open(tmp_png, "wb") as f:
                f.write(png.tobytes())
        except OSError as exc:  # (every output goes, as for any error: each file is as it was before the run)
            raise UserError(f"--plot {path}: cannot write ({exc.strerror or exc}); no output of the run was "
                            f"written (files of the same names are as they were)") from None


class _WriteFailed(Exception):
    """An OSError opening, writing or closing ``--out`` (a full disk, ``/dev/full``, a file of
    /proc): :func:`_run_from` says it naming the output (:func:`_write_failed`). ``at_close``:
    at the end of the run (the last rows flushed), not at a frame's row."""

    def __init__(self, error: OSError, at_close: bool = False) -> None:
        super().__init__(str(error))
        self.error, self.at_close = error, at_close


class _Checked:
    """A text file whose OSErrors are :class:`_WriteFailed` (a broken pipe stays itself: ``--out -
    | head`` ends quietly, as before)."""

    def __init__(self, f) -> None:
        self.f = f

    def write(self, text: str) -> None:
        try:
            self.f.write(text)
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise _WriteFailed(exc) from None

    def close(self) -> None:
        try:
            self.f.close()
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise _WriteFailed(exc, at_close=True) from None


@contextlib.contextmanager
def _rows_file(path: str | None):
    """``--out``'s file at ``path`` (None: stdout, :class:`_Flushed`) opened for the rows, its
    OSErrors :class:`_WriteFailed`. Why: a full disk (or ``--out /dev/full``) said "error: [Errno
    28] No space left on device", ``--out /proc/version`` "[Errno 5] Input/output error", naming
    no output. Closed at the end (a short run on a full disk fails there, at the last flush);
    after another error it is closed quietly, that error kept."""
    try:
        f = _Flushed(sys.stdout) if path is None else open(path, "w", newline="", encoding="utf-8")
    except OSError as exc:
        raise _WriteFailed(exc) from None
    out = _Checked(f)
    try:
        yield out
    except BaseException:
        if path is not None:
            with contextlib.suppress(OSError):
                f.close()
        raise
    if path is not None:
        out.close()


def _write_failed(args: argparse.Namespace, failed: _WriteFailed, frames: int, kept: bool, in_place: bool) -> str:
    """The one line saying that ``--out`` could not be written: the output, the system's reason,
    where the run was (the frame whose row failed: the run stops there, not tracking on for
    nothing; or its end), and what is left: the file as it was before the run (``kept``) or
    none. The partial output is removed, and the other outputs are not written (a run ending in
    an error writes nothing, :func:`~quatrack.recognition.trackio.atomic_path`): an old file is
    never replaced by one cut off mid-row. ``in_place``: stdout, a device, a FIFO or a file of
    /proc, written directly (what was written stays written)."""
    import errno

    error = failed.error
    line = f"{'--out - (stdout)' if args.out == STDOUT else f'--out {args.out}'}: cannot write ({error.strerror or error})"
    if failed.at_close:
        line += f" at the end of the run ({frames} frame{'s' if frames != 1 else ''} tracked)"
    elif frames:
        line += f" at frame {frames}; the run stopped there"
    if not in_place:
        line += (f"; {args.out} is as it was before the run" if kept else f"; no {args.out} was made")
        others = [o for o, v in (("--overlay", args.overlay), ("--plot", args.plot)) if v]
        line += f" (the partial file was removed{'; ' + ' and '.join(others) + ' not written either' if others else ''})"
    elif frames and args.out != STDOUT:
        line += "; the poses are not all written"
    if error.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", -1)):
        line += "; free some space or write the poses elsewhere"
    return line


class _Flushed:
    """``--out -``'s stdout, flushed after every row: a program reading a live run's poses from a
    pipe gets each as it is tracked, not 8 KiB at a time."""

    def __init__(self, stream) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()


def _summary_stream(out: str):
    """Where the closing summary goes: stdout, unless the rows go there or to another device or
    FIFO (``--out -``, ``--out /dev/stdout``): then stderr, so that the data stays data (the two
    summary lines came after the last row, and a consumer of the CSV read them as rows)."""
    from quatrack.recognition.trackio import written_where

    return sys.stderr if out == STDOUT or written_where(out)[1] else sys.stdout


def _written(args: argparse.Namespace, video) -> str:
    """"outputs complete", or which output was not written: an overlay without a frame (a stop
    before the first) is no video, and the line said "outputs complete" all the same."""
    if video is not None and video.size is None:
        return f"--overlay {args.overlay} not written (no frame to show); the other outputs complete"
    return "outputs complete"


def _store_learned(s: _Setup, name: str) -> None:
    """Merge the views learned in this run into the stored model (atomic, under the store's
    lock: a concurrent writer's views are kept) and say so in one line on stderr."""
    from quatrack.viewsets.learn import merge_learned_views
    from quatrack.viewsets.store import model_path

    learned = s.tracker.learned_viewsets()
    folder = model_path(s.store, name)
    if not learned:  # (nothing to write: the store is not touched, not even its lock — it may be read-only)
        from quatrack.viewsets.learn import why_none_learned
        print(f"quatrack track: learned no new views ({why_none_learned(s.model, s.tracker.params.learn_max_views)}); "
              f"{folder} unchanged", file=sys.stderr)
        return
    try:
        folder, views, total = merge_learned_views(s.store, name, learned, s.model.mesh,
                                                   s.tracker.params.learn_max_views,
                                                   s.tracker.params.learn_min_angle_deg, learned_on=s.tracker.model)
    except OSError as exc:  # (a full disk, a read-only store: the poses are written, the views are not)
        raise UserError(f"--learn: the {len(learned)} learned view(s) were not saved to {folder}: "
                        f"{exc.strerror or exc}") from None
    if added := len(views):
        from quatrack.viewsets.store import learned_count

        relayed = learned_count(s.store, name, relayed=True)
        of_them = f", {relayed} relayed: they find the object but anchor no frame" if relayed else ""
        held, warning = _views_points(s, views)
        print(f"quatrack track: learned {added} new view(s) -> {folder} ({total} learned in all{of_them}){held}",
              file=sys.stderr)
        if warning:
            print(f"quatrack track: warning: {warning}", file=sys.stderr)
    else:
        print(f"quatrack track: learned no new views (none new to the stored model); {folder} unchanged", file=sys.stderr)


def _views_points(s: _Setup, views) -> tuple[str, str | None]:
    """What the views just learned hold, for the line that counts them: each view's points and how
    many of those are new (:func:`~quatrack.viewsets.learn.new_points`: where the model's views had
    none); and a warning (None: no need) when some add fewer new points than a view needs to be
    learned at all (``learn_min_keypoints``). Why: a box with four plain sides, walked round,
    "learned 7 new view(s)" of 296–472 points, only 10–18 of them new each — its two textured
    faces again — and re-finding it from its other sides gained nothing, with no hint in the
    run's output (user report, finding 7). (The warning does not say "learned": one line does.)"""
    from quatrack.viewsets.learn import new_points

    fresh = new_points(views, s.model.viewsets, s.model.mesh.extent)
    need = s.tracker.params.learn_min_keypoints
    held = (f"; their points: {', '.join(str(len(vs)) for vs in views)} ({sum(fresh)} of them where the model "
            f"had none: {', '.join(map(str, fresh))})")
    weak = [n for n in fresh if n < need]
    if not weak:
        return held, None
    return held, (f"{len(weak)} of the {len(views)} new view(s) hold fewer than {need} points where the model had "
                  f"none ({', '.join(map(str, weak))}): they show texture it already knew (the sides they face plain "
                  f"or weakly textured?), so they will help little to re-find the object from new sides")


def _summary(steps, out: str, stream=None) -> None:
    stream = sys.stdout if stream is None else stream
    out = "stdout" if out == STDOUT else out
    counts = {s: sum(1 for x in steps if x.status == s) for s in ("init", "tracking", "lost")}
    first = next((i for i, s in enumerate(steps) if s.status != "lost"), None)
    after = steps[first:] if first is not None else []
    share = 100.0 * sum(1 for s in after if s.status != "lost") / len(after) if after else 0.0
    track_ms = [s.timings_ms.get("total", 0.0) for s in steps if s.status == "tracking"]
    p50 = f"{np.percentile(track_ms, 50):.1f}" if track_ms else "-"
    print(f"tracked {len(steps)} frames -> {out}", file=stream)
    if first is None:  # (it said "pose in 0.0 % of frames after the first init; step p50 - ms": there was none)
        print(f"  init 0, tracking 0, lost {counts['lost']}; the object was found in no frame", file=stream)
    else:
        print(f"  init {counts['init']}, tracking {counts['tracking']}, lost {counts['lost']}; "
              f"pose in {share:.1f} % of frames after the first init; step p50 {p50} ms", file=stream)
    stream.flush()

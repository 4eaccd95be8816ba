"""``quatrack demo``: stream a video through the service's WebSocket; write the poses, an overlay and a plot.

The steps are plain functions: :func:`_check` turns the options into a :class:`_Plan` (every user
error is found here, before any output: one line, exit status 2), :func:`_stream_video` runs
the WebSocket session (through :func:`quatrack.client.stream`, a plain ``websockets`` client
anyone can copy), :func:`_write_outputs` writes the CSV, the overlay video and the plot
atomically under one folder (default ``./quatrack-demo/``). With no ``--url`` a server is
started on loopback for the run. The defaults use the bundled example wherever the command is
run from; they go together: another ``--video`` needs its ``--camera``, another ``--object`` its
``--video`` (:func:`_check_example_pairing`).
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from pathlib import Path

OUT_DIR = "quatrack-demo"


def bundled_example() -> Path:
    """The folder of the bundled cookie-box example (video, camera, spec), found through the
    installed package (``quatrack.examples``), not the working directory."""
    from quatrack.examples import DEFAULT_EXAMPLE, example_dir

    return example_dir(DEFAULT_EXAMPLE)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", help="a running service, e.g. ws://127.0.0.1:8000 or http://127.0.0.1:8000 "
                                      "(default: start one on loopback)")
    parser.add_argument("--store", metavar="DIR", help="model store for the local service (default: $QUATRACK_STORE or the user data directory)")
    parser.add_argument("--object", default="cookie-box", metavar="NAME", help="trained object (default cookie-box)")
    parser.add_argument("--video", default=None, help="video file to stream (default: the bundled box.mp4, which shows "
                                                       "the bundled cookie-box); for a camera or stream URL use "
                                                       "`quatrack track --video`")
    parser.add_argument("--camera", default=None, help="the video's camera file (required with any --video but the "
                                                        "bundled box.mp4, whose camera is the default)")
    parser.add_argument("--mesh", default=None, help="mesh for the overlay (default: the object's, from the store or the server)")
    parser.add_argument("--out-dir", default=OUT_DIR, metavar="DIR",
                        help=f"folder for the outputs (default ./{OUT_DIR}/, created if missing)")
    parser.add_argument("--out", default="poses.csv", metavar="POSES.csv", help="tracked poses as `quatrack track` writes them, in --out-dir (default poses.csv)")
    parser.add_argument("--overlay", default="overlay.mp4", metavar="VIDEO", help="overlay video in --out-dir (default overlay.mp4; 'none' to skip)")
    parser.add_argument("--plot", default="plot.png", metavar="PNG", help="position/orientation plot in --out-dir (default plot.png; 'none' to skip)")
    parser.add_argument("--fps", type=float, default=None,
                        help="stream in real time at this rate (frames the server cannot keep up with are skipped, "
                             "and written as lost); default: lock-step, every frame tracked")
    parser.add_argument("--max-frames", type=int, default=None, metavar="N", help="stop after N frames (default: all)")
    parser.add_argument("--token", default=None, help="bearer token (default $QUATRACK_API_TOKEN)")
    parser.add_argument("--quiet", action="store_true", help="no progress line")


@dataclass
class _Plan:
    """The checked options."""

    camera: object  # PinholeCamera
    video: str
    ws_url: str | None  # None: start a local server
    http_url: str | None
    token: str | None
    settings: object  # Settings of the local store
    mesh: object | None  # Mesh for the overlay, when known locally
    outputs: dict  # "csv" | "overlay" | "plot" -> path or None


def _output(out_dir: Path, name: str, ext: str, option: str) -> str | None:
    if not name or name.lower() == "none":
        return None
    if not name.lower().endswith(ext):
        raise ValueError(f"{option} {name}: the file name must end in {ext}")
    return str(out_dir / name)


def _is_bundled_video(path: str, example: Path) -> bool:
    """Whether ``path`` is the bundled example's own video file (the one its camera is for)."""
    try:
        return os.path.samefile(path, example / "box.mp4")
    except OSError:
        return False


def _check_example_pairing(args: argparse.Namespace, example: Path) -> None:
    """Refuse an object other than the bundled example's without ``--video``: the default video
    shows the bundled example only, so the run could only answer ``lost`` (or, on a look-alike,
    a wrong pose) and still write outputs that look like a result. Why: ``demo --object my-box``
    streamed the cookie-box video, said "20 lost", exit 0, with no word that the video shows
    another object. The bundled object trained under another name still runs: give its video
    as ``--video``. (The opposite case, ``--video`` of another camera without ``--camera``, is
    refused in :func:`_check`: every pose came out 28 % of the object's size off, exit 0.)"""
    from quatrack.examples import DEFAULT_EXAMPLE

    if args.video is None and args.object != DEFAULT_EXAMPLE:
        raise ValueError(f"--object {args.object}: the default video (the bundled {example / 'box.mp4'}) shows "
                         f"the bundled {DEFAULT_EXAMPLE} only; give --video and --camera of {args.object} (or that --video "
                         f"if {args.object} is the {DEFAULT_EXAMPLE} trained under another name)")


def _check(args: argparse.Namespace) -> _Plan:
    from quatrack.client import api_token, base_urls
    from quatrack.viewsets.camera import load_camera
    from quatrack.viewsets.store import list_models, load_model, unknown_object

    from quatrack.service.settings import Settings

    from quatrack.viewsets.names import check_object_name

    try:  # (a name no store can hold: with --url it went into the WebSocket's URL, "the server refused: 403 ...")
        check_object_name(args.object)
    except ValueError as exc:
        raise ValueError(f"--object: {exc}") from None
    example = bundled_example()
    video = args.video or str(example / "box.mp4")
    camera_file = args.camera or str(example / "camera.json")
    _check_example_pairing(args, example)
    text = video.strip()
    if text.isdigit() or "://" in text:  # (was "--video 0: no such file", as if a camera were a missing file)
        from quatrack.recognition.trackio import masked

        text = masked(text)  # (a camera URL's password)
        raise ValueError(f"--video {text}: demo streams a video file (it reads it again for the overlay); for a "
                         f"camera or a stream URL use `quatrack track --video {text}`, or the browser viewer "
                         f"(`quatrack serve`, then /viewer) for a webcam")
    for opt, path in (("--video", video), ("--camera", camera_file)):
        if not Path(path).is_file():
            hint = "" if getattr(args, opt[2:]) else " (the bundled example is not installed here; give the option)"
            raise ValueError(f"{opt} {path}: no such file{hint}")
        if opt == "--video" and args.camera is None and not _is_bundled_video(path, example):
            raise ValueError(f"--video {path}: give --camera, this video's camera file (the default camera is the "
                             f"bundled example's, for its box.mp4 only: another camera's poses come out wrong, "
                             f"e.g. off in depth by the ratio of the focal lengths)")
    if args.fps is not None and not 0 < args.fps <= 240:
        raise ValueError("--fps must be above 0 and at most 240")
    if args.max_frames is not None and args.max_frames < 1:
        raise ValueError("--max-frames must be at least 1")
    http_url = ws_url = None
    if args.url is not None:
        try:
            http_url, ws_url = base_urls(args.url)
        except ValueError as exc:
            raise ValueError(f"--url {exc}") from None
    token = api_token(args.token or None)  # (--token "": the variable's, as before)
    settings = Settings.from_env(store=args.store, api_token=token)
    in_store = settings.store.is_dir() and args.object in list_models(settings.store)
    if args.url is None and not in_store:
        raise ValueError(f"{unknown_object(settings.store, args.object)}: train it first "  # (the objects it holds, the nearest)
                         f"(quatrack train {example / 'object.json'}), or give --url of a server that has it")
    if args.mesh:
        from quatrack.viewsets.mesh import load_mesh

        mesh = load_mesh(args.mesh)
    else:
        mesh = load_model(settings.store, args.object).mesh if in_store else None
    out_dir = Path(args.out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"--out-dir {out_dir}: not a folder")
    outputs = {"csv": _output(out_dir, args.out, ".csv", "--out"),
               "overlay": _output(out_dir, args.overlay, ".mp4", "--overlay"),
               "plot": _output(out_dir, args.plot, ".png", "--plot")}
    if outputs["csv"] is None:
        raise ValueError("--out: a CSV file name is required")
    for opt, key in (("--out", "csv"), ("--overlay", "overlay"), ("--plot", "plot")):
        folder = Path(outputs[key]).parent if outputs[key] else out_dir
        if folder != out_dir and not folder.is_dir():  # (found after the whole stream, when writing)
            raise ValueError(f"{opt} {getattr(args, opt[2:])}: the folder {folder} does not exist")
    from quatrack.recognition.trackio import check_outputs

    check_outputs([("--video", video), ("--camera", camera_file), ("--mesh", args.mesh)],
                  [("--out", outputs["csv"]), ("--overlay", outputs["overlay"]), ("--plot", outputs["plot"])])
    return _Plan(load_camera(camera_file), video, ws_url, http_url, token, settings, mesh, outputs)


def _stream_video(plan: _Plan, args: argparse.Namespace):
    """Run the session; returns (the stream result, time of every frame read, by index, the
    frames that could not be decoded: ``FrameSource.skipped``, not sent, and whether Ctrl-C or
    SIGTERM stopped it). Stopped after a frame was sent, the answers so far are returned (they
    were lost: an interrupted demo wrote nothing), with the frames sent so far only (a frame
    read as the signal came, never sent, was written ``lost`` and counted as stopped "after"
    it); before, the interrupt is raised."""
    import asyncio
    import contextlib

    from quatrack.client import QuatrackError, StreamResult, stream
    from quatrack.recognition.trackio import Progress, jpeg_frames, open_frames
    from quatrack.viewsets.camera import camera_to_dict

    from quatrack.service.server import BackgroundServer

    times: dict[int, float] = {}  # every frame read, answered or not, for the CSV
    order: list[int] = []  # the frames read, in the order they are handed to the stream (and sent)
    source = open_frames(video=plan.video, max_frames=args.max_frames)

    def frames():
        for i, t, data in jpeg_frames(source):
            times[i] = t
            order.append(i)
            yield i, t, data

    with contextlib.ExitStack() as stack:
        ws_url = plan.ws_url
        if ws_url is None:
            srv = stack.enter_context(BackgroundServer(plan.settings))
            ws_url, plan.http_url = srv.ws_url, srv.url
            print(f"demo: serving {plan.settings.store} on {srv.url}", file=sys.stderr)
        url = f"{ws_url}/v1/objects/{args.object}/track"
        progress = Progress("demo", enabled=False if args.quiet else None)
        res, interrupted = StreamResult(), False
        try:
            asyncio.run(stream(url, camera_to_dict(plan.camera), frames(), fps=args.fps, token=plan.token,
                               on_answer=lambda msg: progress.update(msg.get("status")), result=res))
        except QuatrackError as exc:
            raise ValueError(_explain(exc, args, _server_names(plan) if exc.code == "unknown_object" else None)) from None
        except KeyboardInterrupt:
            if not res.sent:  # (nothing sent: nothing to write)
                raise
            from quatrack.track_cli import _defer_interrupts

            _defer_interrupts("demo")  # (a second Ctrl-C while the outputs are written is said, not taken)
            interrupted = True
        finally:
            progress.close()
            source.close()
        if plan.mesh is None and args.overlay.lower() != "none":
            plan.mesh = _server_edges(plan, args)
    skipped = list(source.skipped)
    if interrupted:  # the frames sent so far, as the docs say: one read as the signal came was not sent
        sent = order[:res.sent]  # (sent in the order read; res.sent counts those whose image went out)
        times = {i: times[i] for i in sent}
        skipped = [item for item in skipped if item[0] < max(sent)]
    return res, times, skipped, interrupted


def _server_names(plan: _Plan) -> list[str] | None:
    """The objects the server holds (``GET /v1/objects``), or None when it does not say."""
    from quatrack.client import Client, QuatrackError

    try:
        with Client(plan.http_url, None, plan.token) as c:
            return [o.name for o in c.objects().objects]
    except (QuatrackError, ValueError):
        return None


def _explain(exc, args, names: list[str] | None = None) -> str:
    """A server's refusal as a one-line message naming the culprit; an unknown object with the
    server's objects (``names``) and the nearest (:func:`~quatrack.viewsets.store.names_hint`)."""
    if exc.code == "unauthorized":
        from quatrack.client import api_token

        if api_token(args.token or None):  # (one was given: it is the wrong one)
            source = "--token" if args.token else "QUATRACK_API_TOKEN"
            return f"{args.url or 'the server'} refused the token of {source}: not the server's QUATRACK_API_TOKEN"
        return f"{args.url or 'the server'} needs a token: give --token or set QUATRACK_API_TOKEN"
    if exc.code == "unknown_object":
        if names is not None:
            from quatrack.viewsets.store import names_hint

            return f"--object {args.object}: the server has no such object{names_hint(args.object, names)}"
        return f"--object {args.object}: the server has no such object ({exc.message})"
    if exc.code == "unreachable":
        return f"--url {args.url}: no server answers there ({exc.message})"
    return f"the server refused: {exc}"


def _server_edges(plan: _Plan, args):
    """The overlay's wireframe from the server (``GET /v1/objects/{name}/mesh``), or None."""
    from quatrack.client import Client, QuatrackError

    try:
        with Client(plan.http_url, args.object, plan.token) as c:
            return c.mesh_edges()
    except QuatrackError:
        return None


#: the reason of a frame that could not be decoded, as ``quatrack track`` writes it (``Tracker.skip``'s)
UNREADABLE = "the frame cannot be read: "


def _steps(res, times: dict, skipped: list) -> list:
    """One step per frame of the video, in order: the server's answer (or ``lost``, "no answer")
    for each frame sent, and a ``lost`` row for each frame that could not be decoded, as ``track``
    writes them (they were left out: the rows and the overlay skipped from frame 2 to 5)."""
    import dataclasses

    from quatrack.recognition.trackio import step_from_message

    steps = {i: step_from_message(res.poses.get(i), i, t) for i, t in times.items()}
    for i, t, why in skipped:
        steps[i] = dataclasses.replace(step_from_message(None, i, t), reason=UNREADABLE + why)
    return [steps[i] for i in sorted(steps)]


def _write_outputs(plan: _Plan, args: argparse.Namespace, res, times: dict, skipped: list = ()) -> list:
    """The CSV, the overlay video and the plot, each atomically; returns the steps."""
    import cv2
    import numpy as np

    from quatrack.recognition.overlay import draw_overlay, plot_track
    from quatrack.recognition.trackio import Progress, RowWriter, VideoOut, atomic_path, open_frames

    steps = _steps(res, times, list(skipped))
    os.makedirs(args.out_dir, exist_ok=True)
    with atomic_path(plan.outputs["csv"], "--out") as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
        rows = RowWriter(f)
        for s in steps:
            rows.write(s)
    if plan.outputs["plot"]:
        with atomic_path(plan.outputs["plot"], "--plot") as tmp:
            if not cv2.imwrite(tmp, plot_track(steps)):
                raise ValueError(f"--plot {plan.outputs['plot']}: cannot write the PNG")
    if plan.outputs["overlay"]:
        if plan.mesh is None:
            print(f"demo: no mesh for the overlay ({args.object!r} is not in the local store; give --mesh); skipped",
                  file=sys.stderr)
            plan.outputs["overlay"] = None
            return steps
        mesh, edges = (None, plan.mesh) if not hasattr(plan.mesh, "vertices") else (plan.mesh, None)
        source = open_frames(video=plan.video, max_frames=len(steps))
        progress = Progress("demo: overlay", enabled=False if args.quiet else None)
        with atomic_path(plan.outputs["overlay"], "--overlay") as tmp:
            video = VideoOut(tmp, source.rate)
            # one overlay frame per row, as track writes it: a frame that cannot be decoded shows the
            # previous one again, marked lost (before any: a black frame of the camera's size)
            c = plan.camera
            last = np.zeros((c.height, c.width, 3), np.uint8) if c.width and c.height else None
            k = 0

            def draw(image, step) -> None:
                if image is not None:
                    video.write(draw_overlay(image, plan.camera, mesh, step, edges))
                progress.update(step.status)

            try:
                for i, _, image in source:
                    while k < len(steps) and steps[k].frame < i:
                        draw(last, steps[k])
                        k += 1
                    if k < len(steps) and steps[k].frame == i:
                        last = image
                        draw(image, steps[k])
                        k += 1
                for step in steps[k:]:
                    draw(last, step)
            finally:
                video.close()
                progress.close()
    return steps


def run(args: argparse.Namespace) -> int:
    """Stream a video through the WebSocket; write the poses (CSV), an overlay video and a plot."""
    from quatrack.track_cli import _interrupts_put_back, _terminate_as_interrupt

    with _interrupts_put_back():
        with _terminate_as_interrupt() as stop:  # (SIGTERM, docker stop: as Ctrl-C, from the start)
            plan = _check(args)
            res, times, skipped, interrupted = _stream_video(plan, args)
        return _finish(plan, args, res, times, skipped, stop.cause if interrupted else None)


def _finish(plan: _Plan, args: argparse.Namespace, res, times: dict, skipped: list, stopped: str | None) -> int:
    """Write the outputs of what was answered and say so; ``stopped``: the cause of an interrupt
    ("Ctrl-C", "SIGTERM"), whose frames sent but not answered are written ``lost``, "no answer"."""
    if stopped is not None:
        others = " (the others as lost)" if len(res.poses) < len(times) else ""
        print(f"demo: stopped ({stopped}) after {len(times)} frames; writing the {len(res.poses)} answered{others}",
              file=sys.stderr)
    if res.errors:  # (a camera of another size than the video's frames: every frame refused, exit 0, no word why)
        first = res.errors[0].get("error") or {}
        why = f"{first.get('message') or first.get('code') or res.errors[0]}"
        if not res.poses and stopped is None:
            raise ValueError(f"the server refused every frame of --video {plan.video}: {why}")
        print(f"demo: the server refused {len(res.errors)} frame(s), written as lost; the first: {why}", file=sys.stderr)
    steps = _write_outputs(plan, args, res, times, skipped)
    for k, _, why in skipped[:5]:  # (as track says it)
        print(f"demo: frame {k} cannot be read, written as lost: {why}", file=sys.stderr)
    if len(skipped) > 5:
        print(f"demo: ... {len(skipped)} frames in all cannot be read", file=sys.stderr)
    answered = [s for s in steps if s.reason != "no answer" and not (s.reason or "").startswith(UNREADABLE)]
    counts = {k: sum(s.status == k for s in answered) for k in ("tracking", "init", "lost")}
    written = ", ".join(p for p in plan.outputs.values() if p)
    print(f"demo: {res.sent} frames sent, {len(res.poses)} tracked answers ({counts['tracking']} tracking, "
          f"{counts['init']} init, {counts['lost']} lost), {res.skipped} skipped, {len(res.errors)} errors, "
          f"{res.sent / max(res.wall_s, 1e-9):.1f} frames/s -> {written}")
    return 0

"""``quatrack demo``: stream a video through the service's WebSocket, write the poses and an overlay.

A plain WebSocket client (the ``websockets`` package) that anyone can copy: it streams a video's
frames as JPEG, writes the poses as ``quatrack track`` does, and draws an overlay video.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", help="a running service, e.g. ws://127.0.0.1:8000 (default: start one on loopback)")
    parser.add_argument("--store", metavar="DIR", help="model store for the local service (default: $QUATRACK_STORE or the user data directory)")
    parser.add_argument("--object", default="cookie-box", metavar="NAME", help="trained object (default cookie-box)")
    parser.add_argument("--video", default="examples/cookie-box/box.mp4", help="video to stream (default: the bundled box.mp4)")
    parser.add_argument("--camera", default="examples/cookie-box/camera.json", help="the video's camera file (JSON)")
    parser.add_argument("--mesh", default=None, help="mesh for the overlay (default: the object's, from the store)")
    parser.add_argument("--out", default="demo-poses.csv", metavar="POSES.csv", help="tracked poses, as `quatrack track` writes them")
    parser.add_argument("--overlay", default="demo-overlay.mp4", metavar="VIDEO", help="overlay video ('none' to skip)")
    parser.add_argument("--fps", type=float, default=None,
                        help="stream in real time at this rate (frames the server cannot keep up with are skipped, "
                             "and written as lost); default: lock-step, every frame tracked")
    parser.add_argument("--max-frames", type=int, default=None, metavar="N", help="stop after N frames")
    parser.add_argument("--token", default=None, help="bearer token (default $QUATRACK_API_TOKEN)")


def run(args: argparse.Namespace) -> int:
    """Stream a video through the WebSocket, write the poses (CSV) and an overlay video."""
    import asyncio
    import contextlib
    import os
    import sys
    from pathlib import Path

    import cv2

    from quatrack.viewsets.camera import camera_to_dict, load_camera

    from quatrack.recognition.visibility import mesh_edges
    from quatrack.viewsets.store import list_models, load_model

    from .client import CSV_HEADER, csv_row, draw_overlay, stream, video_frames
    from .server import BackgroundServer
    from .settings import Settings

    pinhole = load_camera(args.camera)
    camera = camera_to_dict(pinhole)
    if not Path(args.video).is_file():
        raise ValueError(f"--video {args.video}: no such file")
    if args.fps is not None and not 0 < args.fps <= 240:
        raise ValueError("--fps must be between 0 and 240")
    token = args.token or os.environ.get("QUATRACK_API_TOKEN")
    settings = Settings.from_env(store=args.store, api_token=token)
    in_store = args.object in list_models(settings.store)
    if args.url is None and not in_store:
        raise ValueError(f"no object {args.object!r} in {settings.store}: train it first "
                         "(quatrack train examples/cookie-box/object.json)")
    mesh = None  # for the overlay: --mesh, else the object's in the local store (if there)
    if args.mesh:
        from quatrack.viewsets.mesh import load_mesh

        mesh = load_mesh(args.mesh)
    elif in_store:
        mesh = load_model(settings.store, args.object).mesh
    edges = None if mesh is None else mesh_edges(mesh)
    with contextlib.ExitStack() as stack:
        url = args.url
        if url is None:
            srv = stack.enter_context(BackgroundServer(settings))
            url = srv.ws_url
            print(f"demo: serving {settings.store} on {srv.url}", file=sys.stderr)
        ws_url = f"{url.rstrip('/')}/v1/objects/{args.object}/track"
        times: dict[int, float] = {}  # every frame read, answered or not, for the CSV

        def source():
            for i, t, data in video_frames(args.video, args.max_frames):
                times[i] = t
                yield i, t, data

        res = asyncio.run(stream(ws_url, camera, source(), fps=args.fps, token=token))
    tmp = Path(args.out).with_name(f".{Path(args.out).name}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:  # renamed when complete: never a half-written CSV
        f.write(CSV_HEADER + "\n")
        for i in sorted(times):
            f.write(csv_row(i, times[i], res.poses.get(i)) + "\n")
    os.replace(tmp, args.out)
    statuses = [m["status"] for m in res.poses.values()]
    print(f"demo: {res.sent} frames sent, {len(res.poses)} tracked answers "
          f"({statuses.count('tracking')} tracking, {statuses.count('init')} init, {statuses.count('lost')} lost), "
          f"{res.skipped} skipped, {len(res.errors)} errors, {res.sent / max(res.wall_s, 1e-9):.1f} frames/s -> {args.out}")
    if args.overlay and args.overlay.lower() != "none":
        if edges is None:
            print(f"demo: no mesh for the overlay ({args.object!r} is not in the local store; give --mesh); skipped",
                  file=sys.stderr)
            return 0
        cap = cv2.VideoCapture(args.video)
        fps = cap.get(cv2.CAP_PROP_FPS) or 30.0
        writer = None
        i = 0
        while args.max_frames is None or i < args.max_frames:
            ok, img = cap.read()
            if not ok:
                break
            if writer is None:
                writer = cv2.VideoWriter(args.overlay, cv2.VideoWriter_fourcc(*"mp4v"), fps, (img.shape[1], img.shape[0]))
            writer.write(draw_overlay(img, res.poses.get(i), pinhole, edges))
            i += 1
        cap.release()
        if writer is not None:
            writer.release()
        print(f"demo: overlay -> {args.overlay}")
    return 0

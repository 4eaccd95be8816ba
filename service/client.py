"""A small WebSocket client for ``/v1/objects/{name}/track`` (used by ``quatrack demo`` and the bench).

It is also the reference for writing one: send the camera JSON, wait for ``ready``, then for each
frame a ``{"type": "frame", "time_s"}`` header and the JPEG bytes; read one message per processed
frame. *Lock-step* (``fps=None``) waits for each answer before sending the next frame, so every
frame is processed; *real time* (``fps=F``) sends at F frames/s regardless, and the server skips
what it cannot keep up with (each answer's ``skipped`` says how many).
"""

from __future__ import annotations

import asyncio
import json
import time
from dataclasses import dataclass, field
from typing import Iterable

import cv2
import numpy as np
import websockets


@dataclass
class StreamResult:
    """Answers by the index of the frame they are for (the caller's numbering)."""

    poses: dict[int, dict] = field(default_factory=dict)
    errors: list[dict] = field(default_factory=list)
    sent: int = 0
    skipped: int = 0
    rtt_ms: list[float] = field(default_factory=list)  # send → answer, per processed frame
    wall_s: float = 0.0


def video_frames(path: str, max_frames: int | None = None, quality: int = 90) -> Iterable[tuple[int, float, bytes]]:
    """(index, time = index / the video's frame rate, JPEG bytes) for each frame. As ``quatrack
    track`` does: OpenCV's per-frame timestamps are not monotonic for every file (box.mp4's aren't)."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise OSError(f"cannot open video {path}")
    fps = cap.get(cv2.CAP_PROP_FPS) or 30.0
    i = 0
    try:
        while max_frames is None or i < max_frames:
            ok, frame = cap.read()
            if not ok:
                break
            yield i, i / fps, cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()
            i += 1
    finally:
        cap.release()


async def stream(url: str, camera: dict, frames: Iterable[tuple[int, float, bytes]], fps: float | None = None,
                 token: str | None = None, timeout: float = 60.0) -> StreamResult:
    """Stream ``frames`` through one tracking session and collect the answers."""
    headers = {"Authorization": f"Bearer {token}"} if token else None
    res = StreamResult()
    numbers: list[int] = []  # server frame number → caller's index
    sent_at: list[float] = []
    t_start = time.perf_counter()
    async with websockets.connect(url, additional_headers=headers, max_size=None, open_timeout=timeout) as ws:
        await ws.send(json.dumps({**camera, "ack": True}))  # ask for the "ready" handshake
        ready = json.loads(await asyncio.wait_for(ws.recv(), timeout))
        if ready.get("type") != "ready":
            raise RuntimeError(f"the server refused the camera: {ready}")

        def take(msg: dict) -> int | None:
            """Record one answer; returns the server frame number it closes, if any."""
            if msg.get("type") == "pose":
                n = msg["frame"]
                res.poses[numbers[n]] = msg
                res.skipped += msg.get("skipped", 0)
                res.rtt_ms.append((time.perf_counter() - sent_at[n]) * 1e3)
                return n
            res.errors.append(msg)
            return msg.get("frame")

        if fps is None:
            for idx, t, data in frames:
                await ws.send(json.dumps({"type": "frame", "time_s": t}))
                numbers.append(idx)
                sent_at.append(time.perf_counter())
                await ws.send(data)
                res.sent += 1
                while True:
                    msg = json.loads(await asyncio.wait_for(ws.recv(), timeout))
                    if take(msg) == len(numbers) - 1 or (msg.get("type") == "error" and "frame" not in msg):
                        break
        else:
            async def receive():
                while True:
                    take(json.loads(await ws.recv()))

            receiver = asyncio.create_task(receive())
            t0 = time.perf_counter()
            for k, (idx, t, data) in enumerate(frames):
                delay = t0 + k / fps - time.perf_counter()
                if delay > 0:
                    await asyncio.sleep(delay)
                await ws.send(json.dumps({"type": "frame", "time_s": t}))
                numbers.append(idx)
                sent_at.append(time.perf_counter())
                await ws.send(data)
                res.sent += 1
            # the newest frame is always answered: wait for it
            deadline = time.perf_counter() + timeout
            while numbers and numbers[-1] not in res.poses and not any(e.get("frame") == len(numbers) - 1 for e in res.errors):
                if time.perf_counter() > deadline or receiver.done():
                    break
                await asyncio.sleep(0.01)
            receiver.cancel()
    res.wall_s = time.perf_counter() - t_start
    return res


CSV_HEADER = "frame,time_s,status,tx,ty,tz,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,inliers"


def csv_row(index: int, time_s: float, msg: dict | None) -> str:
    """One row as ``quatrack track`` writes it; a frame without an answer is ``lost``."""
    if msg is None or msg["status"] == "lost" or msg.get("pose") is None:
        return f"{index},{time_s:.6f},lost" + "," * 13 + f",{0 if msg is None else msg.get('inliers', 0)}"
    p, vel = msg["pose"], msg.get("velocity") or {"v": [0, 0, 0], "omega": [0, 0, 0]}
    nums = [*p["t"], *p["q_wxyz"], *vel["v"], *vel["omega"]]
    return f"{index},{time_s:.6f},{msg['status']}," + ",".join(f"{x:.6g}" for x in nums) + f",{msg.get('inliers', 0)}"


def draw_overlay(image: np.ndarray, msg: dict | None, camera, edges: np.ndarray) -> np.ndarray:
    """The mesh's edges (k, 2, 3), e.g. ``recognition.visibility.mesh_edges``, at the tracked pose
    (green tracking, yellow init) and the status; ``camera`` a ``PinholeCamera``."""
    from quatrack.recognition.overlay import draw_wireframe

    out = image.copy()
    status = "no answer" if msg is None else msg["status"]
    if msg is not None and msg.get("pose"):
        colour = (0, 220, 0) if status == "tracking" else (0, 220, 220)
        draw_wireframe(out, camera, msg["pose"]["t"], msg["pose"]["q_wxyz"], edges, colour)
    label = status if msg is None else f"{status}  inliers {msg.get('inliers', 0)}  {msg.get('latency_ms', 0):.0f} ms"
    cv2.putText(out, label, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, label, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 1, cv2.LINE_AA)
    return out

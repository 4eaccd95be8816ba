"""Pictures of a track: the model's wireframe and axes drawn at the tracked pose, and a plot of
the pose with its 3σ bands over time (OpenCV only: no plotting dependency)."""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.mesh import Mesh

from .visibility import mesh_edges

STATUS_COLOURS = {"init": (0, 215, 255), "tracking": (60, 200, 60), "lost": (40, 40, 230)}


def _segments(camera: PinholeCamera, R: np.ndarray, t: np.ndarray, seg: np.ndarray, n: int = 8) -> list[np.ndarray]:
    """Projected polylines of 3-D segments (k, 2, 3), sampled so lens distortion bends them."""
    s = np.linspace(0.0, 1.0, n)[None, :, None]
    pts = seg[:, :1] * (1 - s) + seg[:, 1:] * s  # (k, n, 3)
    Xc = pts.reshape(-1, 3) @ R.T + t
    front = Xc[:, 2] > 1e-6
    uv = np.full((len(Xc), 2), np.nan)
    uv[front] = camera.project(Xc[front])
    uv = uv.reshape(len(seg), n, 2)
    return [np.rint(line).astype(np.int32) for line in uv if np.all(np.isfinite(line)) and np.all(np.abs(line) < 1e5)]


def draw_wireframe(out: np.ndarray, camera: PinholeCamera, t, q_wxyz, edges: np.ndarray, colour) -> None:
    """Draw, in place, the 3-D segments ``edges`` (k, 2, 3) (e.g. :func:`mesh_edges`) at the pose
    (``t``, ``q_wxyz``), object → camera; sampled along each edge so lens distortion bends them."""
    R = quat.to_matrix(np.asarray(q_wxyz, float))
    cv2.polylines(out, _segments(camera, R, np.asarray(t, float), edges), False, colour, 2, cv2.LINE_AA)


def draw_label(out: np.ndarray, text: str, origin: tuple[int, int] = (8, 8), colour=(255, 255, 255),
               scale: float = 0.6, background=(0, 0, 0)) -> tuple[int, int, int, int]:
    """Draw, in place, ``text`` on an opaque box whose top-left corner is ``origin``; returns
    the box ``(x0, y0, x1, y1)``. Why a box: the usual "thick dark outline, thin fill" label
    is unreadable with OpenCV 5, whose thick and thin glyphs no longer have the same advance
    width, so the two copies drift apart along the line; one thin copy on a box cannot."""
    font, thickness = cv2.FONT_HERSHEY_SIMPLEX, 1
    (w, h), base = cv2.getTextSize(text, font, scale, thickness)
    pad = max(2, int(round(4 * scale)))
    x0, y0 = origin
    x1, y1 = x0 + w + 2 * pad, y0 + h + base + 2 * pad
    cv2.rectangle(out, (x0, y0), (x1 - 1, y1 - 1), background, cv2.FILLED)
    cv2.putText(out, text, (x0 + pad, y0 + pad + h), font, scale, colour, thickness, cv2.LINE_AA)
    return x0, y0, x1, y1


def step_label(step) -> str:
    """``#frame time status inliers [latency]``: the status line of an overlay."""
    text = f"#{step.frame} {step.time_s:.2f}s {step.status} inliers {step.inliers}"
    latency = (step.timings_ms or {}).get("latency")
    return text if latency is None else f"{text} {latency:.0f} ms"


def draw_overlay(image: np.ndarray, camera: PinholeCamera, mesh: Mesh | None, step, edges: np.ndarray | None = None,
                 label: str | None = None) -> np.ndarray:
    """A copy of ``image`` (BGR) with the wireframe, the object axes (x red, y green, z blue) and
    the status line of a :class:`~recognition.video.TrackStep` (colour by status). The one
    overlay drawer of quatrack: ``track --overlay``, ``demo`` and the benchmarks use it. Either
    ``mesh`` or ``edges`` (k, 2, 3) must be given; the axes start at the corner of the edges'
    (or mesh's) bounding box and are 0.3 of its diagonal long."""
    if not (isinstance(image, np.ndarray) and image.dtype == np.uint8 and (image.ndim == 2 or image.shape[-1] == 3)):
        # (a 16-bit, float or BGRA frame, as the tracker takes them: OpenCV's "Assertion failed
        # img.depth() == CV_8U in function 'putText'"); 8-bit grey and BGR are drawn on as before
        from .images import to_bgr8

        image = to_bgr8(image)
    out = image.copy()
    colour = STATUS_COLOURS.get(step.status, (255, 255, 255))
    if edges is None:
        edges = mesh_edges(mesh.run_time)  # (a scan's: its run-time decimation's)
    if step.t is not None and step.q_wxyz is not None and step.status != "lost":
        R = quat.to_matrix(np.asarray(step.q_wxyz, float))
        t = np.asarray(step.t, float)
        draw_wireframe(out, camera, t, step.q_wxyz, edges, colour)
        pts = mesh.vertices if mesh is not None else np.asarray(edges, float).reshape(-1, 3)
        o = pts.min(axis=0)
        L = 0.3 * float(np.linalg.norm(pts.max(axis=0) - o))  # 0.3 × the bounding box diagonal
        axes = np.array([[o, o + [L, 0, 0]], [o, o + [0, L, 0]], [o, o + [0, 0, L]]])
        for line, c in zip(_segments(camera, R, t, axes, 2), ((0, 0, 255), (0, 200, 0), (255, 0, 0))):
            cv2.arrowedLine(out, tuple(map(int, line[0])), tuple(map(int, line[1])), c, 2, cv2.LINE_AA, tipLength=0.15)
    draw_label(out, step_label(step) if label is None else label, colour=colour)
    return out


def resolving_decimals(resolution: float, most: int = 9) -> int:
    """Decimals a number needs to show steps of ``resolution``: ``⌈−log₁₀ resolution⌉``,
    within ``[0, most]``. Why: positions are in the mesh's units, so a fixed ``.2f`` shows a
    mesh in metres to the centimetre (0.00) and one in millimetres to the hundredth.

    >>> resolving_decimals(0.02), resolving_decimals(2e-4), resolving_decimals(0.2), resolving_decimals(50.0)
    (2, 4, 1, 0)
    """
    if not np.isfinite(resolution) or resolution <= 0:
        return most
    return int(min(max(np.ceil(-np.log10(resolution) - 1e-9), 0), most))


def _panel(canvas, box, times, values, sigmas, title, unit, tmax, colours):
    """One plot panel: series (columns of ``values``) with 3σ bands; NaN breaks a line (lost frames)."""
    x0, y0, x1, y1 = box
    cv2.rectangle(canvas, (x0, y0), (x1, y1), (0, 0, 0), 1)
    finite = np.isfinite(values)
    if finite.any():
        lo = np.nanmin(np.where(finite, values - 3 * sigmas, np.nan))
        hi = np.nanmax(np.where(finite, values + 3 * sigmas, np.nan))
    else:
        lo, hi = -1.0, 1.0
    if not hi > lo:
        lo, hi = lo - 1.0, hi + 1.0
    pad = 0.05 * (hi - lo)
    lo, hi = lo - pad, hi + pad
    X = lambda t: (x0 + (x1 - x0) * t / max(tmax, 1e-9)).astype(np.int32)  # noqa: E731
    Y = lambda v: (y1 - (y1 - y0) * (v - lo) / (hi - lo)).astype(np.int32)  # noqa: E731
    band = canvas.copy()
    for k, c in enumerate(colours):
        v, s, ok = values[:, k], sigmas[:, k], finite[:, k]
        for run in np.split(np.arange(len(v)), np.flatnonzero(np.diff(ok.astype(int))) + 1):
            if len(run) == 0 or not ok[run[0]]:
                continue
            top = np.column_stack([X(times[run]), Y(v[run] + 3 * s[run])])
            bot = np.column_stack([X(times[run]), Y(v[run] - 3 * s[run])])[::-1]
            cv2.fillPoly(band, [np.concatenate([top, bot])], tuple(int(0.5 * x + 127) for x in c))
    cv2.addWeighted(band, 0.5, canvas, 0.5, 0, canvas)
    for k, c in enumerate(colours):
        v, ok = values[:, k], finite[:, k]
        for run in np.split(np.arange(len(v)), np.flatnonzero(np.diff(ok.astype(int))) + 1):
            if len(run) and ok[run[0]]:
                cv2.polylines(canvas, [np.column_stack([X(times[run]), Y(v[run])])], False, c, 1, cv2.LINE_AA)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(canvas, title, (x0 + 6, y0 + 16), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    # the axis' ends to a hundredth of its span (a mesh in metres moves by millimetres), right-aligned
    n = resolving_decimals((hi - lo) / 100)
    for v, y in ((hi, y0 + 12), (lo, y1)):
        text = f"{v:.{n}f} {unit}"
        (tw, _), _ = cv2.getTextSize(text, font, 0.4, 1)
        cv2.putText(canvas, text, (max(x0 - 6 - tw, 0), y), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)


def plot_track(steps: Sequence, size: tuple[int, int] = (1100, 900)) -> np.ndarray:
    """A BGR image: position (mesh units) and orientation (rotation vector, degrees) over time,
    each with its 3σ band from the filter's covariance; gaps where the track was lost."""
    w, h = size
    canvas = np.full((h, w, 3), 255, np.uint8)
    n = len(steps)
    times = np.array([s.time_s for s in steps], float) if n else np.zeros(0)
    pos = np.full((n, 3), np.nan)
    ang = np.full((n, 3), np.nan)
    sp = np.zeros((n, 3))
    sa = np.zeros((n, 3))
    prev = None
    for i, s in enumerate(steps):
        if s.t is None:
            prev = None
            continue
        pos[i] = s.t
        rv = np.degrees(quat.to_rotvec(s.q_wxyz))
        if prev is not None:  # keep the rotation vector continuous (its sign flips near 180°)
            alt = rv - 360.0 * rv / max(np.linalg.norm(rv), 1e-9)
            if np.linalg.norm(alt - prev) < np.linalg.norm(rv - prev):
                rv = alt
        ang[i] = prev = rv
        if s.covariance is not None:
            d = np.sqrt(np.clip(np.diagonal(np.asarray(s.covariance))[:6], 0, None))
            sp[i], sa[i] = d[:3], np.degrees(d[3:])
    tmax = float(times.max() - times.min()) if n else 1.0
    t_rel = times - (times.min() if n else 0.0)
    colours = ((40, 40, 220), (40, 160, 40), (220, 80, 40))
    top, bottom = 10, h - 40
    rows = 6
    gap = 8
    hh = (bottom - top - gap * (rows - 1)) // rows
    for k in range(rows):
        y0 = top + k * (hh + gap)
        vals, sig = (pos, sp) if k < 3 else (ang, sa)
        name = ("tx", "ty", "tz", "rx", "ry", "rz")[k]
        unit = "u" if k < 3 else "deg"
        title = f"{name} ({'position, mesh units' if k < 3 else 'rotation vector, degrees'}; band 3 sigma)"
        _panel(canvas, (90, y0, w - 20, y0 + hh), t_rel, vals[:, k % 3 : k % 3 + 1], sig[:, k % 3 : k % 3 + 1],
               title, unit, tmax, (colours[k % 3],))
    cv2.putText(canvas, f"time 0 .. {tmax:.2f} s", (w // 2 - 60, h - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                (0, 0, 0), 1, cv2.LINE_AA)
    return canvas

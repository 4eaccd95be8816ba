"""Tracking benchmark (issue 5): accuracy against rendered ground truth at several sampling rates,
per-step timings, and behaviour on the real ``box.mp4``.

- A rendered sequence: the textured cookie box moved along a smooth but lively trajectory (sums of
  sinusoids in position and orientation, ~40°/s and ~20 cm/s at the peaks) over a real room
  background, with sensor noise and JPEG. Every motion model (ude, m1, m2, m3) tracks it using
  every frame, every 2nd, ..., every 5th (Kragic & Kyrki's Table 1).
- ``box.mp4``: the share of frames with a pose after the first init, and the frame-to-frame pose
  change of the tracker against per-frame recognition (``locate``), a measure of jitter.
"""

from __future__ import annotations

import json
import os
import time

import cv2
import numpy as np

from quatrack.testing.scenes import EXAMPLE, Renderer, example_model, pose_errors
from quatrack.testing.sequences import lively_trajectory, render_sequence
from quatrack.tracking import quaternion as quat

MODELS = ("ude", "m1", "m2", "m3")
RATES = (1, 2, 3, 4, 5)


def _decode(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


def run_sequence(tracker, frames, poses, fps: float, every: int = 1, mesh=None) -> dict:
    """Track frames ``0, every, 2·every, ...``; errors against the truth, statuses and timings."""
    from quatrack.recognition.trackio import Progress

    t_err, r_err, statuses, measure_adjust, totals, stages = [], [], [], [], [], {}
    progress = Progress(f"bench track (every {every})")  # a line on a terminal only
    for k in range(0, len(frames), every):
        step = tracker.step(_decode(frames[k]), k / fps)
        statuses.append(step.status)
        progress.update(step.status)
        if step.t is not None:
            dt, dr = pose_errors(step.t, step.q_wxyz, poses[k], mesh)
            t_err.append(dt)
            r_err.append(dr)
        if step.status == "tracking":
            ms = step.timings_ms
            measure_adjust.append(ms.get("measure", 0.0) + ms.get("adjust", 0.0))
            totals.append(ms["total"])
            for key, v in ms.items():
                stages.setdefault(key, []).append(v)
    progress.close()
    n_track = max(len(totals), 1)
    return {
        "frames": len(statuses),
        "lost": statuses.count("lost"),
        "inits": statuses.count("init"),
        "t_err_mean": float(np.mean(t_err)) if t_err else None,
        "t_err_max": float(np.max(t_err)) if t_err else None,
        "r_err_mean_deg": float(np.mean(r_err)) if r_err else None,
        "r_err_max_deg": float(np.max(r_err)) if r_err else None,
        "measure_adjust_p50_ms": float(np.percentile(measure_adjust, 50)) if measure_adjust else None,
        "measure_adjust_p95_ms": float(np.percentile(measure_adjust, 95)) if measure_adjust else None,
        "step_p50_ms": float(np.percentile(totals, 50)) if totals else None,
        "step_p95_ms": float(np.percentile(totals, 95)) if totals else None,
        "stage_share": {k: float(np.sum(v) / max(np.sum(stages["total"]), 1e-9)) for k, v in stages.items() if k != "total"},
        "stage_mean_ms": {k: float(np.sum(v) / n_track) for k, v in stages.items()},
    }


def _centre_change(a, b, mesh) -> tuple[float, float]:
    ca = quat.to_matrix(a.q_wxyz) @ mesh.centre + a.t
    cb = quat.to_matrix(b.q_wxyz) @ mesh.centre + b.t
    return float(np.linalg.norm(ca - cb)), float(np.degrees(quat.angle_between(a.q_wxyz, b.q_wxyz)))


def real_video(model, camera, locate_frames: int = 150, sheet_every: int = 75):
    """Track ``box.mp4``; compare frame-to-frame changes with per-frame ``locate`` on the first
    ``locate_frames`` frames. Returns the figures and a few overlay frames."""
    from quatrack.recognition.locate import locate
    from quatrack.recognition.match import index_for
    from quatrack.recognition.overlay import draw_overlay
    from quatrack.recognition.video import Tracker, TrackerParams

    index = index_for(model)
    tracker = Tracker(model, camera, TrackerParams(), index=index)
    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    steps, located, sheet, totals, stages = [], [], [], [], {}
    k = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        step = tracker.step(frame, k / 30.0)
        steps.append(step)
        if step.status == "tracking":
            totals.append(step.timings_ms["total"])
            for key, v in step.timings_ms.items():
                stages[key] = stages.get(key, 0.0) + v
        if k < locate_frames:
            located.append(locate(frame, camera, model, index=index))
        if k % sheet_every == 0:
            sheet.append(draw_overlay(frame, camera, model.mesh, step))
        k += 1
    cap.release()
    first = next((i for i, s in enumerate(steps) if s.status != "lost"), len(steps))
    after = steps[first:]
    share = 100.0 * sum(s.status != "lost" for s in after) / max(len(after), 1)

    def changes(seq):
        d = [_centre_change(a, b, model.mesh) for a, b in zip(seq[:-1], seq[1:]) if a.t is not None and b.t is not None]
        if not d:
            return None
        d = np.array(d)
        return {"t_median": float(np.median(d[:, 0])), "t_p95": float(np.percentile(d[:, 0], 95)),
                "r_median_deg": float(np.median(d[:, 1])), "r_p95_deg": float(np.percentile(d[:, 1], 95))}

    class _P:  # locate's answers as pose holders
        def __init__(self, r):
            self.t, self.q_wxyz = (r.t, r.q_wxyz) if r.found else (None, None)

    n = min(locate_frames, len(steps))
    return {
        "frames": len(steps),
        "first_init": first,
        "pose_share_after_init_pct": share,
        "lost": sum(s.status == "lost" for s in after),
        "reinits": sum(s.status == "init" for s in after) - 1,
        "step_p50_ms": float(np.percentile(totals, 50)) if totals else None,
        "step_p95_ms": float(np.percentile(totals, 95)) if totals else None,
        "stage_mean_ms": {k: v / max(len(totals), 1) for k, v in sorted(stages.items())},
        "frame_to_frame_tracker": changes(steps[:n]),
        "frame_to_frame_locate": changes([_P(r) for r in located]),
        "locate_found_pct": 100.0 * sum(r.found for r in located) / max(len(located), 1),
    }, sheet


def contact_sheet(images: list[np.ndarray], cols: int = 3, width: int = 320) -> np.ndarray:
    tiles = [cv2.resize(im, (width, int(im.shape[0] * width / im.shape[1]))) for im in images]
    h = max(t.shape[0] for t in tiles)
    blank = np.zeros((h, width, 3), np.uint8)
    while len(tiles) % cols:
        tiles.append(blank)
    rows = [np.hstack(tiles[i : i + cols]) for i in range(0, len(tiles), cols)]
    return np.vstack(rows)


def study(seconds: float = 10.0, fps: float = 30.0, models=MODELS, rates=RATES, locate_frames: int = 150,
          sheet_path: str | None = "track_contact_sheet.png") -> dict:
    """Everything in the module docstring; returns one JSON-able dict."""
    from quatrack.recognition.match import index_for
    from quatrack.recognition.overlay import draw_overlay
    from quatrack.recognition.video import Tracker, TrackerParams
    from quatrack.viewsets.camera import load_camera

    from quatrack.testing.scenes import video_backgrounds

    t0 = time.perf_counter()
    model = example_model()
    camera = load_camera(EXAMPLE / "camera.json")
    renderer = Renderer.from_spec(EXAMPLE / "object.json")
    background = video_backgrounds()[3]
    traj = lively_trajectory(renderer)
    n = int(round(seconds * fps))
    frames, poses = render_sequence(renderer, camera, traj, n, fps, background)
    render_s = time.perf_counter() - t0
    index = index_for(model)
    diameter = float(model.mesh.extent)
    results = {}
    for name in models:
        for every in rates:
            tracker = Tracker(model, camera, TrackerParams(motion_model=name), index=index)
            tracker.init_pose(poses[0].t, quat.from_matrix(poses[0].R))  # isolate tracking from recognition
            r = run_sequence(tracker, frames, poses, fps, every, model.mesh)
            r["t_err_mean_pct_diameter"] = None if r["t_err_mean"] is None else 100.0 * r["t_err_mean"] / diameter
            results[f"{name}/{every}"] = r
    # the same sequence initialised by recognition, full rate (the default pipeline end to end)
    tracker = Tracker(model, camera, TrackerParams(), index=index)
    auto = run_sequence(tracker, frames, poses, fps, 1, model.mesh)
    sheet = []
    tracker = Tracker(model, camera, TrackerParams(), index=index)
    for k in range(n):
        step = tracker.step(_decode(frames[k]), k / fps)
        if k % (n // 3) == 0 and len(sheet) < 3:
            sheet.append(draw_overlay(_decode(frames[k]), camera, model.mesh, step))
    video, video_sheet = real_video(model, camera, locate_frames)
    if sheet_path:
        cv2.imwrite(sheet_path, contact_sheet(sheet + video_sheet))
    return {
        "machine": f"{os.cpu_count()} cores",
        "sequence": {"seconds": seconds, "fps": fps, "frames": n, "diameter": diameter, "render_s": render_s},
        "rendered": results,
        "rendered_auto_init_full_rate": auto,
        "box_mp4": video,
        "contact_sheet": sheet_path,
        "total_s": time.perf_counter() - t0,
    }


def _fmt(v, spec=".2f"):
    return "-" if v is None else format(v, spec)


def report(res: dict) -> str:
    s = res["sequence"]
    lines = [f"rendered sequence: {s['frames']} frames at {s['fps']:g} fps, object diameter {s['diameter']:.1f} units",
             "model/every  frames lost  t_err mean (% diam) max   r_err mean max (deg)   meas+adj p50/p95 ms  step p50/p95 ms"]
    for key, r in res["rendered"].items():
        lines.append(f"{key:<11} {r['frames']:>6} {r['lost']:>4}  {_fmt(r['t_err_mean'], '.3f')} ({_fmt(r['t_err_mean_pct_diameter'])} %) "
                     f"{_fmt(r['t_err_max'], '.2f')}   {_fmt(r['r_err_mean_deg'], '.3f')} {_fmt(r['r_err_max_deg'])}   "
                     f"{_fmt(r['measure_adjust_p50_ms'], '.1f')}/{_fmt(r['measure_adjust_p95_ms'], '.1f')}   "
                     f"{_fmt(r['step_p50_ms'], '.1f')}/{_fmt(r['step_p95_ms'], '.1f')}")
    a = res["rendered_auto_init_full_rate"]
    lines.append(f"auto-init (recognition) full rate: lost {a['lost']}, t_err mean {_fmt(a['t_err_mean'], '.3f')}, "
                 f"r_err mean {_fmt(a['r_err_mean_deg'], '.3f')} deg")
    share = res["rendered"].get("ude/1", {}).get("stage_share", {})
    lines.append("ude/1 share of step time: " + ", ".join(f"{k} {100 * v:.0f} %" for k, v in sorted(share.items())))
    means = res["rendered"].get("ude/1", {}).get("stage_mean_ms", {})
    lines.append("ude/1 stage means per tracking step (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in sorted(means.items())))
    v = res["box_mp4"]
    lines.append(f"box.mp4: {v['frames']} frames, first init at {v['first_init']}, pose in {v['pose_share_after_init_pct']:.1f} % "
                 f"after it ({v['lost']} lost, {v['reinits']} re-inits); step p50/p95 {_fmt(v['step_p50_ms'], '.1f')}/"
                 f"{_fmt(v['step_p95_ms'], '.1f')} ms")
    if v.get("stage_mean_ms"):
        lines.append("  stage means per tracking step (ms): " + ", ".join(f"{k} {x:.1f}" for k, x in v["stage_mean_ms"].items()))
    ft, fl = v["frame_to_frame_tracker"], v["frame_to_frame_locate"]
    if ft and fl:
        lines.append(f"  frame-to-frame change (median / p95): tracker {ft['t_median']:.2f}/{ft['t_p95']:.2f} units, "
                     f"{ft['r_median_deg']:.2f}/{ft['r_p95_deg']:.2f} deg; locate {fl['t_median']:.2f}/{fl['t_p95']:.2f} units, "
                     f"{fl['r_median_deg']:.2f}/{fl['r_p95_deg']:.2f} deg (locate found {v['locate_found_pct']:.0f} %)")
    lines.append(f"contact sheet: {res['contact_sheet']}; total {res['total_s']:.0f} s")
    return "\n".join(lines)


def main(as_json: bool = False, seconds: float = 10.0, locate_frames: int = 150, sheet: str | None = None) -> int:
    res = study(seconds=seconds, locate_frames=locate_frames, sheet_path=sheet or "track_contact_sheet.png")
    print(json.dumps(res) if as_json else report(res))
    return 0


__all__ = ["run_sequence", "study", "real_video", "main"]

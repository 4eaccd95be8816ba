"""Scanned meshes: ``quatrack bench scan-mesh [--subdivisions K] [--jitter F] [--frames N] [--json]``.

A user's mesh of their object is as often a scan (10⁴–10⁶ triangles, its vertices a little off
the true surface) as a CAD model (a box's 12). This benchmark trains the bundled cookie box on
three meshes of the same box — its own 12 triangles, the same subdivided ``K`` times (4^K × 12
triangles, flat: a fine CAD export) and that subdivided mesh with every vertex jittered by ``F``
× the box's size (Gaussian, seeded: a scan's noise) — and reports for each: training time, the
synthetic views kept and their keypoints, ``locate`` on every 10th of the first 100 frames of
``box.mp4`` (found, time p50), tracking its first ``N`` frames (frames with a pose, step time
p50/p95, the run-time mesh's faces), and how far the tracked poses lie from those of the 12-face
box (median and max, cm and degrees). No ground truth: the 12-face box's track is the reference,
so the figures say what a dense or rough mesh changes, not how accurate either is.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from quatrack.examples import example_dir


def _meshes(subdivisions: int, jitter: float, seed: int = 0) -> dict:
    from quatrack.testing.scans import scanned
    from quatrack.viewsets.mesh import load_mesh

    box = load_mesh(example_dir() / "box.ply")
    fine, rough = scanned(box, subdivisions), scanned(box, subdivisions, jitter, seed)
    return {"12 faces": None, f"{len(fine.faces)} faces": (fine.vertices, fine.faces),
            f"{len(fine.faces)} faces, jittered {100 * jitter:g} %": (rough.vertices, rough.faces)}


def run(subdivisions: int = 6, jitter: float = 0.001, frames: int = 150, progress: bool = True) -> dict:
    import trimesh

    from quatrack.recognition.locate import locate
    from quatrack.recognition.match import index_for
    from quatrack.recognition.video import Tracker, TrackerParams
    from quatrack.tracking import quaternion as quat
    from quatrack.viewsets.camera import load_camera
    from quatrack.viewsets.spec import load_spec
    from quatrack.viewsets.train import train_object

    ex = example_dir()
    camera = load_camera(ex / "camera.json")
    cap = cv2.VideoCapture(str(ex / "box.mp4"))
    video = []
    while len(video) < max(frames, 100):
        ok, f = cap.read()
        if not ok:
            break
        video.append(f)
    spec = json.loads((ex / "object.json").read_text())
    for v in spec["views"]:
        v["image"] = str(ex / v["image"])
        if v.get("mask"):
            v["mask"] = str(ex / v["mask"])
    out: dict = {"subdivisions": subdivisions, "jitter": jitter, "frames": min(frames, len(video)), "meshes": {}}
    reference = None
    with tempfile.TemporaryDirectory() as tmp:
        for label, arrays in _meshes(subdivisions, jitter).items():
            if progress:
                print(f"  {label}: training ...", flush=True)
            if arrays is None:
                spec_path = ex / "object.json"
            else:
                stem = f"mesh{len(out['meshes'])}"
                trimesh.Trimesh(arrays[0], arrays[1], process=False).export(Path(tmp) / f"{stem}.ply")
                (Path(tmp) / f"{stem}.json").write_text(json.dumps({**spec, "name": stem, "mesh": f"{stem}.ply"}))
                spec_path = Path(tmp) / f"{stem}.json"
            t0 = time.perf_counter()
            model = train_object(load_spec(spec_path))
            train_s = time.perf_counter() - t0
            synthetic = [len(vs) for vs in model.viewsets if vs.synthetic]
            index = index_for(model)
            locate(video[0], camera, model, index=index)  # (warm: first-use compilation and caches)
            times, found = [], 0
            for f in video[:100:10]:
                t0 = time.perf_counter()
                found += locate(f, camera, model, index=index).found
                times.append((time.perf_counter() - t0) * 1e3)
            tracker = Tracker(model, camera, TrackerParams(), index=index)
            poses, steps = [], []
            for k, f in enumerate(video[:frames]):
                s = tracker.step(f, k / 30.0)
                poses.append((np.asarray(s.t, float), np.asarray(s.q_wxyz, float)) if s.has_pose else None)
                if s.status == "tracking":
                    steps.append(s.timings_ms["total"])
            row = {"faces": len(model.mesh.faces), "run_time_faces": len(tracker.model.mesh.faces),
                   "train_s": round(train_s, 1), "synthetic_views": len(synthetic),
                   "synthetic_keypoints_median": float(np.median(synthetic)) if synthetic else 0.0,
                   "locate_found": f"{found}/{len(times)}", "locate_p50_ms": round(float(np.median(times)), 1),
                   "frames_with_pose": sum(p is not None for p in poses),
                   "step_p50_ms": round(float(np.median(steps)), 1) if steps else None,
                   "step_p95_ms": round(float(np.percentile(steps, 95)), 1) if steps else None}
            if reference is None:
                reference = poses
            else:
                both = [(a, b) for a, b in zip(reference, poses) if a is not None and b is not None]
                dt = [float(np.linalg.norm(a[0] - b[0])) for a, b in both]
                dr = [float(np.degrees(quat.angle_between(a[1], b[1]))) for a, b in both]
                row.update(vs_12_faces_cm=[round(float(np.median(dt)), 2), round(max(dt), 2)] if dt else None,
                           vs_12_faces_deg=[round(float(np.median(dr)), 2), round(max(dr), 2)] if dr else None)
            out["meshes"][label] = row
    return out


def report(res: dict) -> str:
    lines = [f"The cookie box on three meshes ({res['frames']} frames of box.mp4 tracked; poses compared with "
             f"the 12-face box's):", ""]
    head = ["mesh", "run-time faces", "train s", "synthetic views (median keypoints)", "locate found / p50 ms",
            "frames with a pose", "step p50 / p95 ms", "vs 12 faces: cm (median / max)", "deg (median / max)"]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("| " + " | ".join("---" for _ in head) + " |")
    for label, r in res["meshes"].items():
        cm, deg = r.get("vs_12_faces_cm"), r.get("vs_12_faces_deg")
        lines.append("| " + " | ".join([
            label, str(r["run_time_faces"]), f"{r['train_s']:g}",
            f"{r['synthetic_views']} ({r['synthetic_keypoints_median']:g})",
            f"{r['locate_found']} / {r['locate_p50_ms']:g}", str(r["frames_with_pose"]),
            f"{r['step_p50_ms']} / {r['step_p95_ms']}",
            "—" if cm is None else f"{cm[0]:g} / {cm[1]:g}", "—" if deg is None else f"{deg[0]:g} / {deg[1]:g}"]) + " |")
    return "\n".join(lines)


def main(subdivisions: int = 6, jitter: float = 0.001, frames: int = 150, as_json: bool = False) -> int:
    res = run(subdivisions, jitter, frames, progress=not as_json)
    print(json.dumps(res) if as_json else report(res))
    return 0

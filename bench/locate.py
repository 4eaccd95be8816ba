"""`quatrack bench locate`: speed and accuracy of recognition and initial pose (issue 4).

- **Rendered scenes** (ground truth): the bundled cookie box rendered at known poses turned up
  to 60° away from its registered view, over real room backgrounds, with colour casts, shading,
  blur, noise, JPEG and occluders (:mod:`quatrack.testing.scenes`). Success = centre translation error
  ≤ 5 % of the object's diameter and rotation error ≤ 5°; the curve over viewing angle; the
  localisation window's IoU with the true box.
- **Negatives**: the same backgrounds without the box: how often a pose is (wrongly) reported.
- **Real video** (``box.mp4``, no ground truth): in how many frames a verified pose is found,
  and whether the window's centre lies on the box as drawn by a verified whole-image pose of the
  same frame; a contact sheet of overlays to look at.
- **Other cameras** (the same video as a grey camera, and at 3× and ½ its pixels with the camera
  scaled): in how many sampled frames a verified pose is found, how far it lies from the colour
  640 × 480 frame's (median), and in how many within the 5 %/5° criterion of it. A 2560-px camera and a grey one
  each lost the box in users' trials while every colour 640-px figure passed (session 72).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np

from quatrack.bench.track_zoo import NEES_95, nees
from quatrack.recognition.locate import LocateParams, locate
from quatrack.recognition.match import index_for
from quatrack.recognition.overlay import draw_label, draw_wireframe
from quatrack.recognition.pose import iou
from quatrack.recognition.visibility import mesh_edges
from quatrack.viewsets.camera import load_camera
from quatrack.viewsets.render import render
from quatrack.tracking.pose import Pose

from quatrack.testing import scenes as S

STAGES = ("localise", "match", "pnp", "total")


def _located(image, camera, model, params, index):
    """``locate`` and the CPU time it took (ms, this process, all threads): the stage times are
    wall-clock and grow with the machine's load; the CPU time does much less (bench/RESULTS.md,
    issue 13 speed), so both are reported."""
    c0 = time.process_time()
    r = locate(image, camera, model, params, index=index)
    return r, (time.process_time() - c0) * 1e3
ANGLE_BINS = (0, 10, 20, 30, 40, 50, 60)


def _pct(values, q) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def rendered(n: int, seed: int, model, camera, progress: bool) -> dict:
    from tqdm import tqdm

    renderer = S.Renderer.from_spec(S.EXAMPLE / "object.json")
    backgrounds = S.video_backgrounds()
    rng = np.random.default_rng(seed)
    index = index_for(model)
    diameter = float(model.mesh.extent)
    rows = []
    for _ in tqdm(range(n), desc="rendered scenes", disable=not progress, unit="scene"):
        sc = S.random_scene(rng, renderer, camera, backgrounds)
        r, cpu = _located(sc.image, camera, model, LocateParams(), index)
        dt, dr = (np.inf, np.inf) if not r.found else S.pose_errors(r.t, r.q_wxyz, sc.pose, model.mesh)
        rows.append({
            "angle": sc.view_angle_deg, "found": r.found, "dt": dt, "dr": dr,
            "nees": nees(r, sc.pose) if r.found else None,
            "iou": iou(r.window, sc.bbox) if r.window else 0.0, "occluded": sc.occluded,  # (the localisation's)
            "searched": r.searched, "cpu": cpu, **{k: r.time_ms.get(k, 0.0) for k in STAGES},
        })
    ok = np.array([row["dt"] <= 0.05 * diameter and row["dr"] <= 5.0 for row in rows])
    ang = np.array([row["angle"] for row in rows])
    found = np.array([row["found"] for row in rows])
    curve = []
    for lo, hi in zip(ANGLE_BINS[:-1], ANGLE_BINS[1:]):
        sel = (ang >= lo) & (ang < hi)
        curve.append({"from_deg": lo, "to_deg": hi, "scenes": int(sel.sum()),
                      "success": float(ok[sel].mean()) if sel.any() else None})
    within = ang <= 30.0
    dts = np.array([row["dt"] for row in rows])[found]
    drs = np.array([row["dr"] for row in rows])[found]
    ious = np.array([row["iou"] for row in rows])
    return {
        "scenes": n,
        "success": float(ok.mean()),
        "success_within_30deg": float(ok[within].mean()) if within.any() else None,
        "found": float(found.mean()),
        "wrong_when_found": float(((~ok) & found).sum() / max(found.sum(), 1)),
        "median_translation_error": float(np.median(dts)) if len(dts) else None,
        "median_translation_error_pct_diameter": float(100 * np.median(dts) / diameter) if len(dts) else None,
        "median_rotation_error_deg": float(np.median(drs)) if len(drs) else None,
        **nees_summary([row["nees"] for row in rows]),
        "window_iou_ge_0.5": float(np.mean(ious >= 0.5)),
        "window_iou_median": float(np.median(ious)),
        "fallback_to_whole_image": float(np.mean([row["searched"] == "image" for row in rows])),
        "curve": curve,
        "time_ms": {k: {"p50": _pct([row[k] for row in rows], 50), "p95": _pct([row[k] for row in rows], 95)} for k in STAGES},
        "cpu_ms": {"p50": _pct([row["cpu"] for row in rows], 50), "p95": _pct([row["cpu"] for row in rows], 95)},
    }


def negatives(model, camera) -> dict:
    index = index_for(model)
    found, times, cpus = [], [], []
    for bg in S.video_backgrounds():
        for img in (bg, np.ascontiguousarray(bg[:, ::-1])):
            r, cpu = _located(img, camera, model, LocateParams(), index)
            found.append(r.found)
            times.append(r.time_ms["total"])
            cpus.append(cpu)
    return {"images": len(found), "false_positives": int(np.sum(found)),
            "time_ms": {"p50": _pct(times, 50), "p95": _pct(times, 95)},
            "cpu_ms": {"p50": _pct(cpus, 50), "p95": _pct(cpus, 95)}}


def video(model, camera, every: int, sheet: str | None, progress: bool) -> dict:
    from tqdm import tqdm

    index = index_for(model)
    cap = cv2.VideoCapture(str(S.EXAMPLE / "box.mp4"))
    n_total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or 455
    rows, thumbs = [], []
    edges = mesh_edges(model.mesh)
    i = 0
    bar = tqdm(total=n_total, desc="box.mp4", disable=not progress, unit="frame")
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        bar.update(1)
        if i % every == 0:
            r, cpu = _located(frame, camera, model, LocateParams(), index)
            ref = locate(frame, camera, model, LocateParams(use_window=False), index=index)
            on_box = None
            if ref.found and r.window is not None:
                sil = render(model.mesh, camera, Pose(ref.q_wxyz, ref.t)).face >= 0
                cx = int(np.clip(r.window[0] + r.window[2] / 2, 0, frame.shape[1] - 1))
                cy = int(np.clip(r.window[1] + r.window[3] / 2, 0, frame.shape[0] - 1))
                on_box = bool(sil[cy, cx])
            rows.append({"frame": i, "found": r.found, "ref_found": ref.found, "on_box": on_box, "cpu": cpu,
                         **{k: r.time_ms.get(k, 0.0) for k in STAGES}})
            if sheet and i % (every * 5) == 0 and len(thumbs) < 30:
                g = frame.copy()
                if r.found:
                    draw_wireframe(g, camera, r.t, r.q_wxyz, edges, (0, 255, 0))
                if r.window:
                    x, y, w, h = (int(v) for v in r.window)
                    cv2.rectangle(g, (x, y), (x + w, y + h), (255, 128, 0), 2)
                draw_label(g, f"{i} {'found' if r.found else 'not found'} {r.inliers} inliers", colour=(0, 255, 255), scale=0.8)
                thumbs.append(cv2.resize(g, (320, 240)))
        i += 1
    bar.close()
    if sheet and thumbs:
        while len(thumbs) % 5:
            thumbs.append(np.zeros_like(thumbs[0]))
        grid = np.vstack([np.hstack(thumbs[k : k + 5]) for k in range(0, len(thumbs), 5)])
        Path(sheet).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(sheet), grid)
    on = [row["on_box"] for row in rows if row["on_box"] is not None]
    return {
        "frames": len(rows), "every": every,
        "found": float(np.mean([row["found"] for row in rows])),
        "found_whole_image": float(np.mean([row["ref_found"] for row in rows])),
        "window_centre_on_box": float(np.mean(on)) if on else None,
        "time_ms": {k: {"p50": _pct([row[k] for row in rows], 50), "p95": _pct([row[k] for row in rows], 95)} for k in STAGES},
        "cpu_ms": {"p50": _pct([row["cpu"] for row in rows], 50), "p95": _pct([row["cpu"] for row in rows], 95)},
        "sheet": sheet,
    }


OTHER_CAMERAS = (("grey", 1.0, True), ("3x", 3.0, False), ("half", 0.5, False))  # (name, scale, grey)


def other_cameras(model, camera, every: int = 15, progress: bool = False) -> dict:
    """``box.mp4``'s every ``every``-th frame as :data:`OTHER_CAMERAS` give it (resized with the
    camera scaled, pixel centres kept; grey: one channel): per camera, the share of frames with a
    verified pose (``found``), the median distance of its pose from the colour 640 × 480 frame's
    (``diff_p50_pct`` of the diameter, ``diff_p50_deg``) and the share within 5 %/5° of it
    (``agree``; both of the frames where both were found), and the time. No ground truth: the
    colour frame's pose is the reference, itself 0.5–2° uncertain in this video (its reported σ;
    the video's own figures are above)."""
    from tqdm import tqdm

    index = index_for(model)
    cap = cv2.VideoCapture(str(S.EXAMPLE / "box.mp4"))
    frames, i = [], 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        if i % every == 0:
            frames.append(frame)
        i += 1
    cap.release()
    refs = [locate(f, camera, model, LocateParams(), index=index) for f in frames]
    d = float(model.mesh.extent)
    out: dict = {"frames": len(frames), "every": every, "colour_found": float(np.mean([r.found for r in refs]))}
    for name, k, grey in tqdm(OTHER_CAMERAS, desc="other cameras", disable=not progress, unit="camera"):
        cam = camera if k == 1.0 else camera.scaled(k)
        found, dts, drs, times, cpus = [], [], [], [], []
        for f, ref in zip(frames, refs):
            img = f if k == 1.0 else cv2.resize(f, (cam.width, cam.height),
                                                interpolation=cv2.INTER_CUBIC if k > 1 else cv2.INTER_AREA)
            if grey:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            r, cpu = _located(img, cam, model, LocateParams(), index)
            found.append(r.found)
            times.append(r.time_ms["total"])
            cpus.append(cpu)
            if r.found and ref.found:
                dt, dr = S.pose_errors(r.t, r.q_wxyz, Pose(ref.q_wxyz, ref.t), model.mesh)
                dts.append(100 * dt / d)
                drs.append(dr)
        both = np.array(dts) <= 5.0, np.array(drs) <= 5.0
        out[name] = {"scale": k, "grey": grey, "found": float(np.mean(found)),
                     "diff_p50_pct": _pct(dts, 50), "diff_p50_deg": _pct(drs, 50),
                     "agree": float(np.mean(both[0] & both[1])) if dts else None,
                     "time_ms": {"p50": _pct(times, 50), "p95": _pct(times, 95)},
                     "cpu_ms": {"p50": _pct(cpus, 50), "p95": _pct(cpus, 95)}}
    return out


def run(scenes: int = 200, seed: int = 0, every: int = 3, sheet: str | None = None, progress: bool = True) -> dict:
    model = S.example_model()
    camera = load_camera(S.EXAMPLE / "camera.json")
    index_for(model)._matcher()  # build the index before timing anything
    return {
        "rendered": rendered(scenes, seed, model, camera, progress),
        "negatives": negatives(model, camera),
        "video": video(model, camera, every, sheet, progress),
        "cameras": other_cameras(model, camera, progress=progress),
    }


def _share(x: float | None, digits: int = 0) -> str:
    return "-" if x is None else f"{100 * x:.{digits}f} %"


def _num(x: float | None, fmt: str) -> str:
    """``x`` formatted, or "-" when there is nothing to report (no scene found, say)."""
    return "-" if x is None else format(x, fmt)


def format_report(s: dict) -> str:
    r, n, v = s["rendered"], s["negatives"], s["video"]
    lines = [f"Rendered scenes ({r['scenes']}, 0–60° from the registered view):",
             f"  success {100 * r['success']:.1f} % (within 30°: {_share(r['success_within_30deg'], 1)}), "
             f"found {100 * r['found']:.1f} %, wrong when found {100 * r['wrong_when_found']:.1f} %",
             f"  median error {_num(r['median_translation_error_pct_diameter'], '.2f')} % of diameter, "
             f"{_num(r['median_rotation_error_deg'], '.2f')}°; window IoU ≥ 0.5 in {100 * r['window_iou_ge_0.5']:.0f} % "
             f"(median {r['window_iou_median']:.2f}); whole-image fallback in {100 * r['fallback_to_whole_image']:.0f} %",
             f"  the found poses' covariance: NEES median {_num(r.get('nees_p50'), '.2f')} (χ²₆'s 5.35), "
             f"{_share(r.get('nees_in95'), 1)} of the truths within the reported 95 % ellipsoid",
             "  success by angle: " + ", ".join(f"{c['from_deg']}–{c['to_deg']}°: {_share(c['success'])} ({c['scenes']})"
                                                 for c in r["curve"])]
    for name, block in (("rendered", r), ("box.mp4", v)):
        lines.append(f"  time {name}: " + ", ".join(
            f"{k} p50 {block['time_ms'][k]['p50']:.1f} / p95 {block['time_ms'][k]['p95']:.1f} ms" for k in STAGES)
            + f"; CPU p50 {block['cpu_ms']['p50']:.1f} / p95 {block['cpu_ms']['p95']:.1f} ms")
    lines += [f"Negatives: {n['false_positives']} of {n['images']} background images gave a pose; "
              f"p50 {n['time_ms']['p50']:.0f} ms (CPU {n['cpu_ms']['p50']:.0f} ms)",
              f"box.mp4 (every {v['every']}. frame, {v['frames']} frames): verified pose in {100 * v['found']:.1f} % "
              f"(whole-image search: {100 * v['found_whole_image']:.1f} %), window centre on the box in "
              f"{_share(v['window_centre_on_box'], 1)}" + (f"; contact sheet {v['sheet']}" if v["sheet"] else "")]
    c = s.get("cameras")
    if c:
        lines.append(f"box.mp4 as other cameras give it (every {c['every']}. frame, {c['frames']} frames; colour "
                     f"640 × 480: {_share(c['colour_found'], 1)}):")
        for name, k, grey in OTHER_CAMERAS:
            b = c[name]
            lines.append(f"  {'grey' if grey else 'colour'} ×{k:g}: verified pose in {_share(b['found'], 1)}, "
                         f"{_num(b['diff_p50_pct'], '.2f')} % / {_num(b['diff_p50_deg'], '.2f')}° from the colour "
                         f"frame's pose (median), within 5 %/5° of it in {_share(b['agree'], 1)}; "
                         f"p50 {_num(b['time_ms']['p50'], '.0f')} / p95 {_num(b['time_ms']['p95'], '.0f')} ms "
                         f"(CPU p50 {_num(b['cpu_ms']['p50'], '.0f')} ms)")
    return "\n".join(lines)


def main(scenes: int, seed: int, every: int, sheet: str | None, as_json: bool) -> int:
    t0 = time.perf_counter()
    summary = run(scenes, seed, every, sheet, progress=not as_json)
    summary["wall_s"] = time.perf_counter() - t0
    print(json.dumps(summary) if as_json else format_report(summary))
    return 0


# -- the zoo (issue 13): other objects, units, grey, out of frame, far from the training views -----

ZOO_OUTSIDE = (0.0, 0.2, 0.4, 0.6)
ZOO_ANGLES = (0.0, 15.0, 30.0, 45.0, 60.0)


def _nearest_view_angle(pose, train_poses, centre) -> float:
    from quatrack.recognition.pose import view_angle_deg

    return min(view_angle_deg(pose.R, pose.t, p.R, p.t, centre) for p in train_poses)


def _judge(r, pose, mesh) -> str:
    """"correct" (≤ 5 % of the diameter and ≤ 5°), "wrong" or "missed"."""
    if not r.found:
        return "missed"
    dt, dr = S.pose_errors(r.t, r.q_wxyz, pose, mesh)
    return "correct" if dt <= 0.05 * mesh.extent and dr <= 5.0 else "wrong"


def zoo_models(objects, views=(1, 4), greys=(False, True), progress: bool = False, cache: str | Path | None = None):
    """Train every (object, n_views, grey) of the zoo once, in a temporary directory:
    ``{(name, n_views, grey): (model, training poses)}``. ``cache``: a directory where trained
    models are kept (a model store per variant) and reused by later runs."""
    import tempfile

    from tqdm import tqdm

    from quatrack.viewsets.spec import load_spec
    from quatrack.viewsets.store import load_model, save_model
    from quatrack.viewsets.train import train_object

    from quatrack.testing import zoo as Z

    out = {}
    jobs = [(o, v, g) for o in objects for v in views for g in greys]
    with tempfile.TemporaryDirectory(prefix="quatrack-zoo-") as tmp:
        for name, v, g in tqdm(jobs, desc="training zoo models", disable=not progress, unit="model"):
            tag = f"{name}-{v}-{'grey' if g else 'colour'}"
            seed = len(out)
            poses = Z.training_poses(Z.textured(name), Z.zoo_camera(), v)
            store = None if cache is None else Path(cache) / f"{tag}-s{seed}"
            if store is not None and (store / name).is_dir():
                out[(name, v, g)] = (load_model(store, name), poses)
                continue
            spec = load_spec(Z.write_spec(name, Path(tmp) / tag, v, g, seed=seed))
            model = train_object(spec)
            if store is not None:
                save_model(store, model)
            out[(name, v, g)] = (model, [vw.pose for vw in spec.views])
    return out


def zoo_scenes(models: dict, scenes_per_model: int, seed: int, progress: bool = False, bgs=None, rng=None):
    """The zoo's scenes, deterministic for a seed: per trained model, ``scenes_per_model`` scenes
    cycling through the out-of-frame shares and the angles from a training view. Yields
    ``(key, model, scene, row)``, ``row`` describing the scene (object, unit, views, grey,
    outside, angle from the nearest training view, seed and scene number)."""
    from tqdm import tqdm

    from quatrack.testing import zoo as Z

    cam = Z.zoo_camera()
    bgs = Z.real_backgrounds() if bgs is None else bgs
    rng = np.random.default_rng(seed) if rng is None else rng
    cv2.setRNGSeed(seed)  # (kept for any OpenCV draw; RANSAC seeds its own RNG per call, FLANN its forest in its thread)
    for key, (model, train_poses) in tqdm(models.items(), desc="zoo scenes", disable=not progress, unit="model"):
        name, views, grey = key
        obj = Z.textured(name)
        for k in range(scenes_per_model):
            outside = ZOO_OUTSIDE[k % len(ZOO_OUTSIDE)]
            angle = ZOO_ANGLES[(k // len(ZOO_OUTSIDE) + k) % len(ZOO_ANGLES)]
            base = train_poses[int(rng.integers(len(train_poses)))]
            sc = Z.random_scene(rng, obj, cam, base, bgs, angle, outside, grey)
            yield key, model, sc, {
                "object": name, "unit": obj.obj.unit, "views": views, "grey": grey, "outside": sc.outside,
                "angle": _nearest_view_angle(sc.pose, train_poses, obj.mesh.centre), "seed": seed, "scene": k,
            }


def located_row(r, pose, mesh) -> dict:
    """One locate answer judged against the truth: result, errors (% of the diameter, degrees),
    the found pose's NEES (``eᵀ C⁻¹ e`` of its error under its reported covariance over
    ``[p, δθ]``: :func:`~quatrack.bench.track_zoo.nees`), time, confidence, the verification's
    evidence, why not found."""
    dt, dr = S.pose_errors(r.t, r.q_wxyz, pose, mesh) if r.found else (None, None)
    return {"result": _judge(r, pose, mesh), "dt_pct": None if dt is None else float(100 * dt / mesh.extent),
            "dr_deg": None if dr is None else float(dr), "nees": nees(r, pose) if r.found else None,
            "ms": r.time_ms["total"],
            "pnp_ms": r.time_ms.get("pnp", 0.0), "confidence": r.confidence,
            "verification": r.verification, "reason": r.reason, "searched": r.searched}


def group_table(rows: list[dict]) -> dict:
    """Per group of zoo scenes (all; unit; colour or grey; 1 or 4 photos; share outside the
    frame; angle from the nearest training view; object): the shares found and correct, found
    but wrong and not found, the found poses' median and 90th-percentile errors (% of the
    diameter, degrees; None when none was found), how honest their covariances are (the NEES's
    median, χ²₆'s is 5.35, and the share of poses whose truth lies within the reported 95 %
    ellipsoid, ``nees_in95``; rows without ``nees`` count as not measured) and the times
    (p50/p95, wall clock and CPU).

    >>> rows = [{"unit": "cm", "grey": False, "views": 1, "outside": 0.0, "angle": 10.0, "object": "a",
    ...          "result": res, "dt_pct": dt, "dr_deg": dr, "nees": e, "ms": 50.0, "pnp_ms": 10.0, "cpu_ms": 60.0}
    ...         for res, dt, dr, e in (("correct", 0.1, 0.2, 2.0), ("correct", 0.3, 0.4, 20.0),
    ...                                ("missed", None, None, None))]
    >>> t = group_table(rows)["all"]
    >>> t["scenes"], round(t["correct"], 3), round(t["err_p50_pct"], 3), round(t["err_p50_deg"], 3)
    (3, 0.667, 0.2, 0.3)
    >>> t["nees_p50"], t["nees_in95"]  # (one of the two found poses' truths beyond its 95 % ellipsoid)
    (11.0, 0.5)
    >>> group_table(rows[2:])["all"]["err_p50_pct"] is None  # (nothing found)
    True
    """
    groups = {
        "all": lambda row: True,
        **{f"unit {u}": (lambda u: lambda row: row["unit"] == u)(u) for u in ("mm", "cm", "m")},
        "colour": lambda row: not row["grey"], "grey": lambda row: row["grey"],
        "1 photo": lambda row: row["views"] == 1, "4 photos": lambda row: row["views"] == 4,
        **{f"outside {lo:.0%}–{hi:.0%}": (lambda lo, hi: lambda row: lo <= row["outside"] < hi)(lo, hi)
           for lo, hi in ((0.0, 0.1), (0.1, 0.3), (0.3, 0.5), (0.5, 0.7))},
        **{f"angle {lo}–{hi}°": (lambda lo, hi: lambda row: lo <= row["angle"] < hi)(lo, hi)
           for lo, hi in ((0, 15), (15, 30), (30, 45), (45, 61))},
        **{f"object {o}": (lambda o: lambda row: row["object"] == o)(o) for o in sorted({r["object"] for r in rows})},
    }
    table = {}
    for g, sel in groups.items():
        rs = [row for row in rows if sel(row)]
        if not rs:
            continue
        n = len(rs)
        table[g] = {
            "scenes": n,
            "correct": sum(r["result"] == "correct" for r in rs) / n,
            "wrong": sum(r["result"] == "wrong" for r in rs) / n,
            "missed": sum(r["result"] == "missed" for r in rs) / n,
            "p50_ms": _pct([r["ms"] for r in rs], 50), "p95_ms": _pct([r["ms"] for r in rs], 95),
            "pnp_p50_ms": _pct([r["pnp_ms"] for r in rs], 50), "pnp_p95_ms": _pct([r["pnp_ms"] for r in rs], 95),
            "cpu_p50_ms": _pct([r["cpu_ms"] for r in rs], 50), "cpu_p95_ms": _pct([r["cpu_ms"] for r in rs], 95),
            **_found_errors([r for r in rs if r["result"] != "missed"]),
        }
    return table


def _found_errors(found: list[dict]) -> dict:
    """The found poses' errors: median and 90th percentile, % of the diameter and degrees; their
    NEES's median and the share within the reported 95 % ellipsoid (:func:`nees_summary`)."""
    dt, dr = [r["dt_pct"] for r in found], [r["dr_deg"] for r in found]
    return {"err_p50_pct": _pct(dt, 50), "err_p90_pct": _pct(dt, 90),
            "err_p50_deg": _pct(dr, 50), "err_p90_deg": _pct(dr, 90),
            **nees_summary([r.get("nees") for r in found])}


def nees_summary(values) -> dict:
    """How honest reported covariances are, from the NEES of each pose (None: not measured):
    ``nees_p50``, the median (χ²₆'s is 5.35), and ``nees_in95``, the share of poses whose truth
    lies within the reported 95 % ellipsoid (NEES < χ²₆'s 95 % quantile, 12.59); None when none
    was measured.

    >>> nees_summary([1.0, 3.0, 20.0, None])
    {'nees_p50': 3.0, 'nees_in95': 0.6666666666666666}
    >>> nees_summary([None])
    {'nees_p50': None, 'nees_in95': None}
    """
    e = [v for v in values if v is not None]
    return {"nees_p50": _pct(e, 50), "nees_in95": (sum(v < NEES_95 for v in e) / len(e)) if e else None}


def zoo(models: dict, scenes_per_model: int, seed: int, progress: bool, params: LocateParams | None = None) -> dict:
    """Per group: found and correct, found but wrong, not found, time p50/p95; plus scenes with no
    object (every model searched) and scenes with two objects (``locate_all``)."""
    from quatrack.recognition.locate import locate_all

    from quatrack.testing import zoo as Z

    params = params or LocateParams()
    cam = Z.zoo_camera()
    bgs = Z.real_backgrounds()
    rng = np.random.default_rng(seed)
    rows = []
    for key, model, sc, row in zoo_scenes(models, scenes_per_model, seed, progress, bgs, rng):
        r, cpu = _located(sc.image, cam, model, params, index_for(model))
        rows.append({**row, **located_row(r, sc.pose, model.mesh), "cpu_ms": cpu})
    table = group_table(rows)
    # calibration of the confidence on the reported poses
    found = [r for r in rows if r["result"] != "missed"]
    calib = []
    for lo, hi in ((0.0, 0.5), (0.5, 0.8), (0.8, 0.95), (0.95, 1.01)):
        rs = [r for r in found if lo <= r["confidence"] < hi]
        calib.append({"from": lo, "to": min(hi, 1.0), "poses": len(rs),
                      "correct": (sum(r["result"] == "correct" for r in rs) / len(rs)) if rs else None})
    # no object: every colour model searched in plain backgrounds
    colour1 = [(k, v) for k, v in models.items() if k[1] == 1 and not k[2]]
    neg_found, neg_ms, neg_cpu = 0, [], []
    for bg in bgs[::4]:
        for flip in (False, True):
            img = np.ascontiguousarray(bg[:, ::-1]) if flip else bg
            t0, c0 = time.perf_counter(), time.process_time()
            res = locate_all(img, cam, [m for _, (m, _) in colour1])
            neg_ms.append((time.perf_counter() - t0) * 1e3)
            neg_cpu.append((time.process_time() - c0) * 1e3)
            neg_found += sum(r.found for r in res)
    # two objects side by side, every colour single-photo model searched
    two = {"scenes": 0, "objects": 0, "correct": 0, "wrong": 0, "missed": 0, "false_reports": 0, "ms": [], "cpu": []}
    names = [k[0] for k, _ in colour1]
    for k in range(min(len(names), 6)):
        a, b = names[k], names[(k + 1) % len(names)]
        if a == b:
            continue
        img, truths = Z.two_object_scene(rng, a, b, {kk[0]: v for kk, v in colour1}, cam, bgs)
        t0, c0 = time.perf_counter(), time.process_time()
        res = locate_all(img, cam, [m for _, (m, _) in colour1])
        two["ms"].append((time.perf_counter() - t0) * 1e3)
        two["cpu"].append((time.process_time() - c0) * 1e3)
        two["scenes"] += 1
        for r in res:
            if r.object in truths:
                two["objects"] += 1
                two[_judge(r, truths[r.object], r_model(colour1, r.object).mesh)] += 1
            elif r.found:
                two["false_reports"] += 1
    two["p50_ms"], two["p95_ms"] = _pct(two["ms"], 50), _pct(two["ms"], 95)
    two["cpu_p50_ms"], two["cpu_p95_ms"] = _pct(two["cpu"], 50), _pct(two["cpu"], 95)
    del two["ms"], two["cpu"]
    return {"groups": table, "calibration": calib,
            "no_object": {"images": 2 * len(bgs[::4]), "models_searched": len(colour1), "false_reports": neg_found,
                          "p50_ms": _pct(neg_ms, 50), "p95_ms": _pct(neg_ms, 95),
                          "cpu_p50_ms": _pct(neg_cpu, 50), "cpu_p95_ms": _pct(neg_cpu, 95)},
            "two_objects": two, "rows": rows,
            "wrong": [{k: r[k] for k in ("object", "views", "grey", "outside", "angle", "seed", "scene", "dt_pct",
                                         "dr_deg", "confidence", "verification")} for r in rows if r["result"] == "wrong"]}


def r_model(models, name):
    return next(v[0] for k, v in models if k[0] == name)


def format_zoo(z: dict) -> str:
    lines = ["Zoo (found and correct / found but wrong / not found, the found poses' median error, time p50/p95):"]
    for g, t in z["groups"].items():
        lines.append(f"  {g:<24} {t['scenes']:>4} scenes  correct {100 * t['correct']:5.1f} %  wrong {100 * t['wrong']:4.1f} %  "
                     f"not found {100 * t['missed']:5.1f} %  error {_num(t.get('err_p50_pct'), '.2f')} % / "
                     f"{_num(t.get('err_p50_deg'), '.2f')}°  {t['p50_ms']:.0f}/{t['p95_ms']:.0f} ms "
                     f"(CPU {t['cpu_p50_ms']:.0f}/{t['cpu_p95_ms']:.0f})")
    lines.append(f"  pnp stage (PnP + verification): p50 {z['groups']['all']['pnp_p50_ms']:.1f} / "
                 f"p95 {z['groups']['all']['pnp_p95_ms']:.1f} ms")
    a = z["groups"]["all"]
    if a.get("nees_in95") is not None:
        lines.append(f"  the found poses' covariance: NEES median {_num(a['nees_p50'], '.2f')} (χ²₆'s 5.35), "
                     f"{_share(a['nees_in95'], 1)} of the truths within the reported 95 % ellipsoid")
    for w in z.get("wrong", []):
        v = w["verification"] or {}
        lines.append(f"  wrong: {w['object']} {w['views']} photo{'s' if w['views'] > 1 else ''} "
                     f"{'grey' if w['grey'] else 'colour'} scene {w['scene']} (seed {w['seed']}): {w['dt_pct']:.1f} % / "
                     f"{w['dr_deg']:.1f}° off, {100 * w['outside']:.0f} % outside, {w['angle']:.0f}° from a view; "
                     f"confidence {w['confidence']:.2f}, " + ", ".join(
                         f"{k} {v[k]}" for k in ("inliers", "inlier_faces", "edge_agreement", "edge_chance", "edge_weakest",
                                                 "inlier_spread", "sd_ratio", "rival_inliers", "edge_shift") if k in v))
    lines.append("  confidence vs share correct: " + ", ".join(
        f"[{c['from']:.2f}, {c['to']:.2f}): {c['poses']} poses, {_share(c['correct'])}" for c in z["calibration"]))
    n = z["no_object"]
    lines.append(f"  no object: {n['false_reports']} reports in {n['images']} images × {n['models_searched']} models; "
                 f"p50 {n['p50_ms']:.0f} / p95 {n['p95_ms']:.0f} ms for all models (CPU {n['cpu_p50_ms']:.0f} / "
                 f"{n['cpu_p95_ms']:.0f})")
    t = z["two_objects"]
    if t["scenes"]:
        lines.append(f"  two objects: {t['scenes']} scenes, {t['objects']} objects: correct {t['correct']}, wrong {t['wrong']}, "
                     f"not found {t['missed']}, other objects reported {t['false_reports']}; p50 {t['p50_ms']:.0f} / "
                     f"p95 {t['p95_ms']:.0f} ms for all models (CPU {t['cpu_p50_ms']:.0f} / {t['cpu_p95_ms']:.0f})")
    return "\n".join(lines)


def main_zoo(objects: list[str] | None, scenes: int, seed: int, as_json: bool, cache: str | None = None) -> int:
    """``cache``: keep the trained models there and reuse them (``zoo_models``)."""
    from quatrack.testing import zoo as Z

    t0 = time.perf_counter()
    names = objects or [o.name for o in Z.ZOO]
    models = zoo_models(names, progress=not as_json, cache=cache)
    z = zoo(models, scenes, seed, progress=not as_json)
    z["wall_s"] = time.perf_counter() - t0
    if as_json:
        print(json.dumps({k: v for k, v in z.items() if k != "rows"}))
    else:
        print(format_zoo(z))
    return 0

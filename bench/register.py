"""``quatrack bench register``: how near the truth a photo registered from clicked corners is.

For each zoo object (:mod:`quatrack.testing.zoo`: boxes of several proportions, a cylinder, a
prism; meshes in mm, cm and m; real photographs as texture) and each of ``photos`` seeds, the
object's training photo is rendered at a known pose, up to 8 of its visible corners are
"clicked" with Gaussian noise of ``noise`` px per axis (:func:`quatrack.testing.clicks.zoo_clicks`),
and the pose is registered as ``quatrack register`` does: PnP from the clicks
(:func:`~quatrack.viewsets.register.pose_from_points`), then the refit to the mesh's edges
(:func:`~quatrack.recognition.registration.refine_with_edges`). Reported per noise level: the errors of
both against the truth (centre, % of the diameter; rotation, degrees: median, 90th percentile,
max), how many refits were kept, and the time per view.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def run(objects=None, photos: int = 4, noises=(1.0, 2.0, 4.0), grey: bool = False, progress: bool = True) -> dict:
    from quatrack.testing import zoo as Z
    from quatrack.testing.clicks import zoo_clicks
    from quatrack.testing.scenes import pose_errors
    from quatrack.recognition.registration import refine_with_edges
    from quatrack.viewsets.register import pose_from_points

    names = list(objects) if objects else [o.name for o in Z.ZOO]
    out = {"objects": names, "photos": photos, "grey": grey, "noise": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for noise in noises:
            rows, kept, ms = [], 0, []
            for name in names:
                for seed in range(photos):
                    spec, view, mesh, pairs = zoo_clicks(name, Path(tmp) / f"{name}-{seed}", seed, noise, grey=grey)
                    grey_img = cv2.imread(str(view.image_path), cv2.IMREAD_GRAYSCALE)
                    t0 = time.perf_counter()
                    reg0 = pose_from_points(pairs, view.camera)
                    reg = refine_with_edges(grey_img, mesh, view.camera, reg0, pairs)  # (σ: the default, as the command)
                    ms.append(1e3 * (time.perf_counter() - t0))
                    kept += reg.moved is not None
                    d = float(mesh.extent)
                    e0 = pose_errors(reg0.pose.t, reg0.pose.q_wxyz, view.pose, mesh)
                    e1 = pose_errors(reg.pose.t, reg.pose.q_wxyz, view.pose, mesh)
                    rows.append((100 * e0[0] / d, e0[1], 100 * e1[0] / d, e1[1]))
            if progress:
                print(f"  noise {noise:g} px: {len(rows)} photos", flush=True)
            r = np.array(rows)

            def stats(col):
                return [round(float(np.median(r[:, col])), 2), round(float(np.percentile(r[:, col], 90)), 2),
                        round(float(r[:, col].max()), 2)]

            out["noise"][f"{noise:g}"] = {"views": len(rows), "refits_kept": kept,
                                          "pnp_pct": stats(0), "pnp_deg": stats(1), "edges_pct": stats(2), "edges_deg": stats(3),
                                          "ms_p50": round(float(np.median(ms)), 1)}
    return out


def report(res: dict) -> str:
    lines = [f"Photos registered from clicked corners ({len(res['objects'])} zoo objects × {res['photos']} photos"
             f"{', grey' if res['grey'] else ''}); error against the truth: median / 90th percentile / max", ""]
    head = ["click noise (px)", "PnP: % of diameter", "PnP: degrees", "with edges: % of diameter", "with edges: degrees",
            "refits kept", "ms per view (p50)"]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("| " + " | ".join("---" for _ in head) + " |")
    fmt = lambda v: " / ".join(f"{x:g}" for x in v)  # noqa: E731
    for noise, r in res["noise"].items():
        lines.append("| " + " | ".join([noise, fmt(r["pnp_pct"]), fmt(r["pnp_deg"]), fmt(r["edges_pct"]),
                                         fmt(r["edges_deg"]), f"{r['refits_kept']} of {r['views']}", f"{r['ms_p50']:g}"]) + " |")
    return "\n".join(lines)


def main(objects=None, photos: int = 4, noises=(1.0, 2.0, 4.0), grey: bool = False, as_json: bool = False) -> int:
    res = run(objects, photos, noises, grey, progress=not as_json)
    print(json.dumps(res) if as_json else report(res))
    return 0

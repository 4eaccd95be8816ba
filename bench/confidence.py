"""Fit the locate confidence (issue 13): ``python -m quatrack.bench.confidence``.

``confidence`` in the locate JSON is meant as the probability that the reported pose is right
(centre within 5 % of the diameter, rotation within 5°). It is a logistic regression on the
verification's evidence (:data:`quatrack.recognition.pose.CONFIDENCE_FEATURES`); this script
fits it and checks it:

1. **Collect**: zoo scenes (every object, 1 and 4 photos, colour and grey; :mod:`quatrack.bench.locate`)
   and cookie-box scenes (:mod:`quatrack.testing.scenes`) of one seed, located with the image
   evidence *relaxed* (no edge, spread, rival, covariance or confidence threshold: every pose
   that passes the geometric checks is reported), so wrong poses are there to learn from; each
   pose is judged against the truth and its evidence kept.
2. **Fit**: ``P(right) = σ(wᵀx)`` by iteratively reweighted least squares (Newton's method on
   the log-likelihood) with a small ridge on the standardised features; a feature whose weight
   comes out with the sign the evidence cannot have (more edge agreement making a pose *less*
   likely right) is dropped and the fit redone, so the confidence is monotone in every piece of
   evidence.
3. **Check** on scenes of another seed: a reliability table (confidence bin → share right),
   the Brier score, and what each ``min_confidence`` would keep (right and wrong poses).

The coefficients printed go into ``CONFIDENCE_COEF`` in ``recognition/pose.py``.
``--rows PREFIX`` keeps the collected rows (JSON lines, one file per seed), ``--collect-only SEED``
only collects, and ``--from-rows PREFIX`` refits from files written before.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from quatrack.recognition.locate import LocateParams, locate
from quatrack.recognition.match import index_for
from quatrack.recognition.pose import CONFIDENCE_FEATURES, PoseParams, confidence, confidence_features

# the sign each weight must have (+1: more of it, more likely right); the bias is free
SIGNS = {"bias": 0, "lead": 1, "agreement": 1, "weakest": 1, "log_inliers": 1, "spread": 1, "faces": 1,
         "log_sd_ratio": -1, "rival_ratio": -1, "log_edge_shift": -1}
BINS = (0.0, 0.2, 0.5, 0.8, 0.9, 0.95, 1.0 + 1e-9)


def relaxed(params: PoseParams = PoseParams()) -> PoseParams:
    """Verification without the image-evidence thresholds: every geometrically valid pose is
    reported (with its evidence)."""
    return replace(params, min_edge_agreement=0.0, min_edge_lead=-1.0, min_weakest_edge=0.0, min_spread=0.0, max_rival_ratio=math.inf,
                   max_sd_ratio=math.inf, max_sd_ratio_one_face=math.inf, min_confidence=0.0)


def features_of(v: dict) -> dict[str, float]:
    """The confidence's inputs from a locate answer's ``verification`` JSON."""
    return confidence_features(v["edge_agreement"] - v["edge_chance"], v["edge_agreement"], v["edge_weakest"],
                               v["inliers"], v["inlier_spread"], v["inlier_faces"], v["sd_ratio"], v["rival_inliers"],
                               math.inf if v.get("edge_shift", 0.0) is None else v.get("edge_shift", 0.0))


def collect(seed: int, zoo_scenes: int, cookie_scenes: int, objects=None, cache: str | None = None,
            progress: bool = True) -> list[dict]:
    """Rows ``{source, result, dt_pct, dr_deg, verification, ...}`` for every pose reported with
    the evidence relaxed (missed scenes are left out: they carry no pose to judge)."""
    from tqdm import tqdm

    from quatrack.bench import locate as B
    from quatrack.testing import scenes as S
    from quatrack.testing import zoo as Z
    from quatrack.viewsets.camera import load_camera

    params = LocateParams(pose=relaxed())
    rows = []
    if zoo_scenes > 0:
        names = objects or [o.name for o in Z.ZOO]
        models = B.zoo_models(names, progress=progress, cache=cache)
        cam = Z.zoo_camera()
        for key, model, sc, row in B.zoo_scenes(models, zoo_scenes, seed, progress):
            r = locate(sc.image, cam, model, params, index=index_for(model))
            rows.append({"source": "zoo", **row, **B.located_row(r, sc.pose, model.mesh)})
    if cookie_scenes > 0:
        model = S.example_model()
        camera = load_camera(S.EXAMPLE / "camera.json")
        renderer = S.Renderer.from_spec(S.EXAMPLE / "object.json")
        backgrounds = S.video_backgrounds()
        rng = np.random.default_rng(seed)
        for k in tqdm(range(cookie_scenes), desc="cookie-box scenes", disable=not progress, unit="scene"):
            sc = S.random_scene(rng, renderer, camera, backgrounds)
            r = locate(sc.image, camera, model, params, index=index_for(model))
            rows.append({"source": "cookie-box", "object": "cookie-box", "views": 1, "grey": False, "outside": 0.0,
                         "angle": sc.view_angle_deg, "seed": seed, "scene": k, **B.located_row(r, sc.pose, model.mesh)})
    return [r for r in rows if r["result"] != "missed" and r["verification"]]


def design(rows: list[dict], names=CONFIDENCE_FEATURES) -> tuple[np.ndarray, np.ndarray]:
    X = np.array([[features_of(r["verification"])[k] for k in names] for r in rows], float).reshape(-1, len(names))
    y = np.array([r["result"] == "correct" for r in rows], float)
    return X, y


def fit_logistic(X: np.ndarray, y: np.ndarray, ridge: float = 1.0, iterations: int = 50) -> np.ndarray:
    """Weights maximising Σ log-likelihood − ½·ridge·‖w‖² over the standardised columns (the
    first column is the bias: neither standardised nor penalised), by Newton's method (IRLS):
    ``w ← w + (XᵀWX + λI)⁻¹ (Xᵀ(y − p) − λw)``, ``W = diag(p(1 − p))``."""
    mu = X[:, 1:].mean(axis=0)
    sd = X[:, 1:].std(axis=0)
    sd[sd < 1e-9] = 1.0
    Z = np.column_stack([np.ones(len(X)), (X[:, 1:] - mu) / sd])
    w = np.zeros(Z.shape[1])
    L = ridge * np.eye(Z.shape[1])
    L[0, 0] = 0.0
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-np.clip(Z @ w, -50, 50)))
        H = Z.T @ (Z * (p * (1 - p))[:, None]) + L + 1e-9 * np.eye(len(w))
        step = np.linalg.solve(H, Z.T @ (y - p) - L @ w)
        w += step
        if np.max(np.abs(step)) < 1e-8:
            break
    coef = np.empty_like(w)
    coef[1:] = w[1:] / sd
    coef[0] = w[0] - np.sum(w[1:] * mu / sd)
    return coef


def fit(rows: list[dict], ridge: float = 1.0) -> tuple[tuple[str, float], ...]:
    """The sign-constrained fit: features whose weight has the wrong sign are dropped in turn."""
    names = list(CONFIDENCE_FEATURES)
    X, y = design(rows)
    if len(set(y)) < 2:
        raise ValueError("the rows are all right or all wrong: nothing to fit")
    keep = list(range(len(names)))
    while True:
        coef = fit_logistic(X[:, keep], y, ridge)
        bad = [(abs(c), i) for c, i in zip(coef, keep) if SIGNS[names[i]] * c < 0]
        if not bad:
            return tuple((names[i], float(f"{c:.4g}")) for c, i in zip(coef, keep))
        keep.remove(max(bad)[1])


def reliability(rows: list[dict], coef=()) -> dict:
    """Confidence bins → poses and share right; the Brier score and the log-loss."""
    p = np.array([confidence(features_of(r["verification"]), coef) for r in rows])
    y = np.array([r["result"] == "correct" for r in rows], float)
    table = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = (p >= lo) & (p < hi)
        table.append({"from": lo, "to": min(hi, 1.0), "poses": int(sel.sum()),
                      "mean_confidence": float(p[sel].mean()) if sel.any() else None,
                      "right": float(y[sel].mean()) if sel.any() else None})
    eps = 1e-6
    keep = [{"min_confidence": t, "right": int(((p >= t) & (y == 1)).sum()), "wrong": int(((p >= t) & (y == 0)).sum())}
            for t in (0.0, 0.5, 0.7, 0.8, 0.9, 0.95)]
    return {"poses": len(rows), "right": int(y.sum()), "brier": float(np.mean((p - y) ** 2)),
            "log_loss": float(-np.mean(y * np.log(p + eps) + (1 - y) * np.log(1 - p + eps))),
            "table": table, "kept": keep}


def format_reliability(name: str, rel: dict) -> str:
    lines = [f"{name}: {rel['poses']} poses, {rel['right']} right; Brier {rel['brier']:.3f}, log-loss {rel['log_loss']:.3f}"]
    for b in rel["table"]:
        if b["poses"]:
            lines.append(f"  confidence [{b['from']:.2f}, {b['to']:.2f}): {b['poses']:4d} poses, mean "
                         f"{b['mean_confidence']:.2f}, right {100 * b['right']:.0f} %")
    lines.append("  kept at min_confidence: " + ", ".join(f"{k['min_confidence']}: {k['right']} right / {k['wrong']} wrong"
                                                        for k in rel["kept"]))
    return "\n".join(lines)


def _read(path: str) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m quatrack.bench.confidence", description=__doc__.split("\n\n")[0])
    ap.add_argument("--fit-seed", type=int, default=1)
    ap.add_argument("--check-seed", type=int, default=2)
    ap.add_argument("--zoo-scenes", type=int, default=4, help="scenes per zoo model (32 models)")
    ap.add_argument("--zoo-objects", metavar="A,B")
    ap.add_argument("--cookie-scenes", type=int, default=100)
    ap.add_argument("--ridge", type=float, default=1.0)
    ap.add_argument("--cache", help="directory to keep the trained zoo models in between runs")
    ap.add_argument("--rows", metavar="PREFIX", help="write the rows to PREFIX-SEED.jsonl (one file per seed)")
    ap.add_argument("--from-rows", metavar="PREFIX", help="refit from rows written before (no scenes)")
    ap.add_argument("--collect-only", metavar="SEED", type=int,
                    help="only collect the rows of this seed into PREFIX-SEED.jsonl (--rows) and stop")
    a = ap.parse_args(argv)
    objects = a.zoo_objects.split(",") if a.zoo_objects is not None else None
    if objects is not None and not all(o.strip() for o in objects):  # ('' ran every object)
        ap.error(f"--zoo-objects: give zoo object names separated by commas, got {a.zoo_objects!r}")
    if a.collect_only is not None:
        if not a.rows:
            ap.error("--collect-only needs --rows PREFIX")
        rows = collect(a.collect_only, a.zoo_scenes, a.cookie_scenes, objects, a.cache)
        Path(f"{a.rows}-{a.collect_only}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        return 0
    if a.from_rows:
        fit_rows, check_rows = _read(f"{a.from_rows}-{a.fit_seed}.jsonl"), _read(f"{a.from_rows}-{a.check_seed}.jsonl")
    else:
        fit_rows = collect(a.fit_seed, a.zoo_scenes, a.cookie_scenes, objects, a.cache)
        check_rows = collect(a.check_seed, a.zoo_scenes, a.cookie_scenes, objects, a.cache)
        if a.rows:
            for tag, rows in ((a.fit_seed, fit_rows), (a.check_seed, check_rows)):
                Path(f"{a.rows}-{tag}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    coef = fit(fit_rows, a.ridge)
    print("CONFIDENCE_COEF = (" + ", ".join(f"({k!r}, {v})" for k, v in coef) + ")")
    print(format_reliability(f"fit (seed {a.fit_seed})", reliability(fit_rows, coef)))
    print(format_reliability(f"check (seed {a.check_seed})", reliability(check_rows, coef)))
    print(format_reliability(f"check with the committed coefficients", reliability(check_rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""How well do the model's edges judge a pose? (issue 12) — ``quatrack bench edge-judge``.

The tracker lets the model's edges judge the poses no trained point vouches for: a pose
re-found on this run's keyframes, a re-acquired one, a track on probation or in doubt
(``Tracker._edges_confirm``, ``_edge_settled``). A judge that refuses right poses ends tracks
that were right (on the zoo walks most of the frames lost while the object is in plain view
follow such a refusal); one that passes wrong poses reports them. Its two error rates can be
measured without running a tracker: on the zoo walks' frames (:mod:`quatrack.testing.orbit`,
rendered with ground truth, the same walks as ``bench track-zoo``), every ``every``-th frame in
which at least 30 % of the object is visible is judged at

- the true pose (a refusal is a *false alarm*),
- the true pose moved by ``0.3`` of the 5 %/5° criterion (the object's centre by 1.5 % of the
  diameter, the rotation by 1.5° about the centre, random directions: a pose well within the
  criterion, which should pass),
- and by ``1.2`` of it (6 % and 6°: a pose beyond the criterion, which should be refused).

The judges, each from :mod:`quatrack.recognition.evidence` with recognition's and the
tracker's thresholds:

- ``agreement``: recognition's edge test (``edge_agreement``: enough visible samples on aligned
  image gradients, well above the image's chance level);
- ``edges-refit``: that test, and the pose refitted to its edges alone (``edge_fit`` without
  points) moves it by at most ``TrackerParams.max_edge_shift`` of the criterion: the first test
  of ``Tracker._edge_settled``;
- ``agreement-gain``: that test, and the refit raises the share of samples on image edges by at
  most ``gain`` (0.09): a right pose gains little by moving to where the edges pull it, a wrong
  one gains much. (Session 30's study: the refit moves a right pose far where its edges cannot
  fix it — a cylinder's turn about its axis — without finding more edges there.)

Per object, the share of frames each judge refuses at each distance from the truth, and the
refit's shift and gain at the truth (median, 90th percentile). Nothing is tracked or trained:
the walks only need rendering (under a minute a walk on the 2-core machine), then ~0.1 s a
judged pose.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import cv2
import numpy as np

from quatrack.testing import zoo as Z
from quatrack.testing.orbit import OrbitParams, render_orbit
from quatrack.tracking import quaternion as quat
from quatrack.tracking.pose import Pose

from .track_zoo import SEQUENCES, walks

DISTANCES = (0.0, 0.3, 1.2)  # shares of the 5 %/5° criterion the judged poses are from the truth
JUDGES = ("agreement", "edges-refit", "agreement-gain")
GAIN = 0.09  # agreement-gain's threshold (the 95th percentile at the truth in session 30's study)


def moved(pose: Pose, share: float, centre: np.ndarray, extent: float, rng: np.random.Generator) -> Pose:
    """``pose`` with the object's centre moved by ``share × 5 %`` of ``extent`` and the object
    turned about its centre by ``share × 5°``, each in a random direction: a pose exactly
    ``share`` of the criterion away (:func:`quatrack.recognition.evidence.pose_shift`).

    >>> from quatrack.recognition.evidence import pose_shift
    >>> mesh = Z.textured("cube-m").mesh
    >>> p = Pose(np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    >>> round(pose_shift(moved(p, 1.2, mesh.centre, mesh.extent, np.random.default_rng(0)), p, mesh), 6)
    1.2
    """
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    q = quat.multiply(quat.exp(0.5 * np.radians(5.0 * share) * axis), pose.q_wxyz)
    c = np.asarray(centre, float)
    c_cam = pose.R @ c + pose.t + direction * share * 0.05 * extent
    return Pose(q, c_cam - quat.to_matrix(q) @ c)


@dataclass(frozen=True)
class Verdict:
    """One judged pose: the walk's object, the frame, the distance from the truth (share of the
    criterion), whether each judge refused it, the edges-alone refit's shift and agreement gain
    (NaN: too few edge samples to refit)."""

    name: str
    frame: int
    distance: float
    refused: dict
    shift: float
    gain: float


def judge(gray: np.ndarray, mesh, camera, pose: Pose, max_edge_shift: float, gain: float = GAIN) -> tuple[dict, float, float]:
    """The three judges' verdicts on ``pose`` (True: refused), the refit's shift and gain."""
    from quatrack.recognition.evidence import edge_fit, measure_edges
    from quatrack.recognition.pose import PoseParams, edges_agree

    pp = PoseParams()
    ev, image = measure_edges(gray, mesh, camera, pose, pp.edges)
    ok = image is not None and edges_agree(ev, pp)
    shift = g = float("nan")
    if image is not None:
        fit = edge_fit(image, mesh, camera, pose, np.zeros((0, 3)), np.zeros((0, 2)), pp.edges, pp.edge_fit_reach)
        if fit.samples >= pp.min_edge_samples and fit.pose is not None:
            shift = float(fit.shift)
            g = float(measure_edges(gray, mesh, camera, fit.pose, pp.edges)[0].agreement - ev.agreement)
    # too few samples to refit: no evidence either way (Tracker._edge_shift), only the agreement judges
    refused = {"agreement": not ok,
               "edges-refit": not ok or bool(shift > max_edge_shift),
               "agreement-gain": not ok or bool(g > gain)}
    return refused, shift, g


def study(names=SEQUENCES, renderings: int = 1, every: int = 5, seconds: float = 10.0,
          orbit: OrbitParams | None = None, backgrounds=None, progress: bool = False) -> list[Verdict]:
    """Every judged pose of the walks (see the module)."""
    from dataclasses import replace

    from quatrack.recognition.video import TrackerParams

    limit = TrackerParams().max_edge_shift
    params = replace(orbit or OrbitParams(), seconds=seconds)
    bgs = backgrounds if backgrounds is not None else Z.real_backgrounds()
    cam = Z.zoo_camera(640, 480)
    out: list[Verdict] = []
    for key, name, seed in walks(names, renderings):
        obj = Z.textured(name)
        seq = render_orbit(obj, cam, bgs, params, seed=seed, name=name)
        mesh = obj.mesh
        rng = np.random.default_rng(seed)
        for k in range(0, len(seq), every):
            if seq.visible[k] < 0.3:
                continue
            gray = cv2.cvtColor(seq.image(k), cv2.COLOR_BGR2GRAY)
            for d in DISTANCES:
                pose = seq.poses[k] if d == 0 else moved(seq.poses[k], d, mesh.centre, mesh.extent, rng)
                refused, shift, g = judge(gray, mesh, cam, pose, limit)
                out.append(Verdict(key, k, d, refused, shift, g))
        if progress:
            print(f"  {key}: {sum(v.name == key for v in out)} poses judged", flush=True)
    return out


def figures(verdicts: list[Verdict]) -> dict:
    """Per walk key and over all: for each judge and distance the share refused; at the truth the
    refit's shift and gain (median, 90th percentile)."""
    def one(vs: list[Verdict]) -> dict:
        f = {"frames": len({(v.name, v.frame) for v in vs})}
        for j in JUDGES:
            f[j] = {str(d): float(np.mean([v.refused[j] for v in vs if v.distance == d]))
                    if any(v.distance == d for v in vs) else None for d in DISTANCES}
        at = [v for v in vs if v.distance == 0]
        for key in ("shift", "gain"):
            x = np.array([getattr(v, key) for v in at], float)
            x = x[np.isfinite(x)]
            f[f"{key}_at_truth"] = [float(np.median(x)), float(np.percentile(x, 90))] if len(x) else None
        return f

    keys = list(dict.fromkeys(v.name for v in verdicts))
    out = {k: one([v for v in verdicts if v.name == k]) for k in keys}
    out["all"] = one(verdicts)
    return out


def report(fig: dict) -> str:
    lines = ["judge refusals: false alarms at the truth | at 0.3 of the criterion (should pass) | caught at 1.2 (should be refused)", ""]
    head = "| walk | frames | " + " | ".join(JUDGES) + " | refit shift / gain at truth (p50, p90) |"
    lines += [head, "|" + " --- |" * (len(JUDGES) + 3)]
    for k, f in fig.items():
        cells = []
        for j in JUDGES:
            r = f[j]
            cells.append(" / ".join("–" if r[str(d)] is None else f"{100 * r[str(d)]:.0f} %" for d in DISTANCES))
        s, g = f["shift_at_truth"], f["gain_at_truth"]
        sg = "–" if s is None or g is None else f"{s[0]:.2f}, {s[1]:.2f} / {g[0]:.3f}, {g[1]:.3f}"
        lines.append(f"| {k} | {f['frames']} | " + " | ".join(cells) + f" | {sg} |")
    return "\n".join(lines)


def main(as_json: bool = False, names: list[str] | None = None, renderings: int = 1, every: int = 5,
         seconds: float = 10.0) -> int:
    fig = figures(study(tuple(names) if names else SEQUENCES, renderings, every, seconds, progress=not as_json))
    print(json.dumps(fig) if as_json else report(fig))
    return 0


__all__ = ["DISTANCES", "JUDGES", "moved", "judge", "study", "figures", "report", "main"]

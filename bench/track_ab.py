"""Tracker settings compared on one video in one process — ``quatrack bench track-ab``.

A change that saves a millisecond a frame cannot be seen by timing two runs one after the
other on a shared virtual machine: its speed changed by up to 30 % between runs in session 32
(bench/RESULTS.md). Here every variant gets its own tracker, and on each frame of the video the
trackers step one after the other, so whatever the machine does meanwhile falls on all of them
alike. Each step's CPU time is the calling thread's (``time.thread_time``): re-anchoring runs in
the step (no executor), as in ``quatrack track``, so its SIFT is counted where it happens.

The variants are the service's tracker settings (:func:`quatrack.service.tracker_factory.make_tracker`,
with re-anchoring in the step) with some :class:`~quatrack.recognition.video.TrackerParams`
fields replaced: ``NAME=JSON``, e.g. ``w17={"klt": {"win": 17}}``; a field that is itself a
dataclass (``klt``, ``visibility``, ``locate``, ``adjust``) takes a JSON object of its own
fields. The first row, ``base``, has none replaced. Per variant: step CPU p50 / mean / p90, the
frames without a pose, and how far its poses are from ``base``'s in the frames both have one (the
object's centre, % of the mesh's diameter, median and max): 0 when the change is exact.
"""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np


def parse_variant(text: str, base) -> tuple[str, object]:
    """``NAME=JSON`` → ``(NAME, base with those fields replaced)``; ValueError (with the known
    fields) when the text or a field is not understood.

    >>> from quatrack.recognition.video import TrackerParams
    >>> name, p = parse_variant('w17={"klt": {"win": 17}, "audit_every": 6}', TrackerParams())
    >>> name, p.klt.win, p.klt.levels, p.audit_every
    ('w17', 17, 3, 6)
    """
    name, sep, spec = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise ValueError(f"variant {text!r}: write NAME=JSON, e.g. 'w17={{\"klt\": {{\"win\": 17}}}}'")
    try:
        fields = json.loads(spec)
    except json.JSONDecodeError as exc:
        raise ValueError(f"variant {name!r}: not JSON ({exc.msg})") from None
    if not isinstance(fields, dict):
        raise ValueError(f"variant {name!r}: the JSON must be an object of TrackerParams fields")
    return name, _replaced(base, fields, name)


def _replaced(obj, fields: dict, where: str):
    known = {f.name: f for f in dataclasses.fields(obj)}
    changes = {}
    for key, value in fields.items():
        if key not in known:
            raise ValueError(f"variant {where!r}: {type(obj).__name__} has no field {key!r} "
                             f"(known: {', '.join(sorted(known))})")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            value = _replaced(current, value, where)
        else:
            value = _typed(value, current, f"variant {where!r}: {key}")
        changes[key] = value
    try:
        return dataclasses.replace(obj, **changes)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"variant {where!r}: {exc}") from None


def _typed(value, current, what: str):
    """``value`` (from JSON) as the type of the field's ``current`` value; ValueError if it is
    not one (a window of ``"a"`` px would fail deep inside OpenCV)."""
    if current is None or value is None:  # (an optional field: anything it takes)
        return value
    kinds = ((bool, (bool,)), (int, (int,)), (float, (int, float)), (str, (str,)), (tuple, (list,)), (dict, (dict,)))
    for kind, accepted in kinds:
        if isinstance(current, kind):
            ok = isinstance(value, accepted) and (kind is bool or not isinstance(value, bool))
            if not ok:
                name = {tuple: "a list", dict: "an object", int: "an integer", float: "a number", bool: "true or false",
                        str: "a string"}[kind]
                raise ValueError(f"{what} must be {name}, not {json.dumps(value)}")
            return tuple(value) if kind is tuple else float(value) if kind is float else value
    return value


def compare(frames, times, model, camera, variants: list[tuple[str, object]], index=None) -> list[dict]:
    """Step every variant's tracker on each frame in turn (see the module); one figure row per
    variant, ``base`` (the first) included."""
    from quatrack.recognition.match import index_for
    from quatrack.recognition.video import Tracker
    from quatrack.tracking.pose import Pose

    index = index if index is not None else index_for(model)
    trackers = [(name, Tracker(model, camera, params, index=index, executor=None)) for name, params in variants]
    cpu = {name: [] for name, _ in trackers}
    centres = {name: [] for name, _ in trackers}
    c = np.asarray(model.mesh.centre, float)
    for image, t in zip(frames, times):
        for name, tracker in trackers:
            t0 = time.thread_time()
            try:
                step = tracker.step(image, t)
            except Exception as exc:  # (a setting the tracker cannot work with: say which, no traceback)
                raise ValueError(f"variant {name!r}: the tracker failed ({type(exc).__name__}: {exc})") from None
            cpu[name].append((time.thread_time() - t0) * 1e3)
            has = step.status != "lost" and step.t is not None
            centres[name].append(Pose(step.q_wxyz, step.t).apply(c) if has else None)
    diameter = float(model.mesh.extent)
    rows = []
    ref = centres[trackers[0][0]]
    for name, _ in trackers:
        d = [np.linalg.norm(a - b) for a, b in zip(centres[name], ref) if a is not None and b is not None]
        ms = np.asarray(cpu[name][1:] or cpu[name])  # (the first step: recognition, and warming up)
        rows.append({"variant": name, "frames": len(cpu[name]), "lost": sum(x is None for x in centres[name]),
                     "cpu_p50_ms": float(np.median(ms)), "cpu_mean_ms": float(np.mean(ms)),
                     "cpu_p90_ms": float(np.percentile(ms, 90)),
                     "from_base_median_pct": float(np.median(d)) / diameter * 100 if d else None,
                     "from_base_max_pct": float(np.max(d)) / diameter * 100 if d else None})
    return rows


def report(rows: list[dict]) -> str:
    out = ["| variant | frames | without a pose | step CPU p50 / mean / p90 (ms) | centre from base, median / max (% of diameter) |",
           "| --- | ---: | ---: | --- | --- |"]
    for r in rows:
        dist = "—" if r["from_base_median_pct"] is None else f"{r['from_base_median_pct']:.3f} / {r['from_base_max_pct']:.3f}"
        out.append(f"| {r['variant']} | {r['frames']} | {r['lost']} | {r['cpu_p50_ms']:.1f} / {r['cpu_mean_ms']:.1f} / "
                   f"{r['cpu_p90_ms']:.1f} | {dist} |")
    return "\n".join(out)


def main(variants: list[str], video: str | None, camera: str | None, spec: str | None, max_frames: int,
         as_json: bool) -> int:
    import cv2

    from quatrack.examples import example_dir
    from quatrack.recognition.trackio import open_frames
    from quatrack.service.tracker_factory import make_tracker
    from quatrack.viewsets.camera import load_camera
    from quatrack.viewsets.spec import load_spec
    from quatrack.viewsets.train import train_object

    if max_frames < 2:
        raise ValueError("--frames must be at least 2")
    from quatrack.recognition.video import TrackerParams

    for v in variants:  # (the text checked before the video is read and the object trained: ~5 s, then the error)
        parse_variant(v, TrackerParams().for_live_streams())
    example = example_dir()  # defaults that do not depend on the working directory
    cam = load_camera(camera or str(example / "camera.json"))
    source = open_frames(video=video or str(example / "box.mp4"), max_frames=max_frames)
    frames, times = [], []
    for _, t, image in source:
        frames.append(image)
        times.append(t)
    model = train_object(load_spec(spec or str(example / "object.json")))
    cv2.setNumThreads(1)  # (one thread: the service's worker of a 2-core machine with 2 workers)
    base = make_tracker(model, cam, None, frames[0].shape[0] * frames[0].shape[1]).params
    parsed = [("base", base)] + [parse_variant(v, base) for v in variants]
    names = [n for n, _ in parsed]
    if len(set(names)) != len(names):
        raise ValueError("variant names must differ from each other and from 'base'")
    rows = compare(frames, times, model, cam, parsed)
    print(json.dumps({"variants": rows}) if as_json else report(rows))
    return 0

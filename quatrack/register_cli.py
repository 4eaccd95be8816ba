"""``quatrack register``: solve and refine the photos' poses of an object spec, and write them back.

A user's own object comes with a mesh and a photo, rarely with the photo's pose. The spec may
give, instead of a view's ``pose``, the ``points`` clicked in it (``{"model": [x, y, z], "pixel":
[u, v]}``, at least four: :mod:`quatrack.viewsets.register`). ``quatrack train`` solves such a
view's pose by PnP from its points alone; ``register`` also pulls each view's pose (solved, or
given) onto the mesh's edges in the photo (:mod:`quatrack.recognition.registration`), prints what it did, and writes a spec with the poses
filled in — by default ``NAME.registered.json`` beside the spec (in the current folder when the
spec's folder cannot be written or lies inside the installed package) — plus, with ``--overlay DIR``,
each photo with the mesh drawn at its pose to look at before training. The written spec keeps
everything the input had (the points too), so it can be edited and registered again.

A view that cannot be registered — clicks that fit no pose, model points off the mesh (other
units), a pose whose mesh edges miss the photo's (the pose inverted, another photo), a photo
``--locate`` cannot find surely — is named on stderr with what to check, the overlays are still
drawn (the clicks against their best pose), nothing else is written, and the exit status is 2.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from quatrack.cli import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", metavar="SPEC.json", help="object spec (docs/contract.md): views with 'pose' and/or 'points'")
    parser.add_argument("--out", metavar="OUT.json",
                        help="where to write the spec with the poses filled in (default: SPEC.registered.json beside SPEC, "
                             "or in the current folder when SPEC's folder cannot be written or is inside the installed quatrack; "
                             "relative paths in it are rewritten for its folder)")
    parser.add_argument("--overlay", metavar="DIR",
                        help="also write each photo with the mesh's edges at its pose (green; hidden ones thin grey), the clicked pixels (yellow) "
                             "and where the pose puts their points (red) as DIR/view-N.png")
    parser.add_argument("--no-edges", action="store_true",
                        help="keep the poses PnP gives from the points (and the given poses) as they are: no refit to the mesh's edges")
    parser.add_argument("--locate", action="store_true",
                        help="views with neither 'pose' nor 'points' are found by recognition, with a model trained "
                             "(in memory) from the views that have a pose — again with every view found, until no more are")
    parser.add_argument("--click-sigma", type=float, default=None, metavar="PX",
                        help="how far a click may be off, in pixels: the clicks' weight against the edges (default: "
                             "2.0, or less where the clicks fit their pose so closely that 2 px is ruled out)")


def _relative(value: str, old_base: Path, new_base: Path) -> str:
    """A path of the spec (relative to ``old_base`` unless absolute) for a spec in ``new_base``."""
    p = Path(value)
    if p.is_absolute() or old_base == new_base:
        return value
    try:
        return os.path.relpath(old_base / p, new_base)
    except ValueError:  # (another drive on Windows)
        return str((old_base / p).resolve())


def _rebased(data: dict, old_base: Path, new_base: Path) -> dict:
    """The spec's JSON with its file paths (mesh, images, cameras, masks) valid from ``new_base``."""
    out = dict(data)
    if isinstance(out.get("mesh"), str):
        out["mesh"] = _relative(out["mesh"], old_base, new_base)
    views = []
    for v in out.get("views", []):
        v = dict(v)
        for key in ("image", "camera", "mask"):
            if isinstance(v.get(key), str):
                v[key] = _relative(v[key], old_base, new_base)
        views.append(v)
    out["views"] = views
    return out


def _edge_runs(mesh, camera, pose, edges: np.ndarray, samples: int = 32) -> tuple[list, list]:
    """The projected model edges (k, 2, 3) split into runs the object shows and runs it hides
    (each a polyline of pixels × 16: OpenCV's 4 fractional bits): a sample is hidden when the
    z-buffer at its pixel holds a surface nearer than it by more than 5 % of the object's diameter
    (and 0.5 % of its depth). Why: the overlay is drawn for a user to judge
    the pose, and the box's back edges drawn as boldly as its front ones read as a wrong pose."""
    from quatrack.viewsets.render import render

    depth = render(mesh, camera, pose).depth
    s = np.linspace(0.0, 1.0, samples)[None, :, None]
    pts = (edges[:, :1] * (1 - s) + edges[:, 1:] * s).reshape(-1, 3) @ pose.R.T + pose.t
    front = pts[:, 2] > 1e-9
    uv = np.full((len(pts), 2), np.nan)
    uv[front] = camera.project(pts[front])
    h, w = depth.shape
    ok = front & np.all(np.isfinite(uv), axis=1) & (np.abs(uv) < 1e5).all(axis=1)
    px = np.clip(np.rint(uv[ok]).astype(int), 0, [w - 1, h - 1])
    hidden = np.zeros(len(pts), bool)
    near = depth[px[:, 1], px[:, 0]]
    # (an edge lies on its faces' border: the surface at its pixel is one of them, within a pixel's
    # slant; a hidden edge lies behind the object's front by a good part of its size)
    hidden[ok] = np.isfinite(near) & (pts[ok, 2] > near + 0.05 * float(mesh.extent) + 0.005 * pts[ok, 2])
    shown_runs, hidden_runs = [], []
    uv, ok, hidden = uv.reshape(len(edges), samples, 2), ok.reshape(len(edges), samples), hidden.reshape(len(edges), samples)
    for e in range(len(edges)):
        start = 0
        for k in range(1, samples + 1):
            if k == samples or ok[e, k] != ok[e, start] or hidden[e, k] != hidden[e, start]:
                if ok[e, start] and k - start >= 2:
                    (hidden_runs if hidden[e, start] else shown_runs).append(np.rint(16 * uv[e, start:k]).astype(np.int32))
                start = k
    return shown_runs, hidden_runs


def _draw(photo: np.ndarray, view, mesh, mesh_edges: np.ndarray, pose, note: str = "") -> np.ndarray:
    """The photo with the mesh's edges at ``pose`` (those the object shows green, those it hides
    thin grey), the clicks (yellow, numbered) and their points' projections (red); ``note`` after
    the view's number in its label (a view drawn but not registered says so on its picture)."""
    import cv2

    from quatrack.recognition.images import to_bgr8
    from quatrack.recognition.overlay import draw_label

    out = to_bgr8(photo).copy()
    shown, hidden = _edge_runs(mesh, view.camera, pose, np.asarray(mesh_edges, float))
    cv2.polylines(out, hidden, False, (150, 150, 150), 1, cv2.LINE_AA, shift=4)
    cv2.polylines(out, shown, False, (60, 200, 60), 2, cv2.LINE_AA, shift=4)
    if view.points is not None:
        proj = view.camera.project(view.points.model @ pose.R.T + pose.t)
        for i, (c, p) in enumerate(zip(view.points.pixel, proj)):
            cv2.circle(out, tuple(int(round(x)) for x in c), 6, (0, 230, 255), 1, cv2.LINE_AA)
            if np.all(np.isfinite(p)) and np.all(np.abs(p) < 1e5):
                cv2.circle(out, tuple(int(round(x)) for x in p), 2, (40, 40, 230), -1, cv2.LINE_AA)
            cv2.putText(out, str(i), (int(c[0]) + 7, int(c[1]) - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 230, 255), 1, cv2.LINE_AA)
    draw_label(out, f"view {view.index}{note}")
    return out


# A photo found by recognition is trained on as if registered: a wrong pose would teach the model
# wrong 3-D points, so it must be surer than locate's own bar (0.7). A zoo wide box seen from below,
# none of its faces in the clicked photo, was found 9.5 % / 78° off at confidence 0.91 with 50 % of
# its edges on the photo's; the right ones read 0.99–1.00 and 81–93 %.
LOCATE_MIN_CONFIDENCE = 0.98
LOCATE_MIN_EDGES = 0.7


def _locate_missing(spec, views: list, photos: dict, refused: int = 0) -> tuple[dict, dict, dict]:
    """``{view index: (pose, how it was found)}`` for the views without a pose, found by
    recognition (:func:`quatrack.recognition.locate.locate`, verified as any found pose) with a
    model trained in memory from the views that have one; trained again with the views found,
    while that finds more (a photo 60° from the clicked one may be found from one found at 30°).
    Second: ``{view index: why it was not found}``; third: ``{view index: pose}`` of those found,
    but not surely enough to train on (drawn, not taken). ``refused``: how many views the caller left
    out (their clicks fit no pose): with none left to train on, each view to find is said not
    looked for — "no view has points" was false, and stopped before the misfit was said."""
    from quatrack.recognition.locate import locate
    from quatrack.viewsets.train import TrainParams, train_object

    found: dict = {}
    missing = [v for v in views if v.pose is None]
    reasons: dict = {}
    unsure: dict = {}
    while missing:
        posed = [replace(v, pose=found[v.index][0]) if v.index in found else v for v in views]
        posed = [v for v in posed if v.pose is not None]
        if not posed and refused:
            return {}, {v.index: f"view {v.index}: not looked for by recognition: no view is registered to train it "
                                 f"from: fix the view(s) named here with clicks that fit no pose, then run again"
                        for v in missing}, {}
        if not posed:
            raise UserError("--locate: no view has a pose or points to start from: give at least one view 'points' "
                            "(clicked corners) or a 'pose'")
        print(f"training on {len(posed)} view(s) to find {len(missing)} more …", file=sys.stderr, flush=True)
        model = train_object(replace(spec, views=tuple(posed)), TrainParams())
        still = []
        for v in missing:
            res = locate(photos[v.index], v.camera, model)
            edges = (res.verification or {}).get("edge_agreement") or 0.0
            unsure.pop(v.index, None)
            if res.found and res.confidence >= LOCATE_MIN_CONFIDENCE and edges >= LOCATE_MIN_EDGES:
                found[v.index] = (res.pose, f"found by recognition ({res.inliers} inliers, confidence "
                                            f"{res.confidence:.2f}, from viewset {res.viewset})")
            else:
                if res.found:
                    unsure[v.index] = res.pose
                reasons[v.index] = (res.reason or "not found") if not res.found else (
                    f"found, but not surely enough to train on: confidence {res.confidence:.2f}, {edges:.0%} of the "
                    f"edges on the photo's (at least {LOCATE_MIN_CONFIDENCE}, {LOCATE_MIN_EDGES:.0%})")
                still.append(v)
        if len(still) == len(missing):
            break
        missing = still
    return found, {v.index: f"view {v.index}: not found by recognition ({reasons[v.index]}): give it 'points' "
                            f"(clicked corners)" for v in missing}, unsure


def _package_folder() -> Path:
    """The installed ``quatrack`` package's folder (site-packages/quatrack from a wheel; a
    checkout's quatrack/ otherwise, which holds no spec)."""
    import quatrack

    return Path(quatrack.__file__).resolve().parent


def default_out(spec_path: Path) -> tuple[Path, str | None]:
    """Where ``register`` writes without ``--out``: ``SPEC.registered.json`` beside the spec, or
    in the current folder when the spec's folder cannot be written or lies inside the installed
    package (``register`` of the bundled example from a wheel wrote into site-packages), with
    why (None: beside the spec)."""
    name = f"{spec_path.stem}.registered.json"
    folder = spec_path.resolve().parent
    if folder.is_relative_to(_package_folder()):
        why = f"{folder} is inside the installed quatrack"
    elif folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):
        why = f"{folder} cannot be written"
    else:
        return spec_path.with_name(name), None
    return Path(name), f"the spec's folder {why}, so in the current folder; --out chooses"


def _outputs(args: argparse.Namespace) -> tuple[Path, Path, Path | None, str | None]:
    """The spec, the registered spec's path, the overlay folder and why the registered spec is not
    beside the spec (None: it is, or ``--out``), checked before any work."""
    if args.click_sigma is not None and not (np.isfinite(args.click_sigma) and args.click_sigma > 0):
        raise UserError(f"--click-sigma must be a positive number of pixels, got {args.click_sigma!r}")
    spec_path = Path(args.spec)
    out_path, moved = (Path(args.out), None) if args.out else default_out(spec_path)
    if out_path.resolve() == spec_path.resolve():
        raise UserError(f"--out {out_path}: that is the spec itself; write the registered spec to another file")
    if not out_path.name or (out_path.exists() and out_path.is_dir()):
        raise UserError(f"--out {out_path}: give a file name, not a folder")
    folder = out_path.resolve().parent
    if not folder.is_dir():
        raise UserError(f"--out {out_path}: {folder} " + ("is a file, not a folder" if folder.exists() else "does not exist"))
    overlay = Path(args.overlay) if args.overlay else None
    if overlay is not None and overlay.exists() and not overlay.is_dir():
        raise UserError(f"--overlay {overlay}: not a folder")
    if overlay is not None:  # (made now: one that cannot be was "[Errno 20] Not a directory" after the work)
        try:
            overlay.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"--overlay {overlay}: cannot make the folder ({exc.strerror or exc})") from None
    return spec_path, out_path, overlay, moved


def _check_mask(view, photo: np.ndarray) -> None:
    """A view's mask read and sized as training reads it (:func:`~quatrack.viewsets.train.read_mask`:
    a :class:`SpecError` otherwise). Why here: register ignores masks, and wrote a spec with a
    missing or misfit mask that ``quatrack train``, as the line it printed said to run, then refused."""
    from quatrack.viewsets.train import read_mask

    if view.mask_path is not None:
        read_mask(view, photo.shape[:2])


def _recheck_clicks(view, where: str, problems: dict, warn) -> None:
    """The clicks' checks that need the photo's size (``load_spec`` passed them for a camera
    sized by its images, which has none: a click 40 px off was then taken and trained on):
    their pixels inside the photo and their RMS within :func:`~quatrack.viewsets.register.max_rms_px`
    for a pose solved from them (a problem: ``problems[index]``), the given pose's agreement
    with them otherwise (a warning, as ``load_spec`` gives)."""
    from quatrack.viewsets.errors import SpecError
    from quatrack.viewsets.register import pose_from_points
    from quatrack.viewsets.spec import _points_disagree

    if view.points is None or view.index in problems:
        return
    if view.pose_from_points:
        try:
            pose_from_points(view.points, view.camera, where)
        except SpecError as exc:
            problems[view.index] = str(exc)
    elif view.pose is not None and (msg := _points_disagree(view.points, view.camera, view.pose)) is not None:
        warn(f"view {view.index}: {msg}")


def _loose(view, reg, click_sigma_px: float | None) -> str:
    """What to say of a pose its clicks alone fix loosely (the edges did not refine it): ``""``
    when they fix its rotation within :data:`~quatrack.viewsets.register.LOOSE_ROTATION_DEG`,
    the clicks' σ as the edges' refit weighs them
    (:func:`~quatrack.recognition.registration.clicks_sigma`: a bar's 7 clicks good to 0.2 px
    were said to leave its rotation ±3.3° loose, at 2 px each)."""
    from quatrack.recognition.registration import clicks_sigma
    from quatrack.viewsets.register import LOOSE_ROTATION_DEG, rotation_sigma_deg

    n = len(view.points)
    s = rotation_sigma_deg(view.points, view.camera, reg.pose, clicks_sigma(reg, n, click_sigma_px))
    if s <= LOOSE_ROTATION_DEG:
        return ""
    return (f"; but its {n} points fix the rotation only to ±{s:.1f}° (1σ; at most {LOOSE_ROTATION_DEG:g}° is "
            f"firm): click points on another face too (four corners of one face seen face-on leave its tilt loose)")


FIRM_CLICKS = 6  # clicks from which a pose solved within their σ is firm (_register_view)
FIRM_CLICKS_LEAD = 0.10  # the edges' lead over chance such a pose needs (locate's: PoseParams.min_edge_lead)


def _register_view(view, grey: np.ndarray, mesh, args: argparse.Namespace, origin: str):
    """One view's final pose, its line for stdout, and what is wrong with it (None: nothing):
    its clicks off the mesh, or the mesh's edges at the pose not on the photo's as a pose
    ``locate`` finds must be (:class:`~quatrack.recognition.pose.PoseParams`' bars)."""
    from quatrack.recognition.registration import xyzw_hint
    from quatrack.recognition.evidence import edge_agreement
    from quatrack.recognition.pose import PoseParams
    from quatrack.recognition.registration import AGREEMENT_SLACK, clicks_sigma, refine_with_edges
    from quatrack.viewsets.errors import SpecError
    from quatrack.viewsets.register import Registration, click_limit_px, off_mesh_message, registration_at
    from quatrack.viewsets.train import check_pose

    line = f"view {view.index}: pose {origin}"
    if view.points is not None and (msg := off_mesh_message(view.points.model, mesh, f"view {view.index}")) is not None:
        return view.pose, line, msg
    try:
        check_pose(mesh, view)  # (in front of the camera, and enough of it in the photo: as training needs)
    except SpecError as exc:
        return view.pose, line, str(exc)
    if view.points is None:  # (no clicks to hold a refit: the edges alone may take a print's line)
        reg = Registration(view.pose, float("nan"), -1, float("nan"))
    else:
        reg = registration_at(view.points, view.camera, view.pose)
        line += f" ({len(view.points)} points, RMS {reg.rms_px:.2f} px, worst: point {reg.worst} at {reg.worst_px:.1f} px)"
        if not args.no_edges:
            reg = refine_with_edges(grey, mesh, view.camera, reg, view.points, click_sigma_px=args.click_sigma)
            a0, a1 = reg.edge_agreement
            if reg.moved is not None:
                line += (f"; refitted to the mesh's edges: {a0:.0%} → {a1:.0%} of their length on the photo's edges, "
                         f"moved {100 * reg.moved[0]:.2f} % of the diameter and {reg.moved[1]:.2f}°, "
                         f"clicks' RMS {reg.rms_px:.2f} px")
            elif reg.refused is not None:
                why = (f"it left the clicks {reg.refused.rms_px:.1f} px (RMS) off — the photo's print, not the "
                       f"object's outline?" if a1 >= a0 - AGREEMENT_SLACK else f"the edges agreed less ({a0:.0%} → {a1:.0%})")
                line += f"; a refit to the mesh's edges not kept: {why}"
        if view.pose_from_points and reg.moved is None:
            line += _loose(view, reg, args.click_sigma)
    e = edge_agreement(grey, mesh, view.camera, reg.pose)
    line += f"; the mesh's edges lie on the photo's for {e.agreement:.0%} of their length ({e.chance:.0%} by chance)"
    p = PoseParams()
    # Clicks that fix the pose firmly (a pose solved from 6 or more of them, within their σ) need
    # the edges only to rule out the mesh in other units or another photo — which leave the edges
    # at chance — not to show locate's lead over chance: a 300 × 30 × 15 mm bar clicked to 0.16 px
    # on gravel was refused at 75 % against 52 % by chance (a user's report); it is said, not refused.
    firm = (view.pose_from_points and view.points is not None and len(view.points) >= FIRM_CLICKS
            and np.isfinite(reg.rms_px)
            and reg.rms_px <= click_limit_px(len(view.points), clicks_sigma(reg, len(view.points), args.click_sigma)))
    lead_needed = FIRM_CLICKS_LEAD if firm else p.min_edge_lead
    if e.samples >= p.min_edge_samples and firm and lead_needed <= e.lead < p.min_edge_lead \
            and e.agreement >= p.min_edge_agreement:
        line += (f" — less above chance than a pose locate finds needs ({p.min_edge_lead:.0%}): the photo's "
                 f"background is busy; kept on its clicks (check the overlay)")
    if e.samples >= p.min_edge_samples and (e.agreement < p.min_edge_agreement or e.lead < lead_needed):
        span = " × ".join(f"{x:.3g}" for x in np.ptp(mesh.vertices, axis=0))
        # (a q_wxyz written [x, y, z, w] that fits read so: train's hint, asked alike — it asked of units)
        hint = xyzw_hint(grey, mesh, view) or (
            f"are the points' model coordinates in the mesh's units (it spans {span}), the pose object → camera, "
            f"the photo this view's?")
        return reg.pose, line, (
            f"view {view.index}: the mesh's edges at its pose lie on the photo's for {e.agreement:.0%} of their length "
            f"({e.chance:.0%} by chance; a pose locate finds needs {p.min_edge_agreement:.0%}, {p.min_edge_lead:.0%} "
            f"above chance): {hint}")
    return reg.pose, line, None


def _drawn_note(overlay: Path | None, drawn: list, n_views: int) -> str:
    """What the last line says of the overlays: every view drawn, or which were and which had no
    pose to draw (not found by --locate, none given): it said "each view drawn" of those too."""
    if overlay is None:
        return ""
    if len(drawn) == n_views:
        return f" (each view drawn at its pose in {overlay})"
    undrawn = ", ".join(str(i) for i in range(n_views) if i not in drawn)
    return (f" (view(s) {', '.join(map(str, drawn)) or 'none'} drawn in {overlay}; view(s) {undrawn} not: no pose "
            f"to draw them at)")


def run(args: argparse.Namespace) -> int:
    import cv2

    from quatrack.recognition.trackio import atomic_path
    from quatrack.recognition.visibility import mesh_edges
    from quatrack.viewsets.mesh import load_mesh
    from quatrack.viewsets.spec import load_spec, missing_pose
    from quatrack.viewsets.train import _read_image

    spec_path, out_path, overlay, moved = _outputs(args)

    def warn(msg: str) -> None:
        if "`quatrack register` also fits it" not in msg:  # (load_spec's hint for train: this is the command)
            print(f"quatrack register: warning: {msg}", file=sys.stderr)

    misfits: list = []
    # (pose_required=False even without --locate: a view missing its pose is one problem among
    # all said, not the end of the reading before a misfit of another view was said)
    spec = load_spec(spec_path, warn=warn, pose_required=False, misfits=misfits)
    problems = {i: str(exc) for i, exc in misfits}
    if not args.locate:
        problems.update({v.index: missing_pose(f"{spec_path}: view {v.index}", "or run with --locate to find it by recognition")
                         for v in spec.views if v.pose is None})
    raw = json.loads(spec_path.read_bytes().decode("utf-8-sig"))
    mesh = load_mesh(spec.mesh_path, warn=warn).run_time  # (a scan's decimation: the edges the tracker sees)
    edges3d = mesh_edges(mesh)
    photos, views = {}, []
    for view in spec.views:
        photo = photos[view.index] = _read_image(view)  # (checks the file and its size against the camera, as training does)
        _check_mask(view, photo)
        cam = view.camera
        if cam.width is None:  # (a camera sized by its images)
            view = replace(view, camera=replace(cam, width=photo.shape[1], height=photo.shape[0]))
            _recheck_clicks(view, f"{spec_path}: view {view.index}", problems, warn)
        views.append(view)
    found, not_found, unsure = (_locate_missing(spec, [v for v in views if v.index not in problems], photos,
                                                len(problems)) if args.locate else ({}, {}, {}))
    problems.update(not_found)
    poses, drawn = [], []
    for view in views:
        if view.index in found:
            view = replace(view, pose=found[view.index][0])
        if view.index in unsure:  # (found, not surely: drawn at that pose for a look, not taken)
            view = replace(view, pose=unsure[view.index])
            pose, line = view.pose, f"view {view.index}: found by recognition, but not surely enough (below)"
        elif view.pose is None:  # (--locate did not find it, or no pose without --locate)
            poses.append(None)
            continue
        elif view.index in problems:  # (its clicks fit no pose: only drawn, at their best pose)
            pose, line = view.pose, f"view {view.index}: the clicks fit no pose (below)"
        else:
            origin = ("solved from its points" if view.pose_from_points
                      else found[view.index][1] if view.index in found else "given")
            grey = cv2.cvtColor(photos[view.index], cv2.COLOR_BGR2GRAY)
            pose, line, problem = _register_view(view, grey, mesh, args, origin)
            if problem is not None:
                problems[view.index] = problem
        print(line)
        poses.append(pose)
        if overlay is not None:
            target = overlay / f"view-{view.index}.png"
            note = ": NOT registered" if view.index in problems else ""
            with atomic_path(target, "--overlay") as tmp:
                if not cv2.imwrite(tmp, _draw(photos[view.index], view, mesh, edges3d, pose, note)):
                    raise UserError(f"--overlay {target}: cannot write the image")
            drawn.append(view.index)
    drawn = _drawn_note(overlay, drawn, len(views))
    if problems:
        lines = "\n".join(f"quatrack register: {problems[i]}" for i in sorted(problems))
        print(lines, file=sys.stderr)
        raise UserError(f"{len(problems)} of {len(views)} view(s) not registered{drawn}; {spec_path} not written over, "
                        f"{out_path} not written")
    data = _rebased(raw, spec_path.resolve().parent, out_path.resolve().parent)
    for v, pose in zip(data["views"], poses):
        v["pose"] = pose.to_json()  # (the contract's {"t", "q_wxyz"})
    with atomic_path(out_path, "--out") as tmp:
        Path(tmp).write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    # (quoted: a path with a space, copied as printed, was two arguments to train)
    print(f"wrote {out_path}{drawn}{f' ({moved})' if moved else ''}; train it with: quatrack train {shlex.quote(str(out_path))}")
    return 0

"""Object spec (JSON) → dataclasses, with every path resolved relative to the spec file.

Nothing here reads images or meshes: only the spec's structure, cameras and poses are checked
(a view's pose solved from its clicked points when it gives no pose: geometry alone,
:mod:`.register`), so a bad spec fails fast with a message naming the file, the view and the field.
"""

from __future__ import annotations

import hashlib
import json
import os
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose

from .camera import camera_from_dict, isfinite, load_camera
from .errors import SpecError, StoreError
from .names import check_object_name
from .register import MIN_POINTS, PointPairs, PointsMisfit, max_rms_px, parse_points, pose_from_points, registration_at

__all__ = ["ObjectSpec", "ViewSpec", "load_spec", "missing_pose", "parse_pose"]


@dataclass(frozen=True)
class ViewSpec:
    """One registered training view: the photo, its camera, the object's pose, an optional mask,
    and the clicked points the pose was solved from (``points``, when the spec gives them:
    :mod:`quatrack.viewsets.register`; ``pose_from_points`` says the spec gave no pose)."""

    index: int
    image_path: Path
    camera: PinholeCamera
    pose: Pose  # (None only from load_spec(..., pose_required=False): a view to be located)
    mask_path: Path | None = None
    points: PointPairs | None = field(default=None, compare=False)
    pose_from_points: bool = False
    # the pose were the spec's q_wxyz written [x, y, z, w] (:func:`_xyzw_reading`), to hint at it
    xyzw_pose: Pose | None = field(default=None, compare=False)


@dataclass(frozen=True)
class ObjectSpec:
    """A parsed object spec; ``checksum`` is the SHA-256 of the spec file's bytes."""

    name: str
    path: Path
    mesh_path: Path
    views: tuple[ViewSpec, ...]
    checksum: str


def _vector(value: Any, n: int, where: str, field: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n:
        raise SpecError(f"{where}: field {field!r} must be a list of {n} numbers")
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and isfinite(x) for x in value):
        raise SpecError(f"{where}: field {field!r} must contain finite numbers only")
    return np.asarray(value, dtype=float)


#: the contract's pose forms, each the fields it needs
POSE_FORMS = (("rvec", "tvec"), ("R", "t"), ("q_wxyz", "t"))
POSE_FIELDS = ("rvec", "tvec", "R", "t", "q_wxyz")


def _form_text(form: tuple[str, ...]) -> str:
    return "{" + ", ".join(form) + "}"


def _one_form(keys: set, where: str) -> None:
    """Refuse a pose giving fields of two forms (``{rvec, tvec}`` and ``{q_wxyz, t}``, or
    ``{q_wxyz, t}`` and a stray ``rvec``): one set was used and the other ignored without a word,
    and which one the user meant cannot be told."""
    whole = [f for f in POSE_FORMS if set(f) <= keys]
    if len(whole) > 1:
        raise SpecError(f"{where}: gives the pose twice, as {' and as '.join(map(_form_text, whole))}: keep one form")
    if whole:
        stray = [k for k in POSE_FIELDS if k in keys and k not in whole[0]]
        if stray:
            others = " or ".join(_form_text(f) for f in POSE_FORMS if set(stray) & set(f) and f != whole[0])
            raise SpecError(f"{where}: field(s) {', '.join(map(repr, stray))} of the {others} form beside "
                            f"{_form_text(whole[0])}: keep one form")


def parse_pose(data: Any, where: str = "pose", warn=None) -> Pose:
    """A pose from ``{"rvec","tvec"}``, ``{"R","t"}`` (3×3 rows) or ``{"q_wxyz","t"}``; fields of
    two forms are refused, other fields told to ``warn`` (optional) and ignored, as elsewhere in a spec."""
    if not isinstance(data, dict):
        raise SpecError(f"{where}: a pose must be a JSON object")
    keys = set(data)
    _one_form(keys, where)
    if any(set(f) <= keys for f in POSE_FORMS):
        _unknown(data, POSE_FIELDS, where, warn)
    if {"rvec", "tvec"} <= keys:
        rvec = _vector(data["rvec"], 3, where, "rvec")
        R = cv2.Rodrigues(rvec.reshape(3, 1))[0]
        t = _vector(data["tvec"], 3, where, "tvec")
    elif {"R", "t"} <= keys:
        rows = data["R"]
        if _homogeneous(rows):
            raise SpecError(f"{where}: field 'R' is a 4×4 matrix; {_FROM_4X4}")
        if not isinstance(rows, list) or len(rows) != 3:
            raise SpecError(f"{where}: field 'R' must be 3 rows of 3 numbers")
        R = np.stack([_vector(r, 3, where, "R") for r in rows])
        if (why := _not_rotation(R)) is not None:
            raise SpecError(f"{where}: field 'R' is not a rotation matrix (orthonormal, det +1): {why}")
        U, _, Vt = np.linalg.svd(R)
        R = U @ Vt
        t = _vector(data["t"], 3, where, "t")
    elif {"q_wxyz", "t"} <= keys:
        q = _vector(data["q_wxyz"], 4, where, "q_wxyz")
        n = float(np.linalg.norm(q))
        if n < 1e-9:
            raise SpecError(f"{where}: field 'q_wxyz' must not be zero")
        if abs(n * n - 1.0) > ROTATION_TOLERANCE and warn:  # (as far from a rotation as an R refused is)
            warn(f"{where}: field 'q_wxyz' is {n:.4g} long, not 1: read as the unit quaternion "
                 f"{_shown_q(q / n)} (a unit quaternion [w, x, y, z] is expected)")
        R = quat.to_matrix(q / n)
        t = _vector(data["t"], 3, where, "t")
    else:
        square = [k for k in sorted(keys) if _homogeneous(data[k])]
        hint = f" ({square[0]!r} is a 4×4 matrix; {_FROM_4X4})" if square else ""
        raise SpecError(
            f"{where}: unknown pose format with keys {sorted(keys)}; use {{rvec, tvec}}, {{R, t}} or {{q_wxyz, t}}{hint}"
        )
    return Pose.from_matrix(R, t)


def _shown_q(q: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.4g}" for v in q) + "]"


def _xyzw_reading(data: Any) -> Pose | None:
    """The pose ``{"q_wxyz", "t"}`` would give were its quaternion written ``[x, y, z, w]`` (scipy's
    and ROS's order), to tell the user when that reading fits the photo and the given one does
    not; None for another pose form, or a quaternion whose two readings are one rotation."""
    if not isinstance(data, dict) or not {"q_wxyz", "t"} <= set(data) or "rvec" in data or "R" in data:
        return None
    try:
        x, y, z, w = (float(v) for v in data["q_wxyz"])
        swapped = Pose(np.array([w, x, y, z]), np.asarray(data["t"], float))
        given = Pose(np.array([x, y, z, w]), swapped.t)
    except (TypeError, ValueError):
        return None
    return None if swapped.allclose(given, atol=1e-6) else swapped


# how far R·Rᵀ may be from the identity: a rotation written with three decimals is up to 1.5e-3
# off (1e-3 refused one in five as "not a rotation"); it is then made exactly orthonormal
ROTATION_TOLERANCE = 5e-3
_FROM_4X4 = "give its top-left 3×3 as 'R' and the first three numbers of its last column as 't'"


def _homogeneous(value: Any) -> bool:
    """Whether ``value`` is 4 lists of 4 (a homogeneous transform ``[R t; 0 0 0 1]``)."""
    return isinstance(value, list) and len(value) == 4 and all(isinstance(r, list) and len(r) == 4 for r in value)


def _not_rotation(R: np.ndarray) -> str | None:
    """None for a rotation matrix (within :data:`ROTATION_TOLERANCE`), else what it is instead:
    a mirror, a scaled rotation (a unit change put into R), or how far from orthonormal.

    >>> _not_rotation(np.eye(3)) is None, _not_rotation(np.diag([1.0, 1, -1])), _not_rotation(10 * np.eye(3))
    (True, 'its determinant is -1 (a mirror: a left-handed frame?)', 'it scales by 10 (its rows are 10 long, not 1): a change of units belongs in the mesh or t, not in R')
    """
    det = float(np.linalg.det(R))
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if det > 0 and err <= ROTATION_TOLERANCE:
        return None
    lengths = np.linalg.norm(R, axis=1)
    scaled = lengths.min() > 0 and np.allclose(R @ R.T / lengths.mean() ** 2, np.eye(3), atol=ROTATION_TOLERANCE)
    if scaled and det < 0:
        return f"its determinant is {det:.3g} (a mirror: a left-handed frame?)"
    if scaled:
        return (f"it scales by {lengths.mean():.3g} (its rows are {lengths.mean():.3g} long, not 1): "
                "a change of units belongs in the mesh or t, not in R")
    return f"R·Rᵀ differs from the identity by up to {err:.3g} (at most {ROTATION_TOLERANCE:g} is taken)"


def _path(base: Path, value: Any, where: str, field: str) -> Path:
    if not isinstance(value, str) or not value:
        raise SpecError(f"{where}: field {field!r} must be a non-empty path string")
    path = (base / value).resolve()
    here = Path(value).resolve()
    if not path.exists() and here.exists() and here != path:  # (written relative to where the user stood)
        raise SpecError(f"{where}: field {field!r}: {path} not found; paths are relative to the spec's folder, "
                        f"and {value!r} is relative to the current one: write {os.path.relpath(here, base)!r}")
    return path


def _unknown(data: dict, known: tuple[str, ...], where: str, warn) -> None:
    """Tell ``warn`` of fields the spec does not know (a typo such as ``"mask_path"`` trained
    silently without the mask): ignored, as the contract lets a spec carry more."""
    extra = [k for k in data if k not in known]
    if extra and warn:
        warn(f"{where}: unknown field(s) {', '.join(map(repr, extra))} ignored (known: {', '.join(known)})")


def _repeated_photos(views: list[ViewSpec], path: Path) -> list[str]:
    """One message per view whose photo an earlier view names too: with the same pose it adds
    nothing but training time (a copied view), with another pose one of the two is wrong (one
    photo shows the object at one pose). Both trained without a word."""
    out = []
    first: dict[Path, ViewSpec] = {}
    for v in views:
        w = first.setdefault(v.image_path, v)
        if w is v or v.pose is None or w.pose is None:
            continue
        apart = v.pose.inverse() @ w.pose
        turn = float(np.degrees(np.linalg.norm(apart.rvec)))
        shift = float(np.linalg.norm(v.pose.t - w.pose.t))
        if turn < 1e-6 and shift <= 1e-9 * max(1.0, float(np.linalg.norm(w.pose.t))):
            out.append(f"{path}: view {v.index} repeats view {w.index} (the same photo at the same pose): it adds "
                       f"nothing but training time")
        else:
            out.append(f"{path}: view {v.index} gives view {w.index}'s photo another pose ({turn:.3g}° and "
                       f"{shift:.3g} mesh units apart): one photo shows the object at one pose; is one of them wrong?")
    return out


def _points_disagree(points: PointPairs, camera: PinholeCamera, pose: Pose) -> str | None:
    """Why a given pose and the view's clicked points disagree (None: they agree): the points'
    RMS at the pose beyond what a registration may have (:func:`~.register.max_rms_px`)."""
    if np.any(pose.apply(points.model)[:, 2] <= 0):
        return "the given pose puts some of its points behind the camera (is it object → camera?)"
    rms, limit = registration_at(points, camera, pose).rms_px, max_rms_px(camera)
    if rms <= limit:
        return None
    return (f"the given pose puts its points {rms:.1f} px (RMS) from their pixels (at most {limit:.1f}); "
            f"the pose is used — drop it to solve the pose from the points")


# what a view missing its pose can do besides (the README's step 4 gives its photos neither)
_LOCATE_HINT = ("or let `quatrack register {spec} --locate` find its pose by recognition, from the views that "
                "have one, and train the spec it writes")


def missing_pose(where: str, hint: str = "") -> str:
    """The one message for a view given neither ``pose`` nor ``points`` (``where``: the spec's
    path and the view; ``hint``: what else the caller can do, e.g. register's ``--locate``)."""
    return (f"{where}: missing field 'pose' (or 'points': at least {MIN_POINTS} clicked model points and their "
            f"pixels, from which the pose is solved{'; ' + hint if hint else ''})")


def load_spec(path: str | Path, warn=None, pose_required: bool = True, misfits: list | None = None) -> ObjectSpec:
    """Parse and check an object spec file; cameras given as paths are loaded too. ``warn``
    (optional) receives one message per object or view with fields the spec does not know.
    ``pose_required=False`` (``quatrack register --locate``) lets a view give neither ``pose`` nor
    ``points``: its ``pose`` is None, for the caller to find. ``misfits`` (a list): a view whose
    points fit no pose (:class:`~.register.PointsMisfit`) is appended to it as ``(index, error)``
    and takes their best pose instead of ending the reading (``quatrack register`` draws it)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SpecError(f"{path}: cannot read spec ({exc.strerror or exc})") from None
    try:
        data = json.loads(raw.decode("utf-8-sig"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SpecError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:
        raise SpecError(f"{path}: not valid JSON (nested too deeply)") from None
    if not isinstance(data, dict):
        raise SpecError(f"{path}: the spec must be a JSON object")
    base = path.resolve().parent
    _unknown(data, ("name", "mesh", "views"), str(path), warn)
    for key in ("name", "mesh", "views"):
        if key not in data:
            raise SpecError(f"{path}: missing field {key!r}")
    try:
        name = check_object_name(data["name"], new=True)
    except StoreError as exc:
        raise SpecError(f"{path}: field 'name': {exc}") from None
    mesh_path = _path(base, data["mesh"], str(path), "mesh")
    views_data = data["views"]
    if not isinstance(views_data, list) or not views_data:
        raise SpecError(f"{path}: field 'views' must be a non-empty list")
    # every view's fields first: a view missing its pose was refused after the warnings of the views
    # before it ("view 0: pose solved from its 6 points …"), which said nothing of the refusal
    for i, v in enumerate(views_data):
        where = f"{path}: view {i}"
        if not isinstance(v, dict):
            raise SpecError(f"{where}: must be a JSON object")
        for key in ("image", "camera"):
            if key not in v:
                raise SpecError(f"{where}: missing field {key!r}")
    posed = any("pose" in v or "points" in v for v in views_data)  # (--locate starts from those)
    for i, v in enumerate(views_data):
        if "pose" not in v and "points" not in v and pose_required:
            raise SpecError(missing_pose(f"{path}: view {i}",
                                         _LOCATE_HINT.format(spec=shlex.quote(str(path))) if posed else ""))
    views = []
    for i, v in enumerate(views_data):
        where = f"{path}: view {i}"
        _unknown(v, ("image", "camera", "pose", "mask", "points"), where, warn)
        image = _path(base, v["image"], where, "image")
        cam = v["camera"]
        if isinstance(cam, str):
            camera = load_camera(_path(base, cam, where, "camera"))
        else:
            camera = camera_from_dict(cam, f"{where}: camera")
        points = parse_points(v["points"], where) if "points" in v else None
        if "pose" in v:
            pose = parse_pose(v["pose"], f"{where}: pose", warn)
            if points is not None and warn:
                if (msg := _points_disagree(points, camera, pose)) is not None:
                    warn(f"view {i}: {msg}")
        elif points is None:
            pose = None  # (pose_required=False: the caller finds it)
        else:
            try:
                reg = pose_from_points(points, camera, where)
            except PointsMisfit as exc:
                if misfits is None:
                    raise
                misfits.append((i, exc))
                reg = exc.registration
            pose = reg.pose
            if warn:
                warn(f"view {i}: pose solved from its {len(points)} points (RMS {reg.rms_px:.1f} px); "
                     f"`quatrack register` also fits it to the mesh's edges (3–6× nearer the truth on rendered "
                     f"photos) and draws it to check")
        mask = _path(base, v["mask"], where, "mask") if v.get("mask") is not None else None
        views.append(ViewSpec(i, image, camera, pose, mask, points, "pose" not in v and points is not None,
                              _xyzw_reading(v.get("pose"))))
    if warn:
        for msg in _repeated_photos(views, path):
            warn(msg)
    return ObjectSpec(name, path.resolve(), mesh_path, tuple(views), hashlib.sha256(raw).hexdigest())

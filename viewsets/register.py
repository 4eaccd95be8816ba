"""Registering a photo: the object's pose in it from a few clicked points, refined by the mesh's edges.

Training needs each photo's pose (object → camera). A user with a mesh and a photo rarely has it,
but can always name a few points on both: "this corner of the box, ``[0, 0, 6]`` in the mesh, is
at pixel (312, 188)" — read off any image viewer. Four or more such pairs fix the pose by PnP
(:func:`pose_from_points`), to within the clicks' error of a pixel or two; the mesh's visible
edges, which the photo shows along their whole length, then pull it onto the image
(:func:`quatrack.recognition.registration.refine_with_edges`:
:func:`quatrack.recognition.evidence.edge_fit` with the clicks as its points). On the zoo's 32 training photos (8 objects × 4), 5–8 visible corners clicked with
2 px of noise gave poses 1.33 % of the diameter / 1.29° off (median; 90th percentile 2.8 % /
2.3°) by PnP, and 0.30 % / 0.42° (1.4 % / 1.2°) with the edges, which were kept for 30 of the 32;
with 4 px, 2.67 % / 2.55° and 0.47 % / 0.79° (``quatrack bench register``; ``bench/RESULTS.md``,
session 63). They help least on a thin object or a busy print beside the outline, and a refit
that leaves the clicks is not kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose

from .camera import isfinite
from .errors import SpecError

__all__ = ["LOOSE_ROTATION_DEG", "MIN_POINTS", "PointPairs", "PointsMisfit", "Registration", "check_clicked_view",
           "click_limit_px", "click_sigma", "max_rms_px", "off_mesh_message", "parse_points", "points_off_mesh",
           "pose_from_points", "registration_at", "rotation_sigma_deg"]

MIN_POINTS = 4  # PnP's unique pose needs 4 pairs (3 leave up to four poses)
MAX_RMS_SHARE = 0.01  # of the photo's diagonal: the clicks' RMS a registration may have (6.4 px at 640 × 480)
MIN_MAX_RMS_PX = 3.0


@dataclass(frozen=True)
class PointPairs:
    """Clicked pairs: ``model`` (n, 3) points in the mesh's units and the ``pixel`` (n, 2) each is
    seen at in the photo (pixel centres at integer coordinates, as OpenCV)."""

    model: np.ndarray
    pixel: np.ndarray

    def __len__(self) -> int:
        return len(self.model)


@dataclass(frozen=True)
class Registration:
    """A photo's pose and how well the clicks support it: ``rms_px`` (the clicks' reprojection
    RMS at ``pose``), ``worst`` (the index of the click farthest from its point's projection) and
    ``worst_px``; after :func:`refine_with_edges` also ``edge_agreement`` (the share of the
    visible model edges on the photo's edges, before → after the refit), ``moved`` (how far the
    edges moved the pose: ``(|Δc| / diameter, Δθ in degrees)``, ``c`` the object's centre; None:
    not moved) and ``refused`` (the refit not kept, with its own figures)."""

    pose: Pose
    rms_px: float
    worst: int
    worst_px: float
    edge_agreement: tuple[float, float] | None = None
    moved: tuple[float, float] | None = None
    refused: "Registration | None" = None


def max_rms_px(camera: PinholeCamera) -> float:
    """The clicks' RMS a registration may have: 1 % of the photo's diagonal, at least 3 px (a
    click on the wrong corner lies tens of pixels off; a careful one within 2)."""
    if camera.width is None or camera.height is None:
        return float("inf")
    return max(MIN_MAX_RMS_PX, MAX_RMS_SHARE * float(np.hypot(camera.width, camera.height)))


def parse_points(value: Any, where: str) -> PointPairs:
    """``[{"model": [x, y, z], "pixel": [u, v]}, ...]`` (at least :data:`MIN_POINTS`) → pairs.

    >>> p = parse_points([{"model": [0, 0, 0], "pixel": [1, 2]}] * 4, "view 0")
    Traceback (most recent call last):
    ...
    quatrack.viewsets.errors.SpecError: view 0: points 0 and 1 are the same model point (each must be another point of the mesh)
    """
    if not isinstance(value, list):
        raise SpecError(f"{where}: field 'points' must be a list of {{\"model\": [x, y, z], \"pixel\": [u, v]}}")
    model, pixel = [], []
    for i, item in enumerate(value):
        if not isinstance(item, dict) or not {"model", "pixel"} <= set(item):
            raise SpecError(f"{where}: point {i} must be an object with 'model' ([x, y, z] in the mesh's units) "
                            f"and 'pixel' ([u, v] in the photo)")
        for key, n in (("model", 3), ("pixel", 2)):
            v = item[key]
            if (not isinstance(v, list) or len(v) != n
                    or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and isfinite(x) for x in v)):
                raise SpecError(f"{where}: point {i}: field {key!r} must be a list of {n} finite numbers")
        model.append(item["model"])
        pixel.append(item["pixel"])
    if len(model) < MIN_POINTS:
        raise SpecError(f"{where}: {len(model)} points given, at least {MIN_POINTS} are needed to fix a pose "
                        f"(corners of the object are the easiest to click)")
    X = np.asarray(model, float)
    uv = np.asarray(pixel, float)
    for name, arr in (("model", X), ("pixel", uv)):
        # (the largest coordinate difference, relative to the median coordinate: one point given
        # absurdly far, 1e300, made every other pair "the same" and the squares overflowed)
        d = np.abs(arr[:, None] - arr[None]).max(axis=2)
        i, j = np.nonzero(np.triu(d <= 1e-9 * max(float(np.median(np.abs(arr))), 1.0), 1))
        if len(i):
            what = "model point (each must be another point of the mesh)" if name == "model" else "pixel"
            raise SpecError(f"{where}: points {i[0]} and {j[0]} are the same {what}")
    return PointPairs(X, uv)


def _collinear(X: np.ndarray) -> bool:
    """Whether the points lie (nearly) on one line: their spread's second axis is under 1 % of the first."""
    X = X / max(float(np.abs(X).max()), 1e-300)  # (scale-free; 1e300 overflowed the SVD)
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    return s[0] <= 0 or s[1] < 1e-2 * s[0]


def _without_farthest(X: np.ndarray) -> np.ndarray:
    """The points but the one farthest from their median. Why: one coordinate mistyped (1608 for
    8 on a 16-unit box) stretches the spread so that the others look like a line beside it, and
    "on one line" sent the user to add points when one was wrong (PnP's misfit names it)."""
    far = int(np.argmax(np.abs(X - np.median(X, axis=0)).max(axis=1)))
    return np.delete(X, far, axis=0)


def _outside(pixel: np.ndarray, camera: PinholeCamera) -> str | None:
    """Why some clicked pixels cannot be this photo's (None: all lie in it; a camera sized by
    its images is asked again once sized): outside its ``width × height``. Why: clicks read
    off a resized copy or a zoomed viewer fit no pose, and were blamed on "no one point" or the
    mesh's units."""
    if camera.width is None or camera.height is None:
        return None
    w, h = camera.width, camera.height
    out = np.nonzero((pixel[:, 0] < -0.5) | (pixel[:, 0] > w - 0.5) | (pixel[:, 1] < -0.5) | (pixel[:, 1] > h - 0.5))[0]
    if not len(out):
        return None
    u, v = pixel[out[0]]
    return (f"point {out[0]}'s pixel ({u:.6g}, {v:.6g}) lies outside the {w}×{h} photo ({len(out)} of {len(pixel)} "
            f"clicks do): give the pixels of this photo at its full size (not of a resized copy or a zoomed "
            f"view), u across from the left, v down from the top")


def _residuals(pairs: PointPairs, camera: PinholeCamera, pose: Pose) -> np.ndarray:
    Xc = pairs.model @ pose.R.T + pose.t
    return np.linalg.norm(camera.project(Xc) - pairs.pixel, axis=1)


def registration_at(pairs: PointPairs, camera: PinholeCamera, pose: Pose, **extra) -> Registration:
    """The clicks' figures at ``pose`` (their RMS, the worst one), ``extra`` fields added."""
    r = _residuals(pairs, camera, pose)
    worst = int(np.argmax(r))
    return Registration(pose, float(np.sqrt(np.mean(r ** 2))), worst, float(r[worst]), **extra)


def pose_from_points(pairs: PointPairs, camera: PinholeCamera, where: str = "view") -> Registration:
    """The pose that puts the model points on their pixels: SQPnP's global least-squares solution
    (planar or not, no start needed), polished by Levenberg–Marquardt on the reprojection error
    ``Σ ‖π(R Xᵢ + t) − uᵢ‖²`` (lens distortion included).

    Refused, with the reason (:class:`SpecError`): points on one line (a rotation about it is
    free), a pose that puts a point behind the camera, and clicks whose RMS exceeds
    :func:`max_rms_px` — then the click farthest from its point is named, usually a corner
    clicked for its neighbour or a point given in other units than the mesh."""
    if len(pairs) < MIN_POINTS:
        raise SpecError(f"{where}: {len(pairs)} points given, at least {MIN_POINTS} are needed to fix a pose")
    if _collinear(pairs.model) and _collinear(_without_farthest(pairs.model)):
        raise SpecError(f"{where}: the points lie on one line in the model: add points off that line")
    if (outside := _outside(pairs.pixel, camera)) is not None:
        raise SpecError(f"{where}: {outside}")
    pose = _solve(pairs.model, pairs.pixel, camera, polish=True)
    if pose is None:
        raise SpecError(f"{where}: no pose fits the points (are the pixels in this photo and the model points in the mesh's units?)")
    z = (pairs.model @ pose.R.T + pose.t)[:, 2]
    if np.any(z <= 0):
        raise SpecError(f"{where}: the best pose puts point {int(np.argmin(z))} behind the camera: "
                        f"are the pixels in this photo and the model points in the mesh's units?")
    reg = registration_at(pairs, camera, pose)
    limit = max_rms_px(camera)
    if reg.rms_px > limit:
        raise PointsMisfit(f"{where}: the points do not fit one pose: RMS {reg.rms_px:.1f} px (at most {limit:.1f}); "
                           f"{_culprit(pairs, camera, reg, limit)}", reg)
    return reg


class PointsMisfit(SpecError):
    """Clicks that fit no pose (:func:`pose_from_points`); ``registration`` is their best pose,
    for a picture of where it puts them (``quatrack register --overlay``)."""

    def __init__(self, message: str, registration: Registration):
        super().__init__(message)
        self.registration = registration


def _solve(X: np.ndarray, uv: np.ndarray, camera: PinholeCamera, polish: bool = False) -> Pose | None:
    """SQPnP's pose of the pairs (``polish``: then Levenberg–Marquardt on the reprojection
    error), None when OpenCV finds none or a non-finite one."""
    K, dist = camera.matrix, np.asarray(camera.dist_coeffs, float)
    X, uv = np.ascontiguousarray(X, np.float64), np.ascontiguousarray(uv, np.float64)
    try:
        ok, rvec, tvec = cv2.solvePnP(X, uv, K, dist, flags=cv2.SOLVEPNP_SQPNP)
        if ok and polish:
            rvec, tvec = cv2.solvePnPRefineLM(X, uv, K, dist, rvec, tvec)
    except cv2.error:
        return None
    if not ok or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return None
    return Pose.from_matrix(cv2.Rodrigues(rvec)[0], tvec.ravel())


def _culprit(pairs: PointPairs, camera: PinholeCamera, reg: Registration, limit: float) -> str:
    """Which click is wrong, said as surely as the clicks allow. With 5 or more, the one whose
    removal lets the others fit (their RMS within ``limit``) — PnP's worst residual can be a right
    click pulled aside by a wrong one; with 4, one wrong click cannot be told from the others
    (the other 3 fit some pose whichever is left out)."""
    n = len(pairs)
    if n <= MIN_POINTS:
        return (f"with {n} points one wrong click cannot be told from the others: check each (the right point of "
                f"the mesh, its pixel in this photo), or add a point")
    fits = []
    for i in range(n):
        keep = np.arange(n) != i
        pose = _solve(pairs.model[keep], pairs.pixel[keep], camera)
        if pose is None:
            continue
        others = PointPairs(pairs.model[keep], pairs.pixel[keep])
        rms = float(np.sqrt(np.mean(_residuals(others, camera, pose) ** 2)))
        fits.append((rms, i, float(_residuals(PointPairs(pairs.model[i:i + 1], pairs.pixel[i:i + 1]), camera, pose)[0])))
    good = sorted(f for f in fits if f[0] <= limit)
    if len(good) == 1 or (good and good[0][0] < 0.5 * good[1][0]):
        rms, i, off = good[0]
        return (f"point {i} lies {off:.0f} px from where the pose of the others puts it (they fit to {rms:.1f} px) — "
                f"is it the right point of the mesh, and its pixel in this photo?")
    return (f"no one point explains it (point {reg.worst} lies farthest, {reg.worst_px:.0f} px, from the best pose): "
            f"are the model points in the mesh's units, and the pixels in this photo?")


def click_limit_px(n: int, click_sigma_px: float) -> float:
    """The clicks' RMS a refitted pose may leave: ``σ √(χ²₂ₙ(0.99) / n)`` — at the true pose the
    ``n`` clicks' squared errors over ``σ²`` sum to a χ² with ``2n`` degrees of freedom, so a
    pose that leaves more has left the clicks, not found the edges (4.1 px for 7 clicks at σ 2)."""
    from scipy.stats import chi2

    return float(click_sigma_px * np.sqrt(chi2.ppf(0.99, 2 * n) / n))


def click_sigma(reg: Registration, n: int, click_sigma_px: float) -> float:
    """The clicks' σ (px per coordinate): the larger of the one stated and the one PnP's
    residual shows, ``rms · √(n / (2n − 6))`` (``n`` clicks: ``n · rms²`` sums 2n squared
    coordinates, 6 of them fitted; ``reg`` from :func:`pose_from_points`). Why both: a user's
    clicks are as careful as they are, and a gate set for 2 px refused every refit of clicks
    4 px off."""
    seen = reg.rms_px * np.sqrt(n / (2 * n - 6)) if n > 3 and np.isfinite(reg.rms_px) else 0.0
    return float(max(click_sigma_px, seen))


LOOSE_ROTATION_DEG = 3.0  # the clicks' rotation 1σ above which register says to click more (see rotation_sigma_deg)


def rotation_sigma_deg(pairs: PointPairs, camera: PinholeCamera, pose: Pose, sigma_px: float) -> float:
    """How loosely the clicks alone fix the pose's rotation: the 1σ (degrees, about its worst
    axis) of ``σ² (JᵀJ)⁻¹``, ``J`` the clicks' reprojection Jacobian over a small rotation and
    translation at ``pose`` (its rotation block, the translation free). Why: four corners of one
    face seen face-on leave its tilt to ±3–7° at 2 px (PnP 5–18° off in 7 of 24 zoo photos
    clicked so); corners of two faces fix it to about 1°. inf when the clicks fix no pose."""
    R0, t0 = pose.R, pose.t
    h = np.concatenate([np.full(3, 1e-6), np.full(3, 1e-6 * max(float(np.linalg.norm(t0)), 1.0))])

    def uv(p: np.ndarray) -> np.ndarray:
        R = cv2.Rodrigues(p[:3].reshape(3, 1))[0] @ R0
        return camera.project(pairs.model @ R.T + t0 + p[3:]).ravel()

    J = np.column_stack([(uv(d) - uv(-d)) / (2 * d[k]) for k, d in enumerate(np.diag(h))])
    with np.errstate(all="ignore"):
        A = J.T @ J
        if not np.all(np.isfinite(A)) or np.linalg.matrix_rank(A) < 6:
            return float("inf")
        C = sigma_px ** 2 * np.linalg.inv(A)
    return float(np.degrees(np.sqrt(max(float(np.linalg.eigvalsh(C[:3, :3]).max()), 0.0))))


OFF_MESH_SHARE = 0.05  # of the mesh's diameter: how far a clicked model point may lie from its surface


def points_off_mesh(points: np.ndarray, mesh, share: float = OFF_MESH_SHARE) -> list[tuple[int, float]]:
    """``(index, distance)`` of the model points farther than ``share`` × the diameter from the
    mesh's surface (exact point–triangle distances, trimesh's). Why: a point given in other units
    than the mesh (cm for a mesh in mm: 10× too near its origin) or of another object still fits
    *some* pose — PnP cannot tell — but not one the photo shows (bench: the edges then agree 0 %).

    >>> from quatrack.viewsets.mesh import make_mesh
    >>> tri = make_mesh(np.array([[0., 0, 0], [10, 0, 0], [0, 10, 0]]), np.array([[0, 1, 2]]))
    >>> points_off_mesh(np.array([[1., 1, 0], [1, 1, 3]]), tri)
    [(1, 3.0)]
    """
    import trimesh

    tris = mesh.triangles
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    limit = share * float(mesh.extent)
    out = []
    for i, p in enumerate(np.asarray(points, float)):
        # only the triangles whose box lies no farther than the nearest vertex can hold the
        # nearest point (a box's distance never exceeds its triangle's): a scan's 786 432
        # triangles took ~0.5 s a point against all of them, a few dozen now
        box = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=1)
        near_vertex = float(np.sqrt(((tris - p) ** 2).sum(axis=2)).min())  # (a triangle's corner: never none)
        cand = tris[box <= near_vertex]
        near = trimesh.triangles.closest_point(cand, np.repeat(p[None], len(cand), axis=0))
        d = float(np.sqrt(((near - p) ** 2).sum(axis=1)).min())
        if d > limit:
            out.append((i, d))
    return out


def off_mesh_message(points: np.ndarray, mesh, where: str) -> str | None:
    """:func:`points_off_mesh` said for a user (None when every point lies on the mesh)."""
    off = points_off_mesh(points, mesh)
    if not off:
        return None
    i, d = off[0]
    span = " × ".join(f"{x:.3g}" for x in np.ptp(mesh.vertices, axis=0))
    return (f"{where}: point {i}'s model coordinates lie {d:.3g} from the mesh's surface "
            f"({len(off)} of {len(points)} points off it; the mesh spans {span}): are they in the mesh's units, "
            f"on this object?")


def check_clicked_view(view, mesh, warn=None) -> None:
    """What ``quatrack train`` checks of a view whose pose was solved from its clicks, once its
    photo has sized its camera (``view.pose_from_points``): the clicks on the mesh
    (:func:`off_mesh_message`) and fitting one pose in the photo (:func:`pose_from_points` again:
    a camera sized by its images had no bound at :func:`~.spec.load_spec`) — a :class:`SpecError`
    otherwise; and ``warn`` told when they fix its rotation loosely (:func:`rotation_sigma_deg`).
    The edges' refit is ``quatrack register``'s (:mod:`quatrack.recognition.registration`: a
    higher layer), which brings such poses 3–6× nearer the truth."""
    if (msg := off_mesh_message(view.points.model, mesh, f"view {view.index}")) is not None:
        raise SpecError(msg)
    reg = pose_from_points(view.points, view.camera, f"view {view.index}")
    sd = rotation_sigma_deg(view.points, view.camera, view.pose, click_sigma(reg, len(view.points), 2.0))
    if warn and sd > LOOSE_ROTATION_DEG:
        warn(f"view {view.index}: its clicks fix the rotation only to ±{sd:.1f}° (1σ): click corners of a second "
             f"face too, or run `quatrack register`, which also fits the pose to the mesh's edges")

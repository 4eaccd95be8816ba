"""Recognition and initial pose, the path behind ``quatrack locate`` and ``POST .../pose``.

``locate`` = :func:`~quatrack.recognition.window_search.search_window` (RFCH window; its time is reported as ``localise``) → SIFT in the window plus a margin → match to every viewset →
the viewset with most matches → RANSAC PnP + refinement → verification (geometry, then evidence
in the image a wrong pose cannot fake: :func:`quatrack.recognition.pose.verification`) → the
verified pose reported as a robust (Cauchy) fit of its inliers (:func:`quatrack.recognition.pose.polish`). If the
window yields no verified pose, the whole image is searched before giving up. Per-stage times are
reported. :func:`locate_all` searches every given model (``--object all``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.viewsets.features import Features, stretched
from quatrack.viewsets.store import ObjectModel

from .appearance import TextureAgreement, texture_agreement, texture_refit
from .fields import check_field_kinds
from .images import DEFAULT_MAX_PIXELS, prepare_image
from .window_search import Window, WindowSearchParams, search_window
from .match import ModelIndex, index_for, rank_viewsets
from .evidence import pose_shift
from .pose import (RANSAC_SAMPLE, PnPSolution, PoseParams, Verification, polish, reprojection_rms, rival_inliers,
                   solve_pnp, value_key, verification, verify)


# The verification's evidence (edges, texture) is read on the grey image brought up, when it is
# dim, until its brightest 1 % (the 99th percentile) reaches this level: the edges' thresholds are
# absolute (``EdgeParams.min_grad``, grey levels), set on images whose brightest 1 % lies at
# 190–255, and an under-exposed photo (×0.3: p₉₉ ≈ 75) had its poses matched and then refused,
# "the model's edges do not lie on image edges" (a user's trial: the zoo's slab 1 of 16 found,
# the cookie box 6; brought up to 128, 16 and 16, none wrong). A brighter image is read as it is.
# (SIFT brightens a dim query further, to 230: viewsets.features.RUN_TIME_STRETCH; its
# descriptors are normalised, the evidence's thresholds are not.)
EVIDENCE_MIN_P99 = 128.0


@dataclass(frozen=True)
class LocateParams:
    window: WindowSearchParams = field(default_factory=WindowSearchParams)
    pose: PoseParams = field(default_factory=PoseParams)
    margin: float = 0.25  # the window is enlarged by this fraction on every side for SIFT
    # SIFT sees the window (plus margin) shrunk so that the window's longer side is at most this
    # many pixels (never enlarged; None: full resolution). SIFT's cost grows with the area (it
    # doubles its input first), and the viewsets hold the object at 0.6–1.4× the registered
    # photos' size, so a shrunk object still matches (bench/RESULTS.md, "Speed (issue 13)").
    # 200 → 160 (session 19): SIFT ×0.64 the area, ~10 % less CPU per scene; the same success on
    # 200 cookie-box scenes × 4 FLANN forests and on the zoo (bench/RESULTS.md, issue 13 speed)
    sift_object_px: float | None = 160.0
    retry_full_resolution: bool = True  # a shrunk window without a verified pose is described again at full size
    # the whole-image fallback after a failed window describes the frame shrunk so that the
    # object's typical size (:func:`typical_object_px`) is at most this many pixels (and never
    # larger than the window's scale); None: at the window's scale. SIFT of the whole frame was
    # the slow tail of locate (bench/RESULTS.md, session 18)
    fallback_object_px: float | None = 200.0
    # When several models are searched in one image (locate_all), a model's fallback reuses a
    # whole-image pass another model described at a scale up to 2^(1/fallback_scale_steps) finer
    # than its own (:func:`shared_features`: never less detail, no pass of its own); None: every
    # model describes its own. A single model is searched exactly as before
    fallback_scale_steps: int | None = 4
    viewsets_tried: int = 2  # the best and the runner-up
    # each tried viewset's matches found again against that view alone (ModelIndex.match_view)
    # instead of the shared index's share of them: for models with many near-identical views
    # (the tracker's keyframes and their synthetic views), whose votes split between them
    rematch_views: bool = False
    prefer_tried: int = 8  # locate(prefer=…): that many of the preferred views are tried, the most matched first
    pool_all: bool = True  # then all matches of every viewset together
    whole_image_fallback: bool = True
    # the whole image's search asks for a consensus of at least this many inliers (None:
    # ``pose.min_inliers``): the whole frame's clutter matches by the hundred, and chance
    # consensuses of a few of them cost a verification each. At 6 the PnP stage of an image
    # without the object took ~16× longer (8 models: 14 → 230 ms) for ~6 more right poses in 384
    # zoo scenes (session 41, bench/RESULTS.md)
    fallback_min_inliers: int | None = 12
    # RANSAC on few matches stops after the draws that would have found a consensus of
    # ``pose.min_inliers`` with this probability (:func:`ransac_iterations_bound`)
    ransac_bound_confidence: float = 0.9999
    use_window: bool = True  # False: skip localisation, match in the whole image
    # a verified pose must look as the model's photos show the object (ObjectModel.appearance,
    # recognition/appearance.py): their crops rendered at the pose correlate with the image at
    # least this well where they show what the pose shows (~1 right; ~0 another face's texture;
    # faces sharing texture and outline — a cube turned by 90° — pass SIFT consensus and the
    # edges). 0: off; a model without photos (stored before session 36) is not judged so
    min_texture_ncc: float = 0.5
    # ... and the verified pose is then polished by that texture (:func:`_texture_polished`):
    # the photos rendered at the pose are followed into the image (:func:`.appearance.texture_refit`)
    # and the pose solved there is reported where it rests on at least
    # ``texture_polish_min_inliers`` points and the photos correlate with the image there no worse
    # than ``texture_polish_tolerance`` below the verified pose's. `bench locate --zoo` seeds
    # 0–15 (6144 scenes): poses beyond 5 %/5° 23 → 9, right ones 4003 → 4017, the median error
    # 0.31 → 0.11 % of the diameter and 0.26 → 0.09° (bench/RESULTS.md, session 70). Refits on
    # few points (12–17) had moved right poses off by up to 6°, as had one the texture read worse.
    # The texture is read again only where the refit moved the pose by at least
    # ``texture_polish_check_shift`` of the 5 %/5° criterion (~2.5 ms saved; 83 % of the refits
    # move it less, and so small a move cannot take a right pose far past the criterion)
    texture_polish: bool = True
    texture_polish_min_inliers: int = 20
    texture_polish_tolerance: float = 0.01
    texture_polish_check_shift: float = 0.2
    max_pixels: int = DEFAULT_MAX_PIXELS

    def __post_init__(self) -> None:
        # (a string was "'<=' not supported" deep in prepare_image; 0 or less shrank every image to
        # 32 px; at least 1, as QUATRACK_LOCATE_MAX_PIXELS)
        v = self.max_pixels
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"max_pixels must be a whole number of pixels, at least 1, got {v!r}"[:120])
        check_field_kinds(self, {"WindowSearchParams": WindowSearchParams, "PoseParams": PoseParams})


@dataclass
class Located:
    """The answer for one image (pixels of the original image; pose in mesh units).

    Answers compare by value (``==``: every field, arrays number for number, exactly; not
    ``time_ms``, which measures the machine, not the answer: the same image gives equal answers).
    Not hashable: an answer may be changed after it is made (:func:`locate_all` marks one not
    found)."""

    found: bool
    # (x, y, w, h): found, the object's box in the image (its mesh projected at the pose); not
    # found, the RFCH window searched (None when none was). Before session 64 a pose found in
    # the window had the window's box, on a 16-px grid and often beside the object
    bbox: tuple[float, float, float, float] | None = None
    chi2: float | None = None
    viewset: str | None = None
    matches: int = 0
    inliers: int = 0
    reprojection_rms_px: float | None = None
    t: np.ndarray | None = None
    q_wxyz: np.ndarray | None = None
    covariance: np.ndarray | None = None
    time_ms: dict = field(default_factory=dict, compare=False)
    reason: str | None = None  # why not found
    searched: str = "window"  # "window" or "image": where the pose came from
    verification: dict | None = None  # the evidence for the last pose checked (issue 13)
    object: str | None = None  # the model's name
    # (x, y, w, h): the RFCH window searched (the localisation's answer, found or not); None when
    # the whole image was searched without one
    window: tuple[float, float, float, float] | None = None
    # locate_all only (None from locate): for a found object, the objects found at the same
    # place with less confidence and so reported not found in its place, each
    # ``{"object", "confidence", "pose"}``, the most confident first: a look-alike (the same
    # print at another size) that one camera cannot tell apart from it (bench: a 0.003 margin)
    rivals: list | None = None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Located):
            return NotImplemented
        return self is other or value_key(self) == value_key(other)

    __hash__ = None  # (mutable: see the class's doc)

    @property
    def pose(self) -> Pose | None:
        """The pose (object → camera) when found."""
        return Pose(self.q_wxyz, self.t) if self.found else None

    @property
    def confidence(self) -> float:
        """The verification's calibrated confidence (0 when nothing was verified)."""
        return float(self.verification["confidence"]) if self.found and self.verification else 0.0

    def to_json(self) -> dict:
        """The contract's JSON object (``image`` is added by the caller), plus the extensions
        ``reason``, ``searched``, ``object`` and ``verification`` (and ``rivals``, from
        :func:`locate_all` only)."""
        out = {
            "object": self.object,
            "found": self.found,
            "bbox": None if self.bbox is None else [round(float(v), 2) for v in self.bbox],
            "window": None if self.window is None else [round(float(v), 2) for v in self.window],
            "chi2": None if self.chi2 is None else float(self.chi2),
            "viewset": self.viewset,
            "matches": int(self.matches),
            "inliers": int(self.inliers),
            "reprojection_rms_px": None if self.reprojection_rms_px is None else float(self.reprojection_rms_px),
            "pose": None if not self.found else {"t": [float(v) for v in self.t], "q_wxyz": [float(v) for v in self.q_wxyz]},
            "covariance": None if not self.found else [[float(v) for v in row] for row in self.covariance],
            "time_ms": {k: round(v, 3) for k, v in self.time_ms.items()},
            "reason": self.reason,
            "searched": self.searched,
            "verification": self.verification,
        }
        if self.rivals is not None:
            out["rivals"] = self.rivals
        return out


def _crop_box(bbox, margin: float, w: int, h: int) -> tuple[int, int, int, int]:
    x, y, bw, bh = bbox
    x0 = int(max(0, np.floor(x - margin * bw)))
    y0 = int(max(0, np.floor(y - margin * bh)))
    x1 = int(min(w, np.ceil(x + bw * (1 + margin))))
    y1 = int(min(h, np.ceil(y + bh * (1 + margin))))
    return x0, y0, x1, y1


@dataclass
class _Search:
    """What the pose search found: the pose (None if none verified), the matches used, why not,
    the viewset's label, the last verification."""

    est: PnPSolution | None = None
    matches: int = 0
    reason: str | None = None
    viewset: str | None = None
    verification: Verification | None = None


def _pose_from(
    features: Features, index: ModelIndex, model: ObjectModel, camera: PinholeCamera,
    window: tuple | None, params: LocateParams, timer: dict, grey: np.ndarray, prefer=None,
) -> _Search:
    """Match, rank viewsets by votes, PnP on the best one's matches (then the runner-up's, then
    the most matched of ``prefer``, then all matches pooled); the first pose that passes the
    geometric checks and the image evidence wins (a rival consensus among the other matches
    counts against it)."""
    t0 = time.perf_counter()
    matches = index.match(features)
    ranked = rank_viewsets(matches, len(model.viewsets))
    views = ranked[: params.viewsets_tried]
    own = {v: index.match_view(features, v) for v in views} if params.rematch_views else {}
    if prefer is not None and len(prefer):
        # the preferred views, each re-matched alone, the most matched first
        extra = {int(v): index.match_view(features, int(v)) for v in prefer if int(v) not in views}
        order = sorted(extra, key=lambda v: -len(extra[v]))[: params.prefer_tried]
        own.update((v, extra[v]) for v in order)
        views = views + order
    timer["match"] = timer.get("match", 0.0) + (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    trials = [(model.viewsets[v].label, np.flatnonzero(matches.viewset == v), own.get(v)) for v in views]
    if params.pool_all and ranked:  # (the shared index's matches)
        trials.append((model.viewsets[ranked[0]].label, np.arange(len(matches)), None))
    out = _Search(None, len(trials[0][1]) if trials else 0, "no viewset has enough matches",
                  trials[0][0] if trials else None)
    uv_all = features.keypoints[matches.query_idx] if len(matches) else np.zeros((0, 2))
    try:
        for label, keep, alone in trials:
            m, keep = (matches.subset(keep), keep) if alone is None else (alone, np.arange(len(alone)))
            if len(keep) < params.pose.min_inliers:
                continue
            vs = model.viewsets[int(np.bincount(m.viewset).argmax())]
            prior = (vs.pose.R, vs.pose.t, model.mesh.centre)
            uv = features.keypoints[m.query_idx]
            pose_params = params.pose
            cap = ransac_iterations_bound(len(keep), pose_params.min_inliers, RANSAC_SAMPLE, params.ransac_bound_confidence)
            if cap < pose_params.ransac_iterations:
                pose_params = replace(pose_params, ransac_iterations=cap)
            est = solve_pnp(camera, m.points3d, uv, pose_params, prior)
            if est is None:
                out.reason = f"PnP found no consensus ({len(keep)} matches, viewset {label})"
                continue
            why = verify(est, len(keep), camera, model.mesh, window, params.pose, m.points3d, m.normals, prior)
            if why is not None:
                out.reason = f"{why} (viewset {label})"
                continue
            # a rival: the best other consensus among all matches that are not this pose's inliers
            # (as rows of all matches; a re-matched view's inliers by their query features)
            inl_all = keep[est.inliers] if alone is None else \
                np.flatnonzero(np.isin(matches.query_idx, m.query_idx[est.inliers]))
            rest = np.setdiff1d(np.arange(len(matches)), inl_all)
            # measured only if the pose passes the cheaper checks before the rival's (a RANSAC)
            rival = (lambda inl_all=inl_all, est=est: rival_inliers(
                camera, matches.points3d, uv_all, PnPSolution(est.pose, est.covariance, inl_all, est.rms_px),
                model.mesh, params.pose, grey)) if len(rest) >= params.pose.min_inliers else 0
            ver = verification(est, grey, camera, model.mesh, uv, params.pose, rival, m.points3d)
            out.verification = ver
            if ver.passed and ver.fixed_by_edges:  # reported where the points and the edges agree
                fit = ver.edge_fit
                est = PnPSolution(fit.pose, ver.fixed_covariance, est.inliers, fit.points_rms_px, est.ties)
            elif ver.passed:
                est = polish(est, camera, m.points3d, uv, params.pose)
            if ver.passed:
                ver, agreement = _with_texture(ver, model, index, grey, camera, est.pose, params.min_texture_ncc)
                if ver.passed and params.texture_polish and agreement is not None and agreement.pixels:
                    est, ver = _texture_polished(est, ver, agreement, model, index, grey, camera, m.points3d, uv,
                                                 params)
                out.verification = ver
            if ver.passed:
                out.est, out.matches, out.reason, out.viewset = est, len(keep), None, label
                return out
            out.reason = f"{ver.reason} (viewset {label})"
        return out
    finally:
        timer["pnp"] = timer.get("pnp", 0.0) + (time.perf_counter() - t0) * 1e3


def _with_texture(ver: Verification, model: ObjectModel, index: ModelIndex, grey: np.ndarray, camera: PinholeCamera,
                  pose: Pose, min_ncc: float) -> tuple[Verification, TextureAgreement | None]:
    """``ver`` with the texture evidence of ``pose`` (:func:`~.appearance.texture_agreement` of
    the model's photos, rendered once in ``index``), refused below ``min_ncc`` where they show
    what the pose shows; and that evidence (None: not measured)."""
    if not min_ncc or not index.appearance:
        return ver, None
    a = texture_agreement(grey, camera, pose, model.mesh, index.planes, index.appearance)
    ver = replace(ver, texture_ncc=None if not a.pixels else a.ncc, texture_pixels=a.pixels)
    if a.pixels and a.ncc < min_ncc:
        return replace(ver, passed=False, reason=f"the object's photos rendered at the pose correlate {a.ncc:.2f} "
                       f"with the image over {a.pixels} px (at least {min_ncc:g} needed): another face's texture"), a
    return ver, a


def _texture_polished(est: PnPSolution, ver: Verification, agreement: TextureAgreement, model: ObjectModel,
                      index: ModelIndex, grey: np.ndarray, camera: PinholeCamera, points3d: np.ndarray,
                      uv: np.ndarray, params: LocateParams) -> tuple[PnPSolution, Verification]:
    """The verified pose ``est`` polished by the model's photos: their texture rendered at the
    pose, followed into the image and the pose solved there (:func:`~.appearance.texture_refit`,
    reusing ``agreement``'s renders), kept where it rests on at least
    ``params.texture_polish_min_inliers`` points and the photos correlate with the image there
    at least ``ρ_pose − params.texture_polish_tolerance``; else ``est`` as it was.

    Why: SIFT's inliers on one face at a slant leave the pose's tilt and depth loose (a flat box
    verified 5.3 % / 7.2° off, its edges agreeing within 1.5 px); the photos' texture followed
    densely — ~100 corners at the pixel, not ~20 matches at a few — pins it (that pose polished:
    3.1 % / 4.3°). A pose is not found by this step, only moved: the evidence that verified it
    (inliers, edges, confidence) stays; the inliers' reprojection RMS is the polished pose's, and
    so is the texture's correlation where the refit moved the pose by at least
    ``params.texture_polish_check_shift`` of the criterion (read again there, and the refit kept
    only if it holds; a smaller move keeps the verified pose's reading). The covariance stays
    the verified pose's: wide for the polished pose (NEES median 0.10 on 977 right zoo poses,
    χ²₆'s is 5.35), where the refit's own (its consensus's least-squares covariance) was too
    tight by ~5× (NEES median 24.6; bench/RESULTS.md, session 70).
    ``verification.texture_polish`` reports the refit's points and how far it moved the pose
    (in units of the 5 %/5° criterion, :func:`~.evidence.pose_shift`)."""
    fit = texture_refit(grey, camera, est.pose, model.mesh, index.planes, index.appearance,
                        rendered=agreement.rendered)
    if fit.pose is None or fit.inliers < params.texture_polish_min_inliers:
        return est, replace(ver, texture_polish={"inliers": int(fit.inliers), "shift": None, "kept": False})
    shift = pose_shift(est.pose, fit.pose, model.mesh)
    note = {"inliers": int(fit.inliers), "shift": round(float(shift), 4), "kept": False}
    if shift >= params.texture_polish_check_shift:
        there = texture_agreement(grey, camera, fit.pose, model.mesh, index.planes, index.appearance)
        if not there.pixels or not there.ncc >= agreement.ncc - params.texture_polish_tolerance:
            return est, replace(ver, texture_polish=note)
        ver = replace(ver, texture_ncc=there.ncc, texture_pixels=there.pixels)
    rms = reprojection_rms(camera, points3d[est.inliers], uv[est.inliers], fit.pose.t, fit.pose.q_wxyz)
    return (PnPSolution(fit.pose, est.covariance, est.inliers, rms, est.ties),
            replace(ver, texture_polish={**note, "kept": True}))


def ransac_iterations_bound(n: int, k: int, sample: int = RANSAC_SAMPLE, confidence: float = 0.9999) -> int:
    """RANSAC iterations after which a consensus of at least ``k`` among ``n`` matches would have
    been found with probability ``confidence``: a sample of ``sample`` matches is all inliers
    with probability at least ``p = C(k, s) / C(n, s)``, so ``N = ⌈log(1 − confidence) / log(1 − p)⌉``
    draws miss every all-inlier sample with probability at most ``1 − confidence``.

    Why: a pose is refused with fewer than ``min_inliers`` inliers anyway, and a set of few
    matches without such a consensus ran all of RANSAC's iterations (``PoseParams.ransac_iterations``)
    before giving up — the slow tail of locate (bench/RESULTS.md, issue 13 speed). With AP3P's
    samples of 4 (:func:`~.pose.ransac_pnp`), 17 matches and k = 12 the bound is 40 draws; from
    27 matches on it exceeds the 300 draws and changes nothing. The draws before the cap are the
    ones RANSAC made anyway: capping only cuts a hopeless search short.

    >>> ransac_iterations_bound(17, 12), ransac_iterations_bound(12, 12), ransac_iterations_bound(27, 12) > 300
    (40, 1, True)
    >>> ransac_iterations_bound(17, 12, sample=5)  # EPnP's samples of 5 (before session 24)
    68
    """
    if n <= k:
        return 1
    p = math.comb(k, sample) / math.comb(n, sample)
    if p >= 1.0:
        return 1
    return int(math.ceil(math.log(1.0 - confidence) / math.log1p(-p)))


def sift_scale(window: tuple, object_px: float | None) -> float:
    """The factor (≤ 1) by which SIFT's crop is shrunk: the window's longer side to at most
    ``object_px`` pixels; 1 when ``object_px`` is None or the window is smaller already.

    >>> sift_scale((10, 20, 400, 300), 200.0), sift_scale((0, 0, 150, 90), 200.0), sift_scale((0, 0, 400, 300), None)
    (0.5, 1.0, 1.0)
    """
    side = max(float(window[2]), float(window[3]))
    if object_px is None or side <= object_px:
        return 1.0
    return float(object_px) / side


def typical_object_px(model: ObjectModel, image_width: int) -> float:
    """The object's typical apparent size in a query image ``image_width`` pixels wide: the longer
    side of the geometric mean of the smallest and largest training silhouettes (registered and
    synthetic views, ``model.rfch.size_min``/``size_max``), carried over by the image widths
    (as the window search carries them; :func:`~.window_search.window_shapes`)."""
    train_w = model.training_width or float(image_width)
    (w0, h0), (w1, h1) = model.rfch.size_min, model.rfch.size_max
    return float(max(np.sqrt(w0 * w1), np.sqrt(h0 * h1)) * image_width / train_w)


def shared_features(shared: dict, key, scale: float, steps: int | None, describe) -> Features:
    """Whole-image features for ``scale`` from ``shared`` (passes already described for this
    image, by ``key`` = the image's shape and SIFT parameters, then scale), or ``describe(scale)``
    added to it. A pass described at a scale up to ``2^(1/steps)`` finer serves too: it holds
    at least the detail asked for (SIFT sees the object as large or larger), and another model
    searched in the same image need not pay for a pass of its own; ``steps`` None: the same
    scale only.

    >>> made = []
    >>> d = lambda s: made.append(s) or f"sift@{s}"
    >>> shared = {}
    >>> shared_features(shared, "k", 0.6, 4, d), shared_features(shared, "k", 0.55, 4, d)  # 0.6 is ≤ 0.55·2^¼
    ('sift@0.6', 'sift@0.6')
    >>> shared_features(shared, "k", 0.7, 4, d), shared_features(shared, "k", 0.4, 4, d), made
    ('sift@0.7', 'sift@0.4', [0.6, 0.7, 0.4])
    """
    passes = shared.setdefault(key, {})
    reach = 1.0 if steps is None else 2.0 ** (1.0 / steps)
    fits = [s for s in passes if scale <= s <= scale * reach * (1 + 1e-9)]
    if fits:
        return passes[min(fits)]
    passes[scale] = feats = describe(scale)
    return feats


def _describe_and_pose(img, box, scale: float, index: ModelIndex, model: ObjectModel, camera: PinholeCamera,
                       window: tuple | None, params: LocateParams, timer: dict, grey: np.ndarray,
                       shared: dict | None = None, prefer=None) -> _Search:
    """SIFT of ``img`` (its crop ``box``, or all of it) shrunk by ``scale``, then the pose search.
    ``shared``: features of whole-image passes already described for this image (by SIFT
    parameters and scale), read and filled in (:func:`locate_all`)."""
    t0 = time.perf_counter()
    if shared is None or box is not None:
        feats = index.describe(img, box, scale=scale)
    else:
        feats = shared_features(shared, (img.shape, index.viewset_params), float(scale), params.fallback_scale_steps,
                                lambda s: index.describe(img, None, scale=s))
    timer["match"] += (time.perf_counter() - t0) * 1e3
    return _pose_from(feats, index, model, camera, window, params, timer, grey, prefer)


def _image_box(camera: PinholeCamera, size: tuple[int, int], vertices: np.ndarray, t: np.ndarray, q: np.ndarray):
    """``(x, y, w, h)`` of the mesh's projected vertices at ``(t, q)``, clipped to the image of
    ``size`` (width, height); None when a vertex lies behind the camera or nothing is inside."""
    from .pose import projected_bbox

    box = projected_bbox(camera, vertices, t, q)
    if box is None:
        return None
    x0, y0 = max(box[0], 0.0), max(box[1], 0.0)
    x1, y1 = min(box[0] + box[2], float(size[0])), min(box[1] + box[3], float(size[1]))
    return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1 - x0, y1 - y0)


def check_inputs(camera, model) -> None:
    """TypeError unless ``camera`` is a PinholeCamera and ``model`` an ObjectModel (a camera's dict
    or path, a model's name: AttributeError deep inside before), saying where each comes from."""
    if not isinstance(camera, PinholeCamera):
        raise TypeError(f"camera: a PinholeCamera (quatrack.viewsets.camera.load_camera reads a camera file), "
                        f"got {type(camera).__name__}")
    if not isinstance(model, ObjectModel):
        raise TypeError(f"model: an ObjectModel (quatrack.viewsets.store.load_model(store, name) loads one), "
                        f"got {type(model).__name__}")


def locate(
    image: np.ndarray, camera: PinholeCamera, model: ObjectModel, params: LocateParams = LocateParams(),
    index: ModelIndex | None = None, shared: dict | None = None, prefer=None,
) -> Located:
    """Find ``model`` in ``image`` (BGR as OpenCV reads it, grey or BGRA; ``uint8``, full-range
    ``uint16`` or float 0..1: :func:`~quatrack.recognition.images.to_bgr8`) seen by ``camera``; never raises for
    an image without the object (``found`` is False), raises ImageError for an unusable image
    (and TypeError for a camera or model of the wrong type: :func:`check_inputs`).

    ``index``: the model's matching index (:func:`~quatrack.recognition.match.index_for`, built
    once per loaded model and cached); pass it when calling in a loop. ``shared``: a dict kept
    across the calls for *one* image (several models, :func:`locate_all`): the whole-image
    fallback reuses a pass described for another model at the same or a slightly finer scale
    (:func:`shared_features`). ``prefer``: indices of viewsets where the caller expects the
    object (the tracker: its latest keyframes' views, as an object lost in a video mostly comes
    back near where it went); after the best-voted views, ``params.prefer_tried`` of them are
    tried too, each re-matched alone, the most matched first: texture repeated on other faces
    can outvote the right view by 3 to 1 (a zoo cube seen 30° beyond its last keyframe).

    Examples
    --------
    Train the bundled cookie box from its registered photo (no synthetic views, to keep this
    quick) into a model store, load it back as a service would, and find the box in the first
    frame of its video:

    >>> import shutil, tempfile
    >>> import cv2
    >>> from quatrack.examples import example_dir
    >>> from quatrack.viewsets.camera import load_camera
    >>> from quatrack.viewsets.spec import load_spec
    >>> from quatrack.viewsets.store import load_model, save_model
    >>> from quatrack.viewsets.train import TrainParams, train_object
    >>> ex = example_dir()
    >>> store = tempfile.mkdtemp()
    >>> path = save_model(store, train_object(load_spec(ex / "object.json"), TrainParams(novel=None)))
    >>> model = load_model(store, "cookie-box")
    >>> camera = load_camera(ex / "camera.json")
    >>> ok, frame = cv2.VideoCapture(str(ex / "box.mp4")).read()
    >>> r = locate(frame, camera, model)
    >>> r.found, r.searched  # found in the RFCH window, not by searching the whole image
    (True, 'window')

    The pose maps the object's frame to the camera's, in the mesh's units (cm here): the box
    is about 70 cm in front of the camera. Each stage's time is reported in milliseconds:

    >>> bool(60 < np.linalg.norm(r.pose.t) < 80), r.pose.q_wxyz.shape, r.covariance.shape
    (True, (4,), (6, 6))
    >>> sorted(r.time_ms)
    ['localise', 'match', 'pnp', 'total']

    An image without the object is an answer too, with the reason:

    >>> empty = locate(np.full((480, 640, 3), 128, np.uint8), camera, model)
    >>> empty.found, empty.searched, empty.reason
    (False, 'image', 'no viewset has enough matches')
    >>> shutil.rmtree(store)
    """
    t_start = time.perf_counter()
    check_inputs(camera, model)
    if not isinstance(params, LocateParams):  # (a dict: AttributeError 'max_pixels' deep inside)
        raise TypeError(f"params: a LocateParams (quatrack.recognition.locate), got {type(params).__name__}")
    prep = prepare_image(image, camera, params.max_pixels)
    img, cam = prep.image, prep.camera
    index = index or index_for(model)
    model = model.at_run_time()  # (a scan's mesh: its geometry checked on its decimation)
    timer: dict[str, float] = {"localise": 0.0, "match": 0.0, "pnp": 0.0}
    h, w = img.shape[:2]

    win: Window | None = None
    if params.use_window:
        t0 = time.perf_counter()
        win = search_window(img, cam, model, params.window)
        timer["localise"] = (time.perf_counter() - t0) * 1e3

    grey = stretched(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), EVIDENCE_MIN_P99)
    res, searched = _Search(reason="no object-like window"), "window"
    scale = 1.0
    if win is not None and win.found:
        box = _crop_box(win.bbox, params.margin, w, h)
        scale = sift_scale(win.bbox, params.sift_object_px)
        res = _describe_and_pose(img, box, scale, index, model, cam, win.bbox, params, timer, grey, prefer=prefer)
        if res.est is None and scale < 1.0 and params.retry_full_resolution:
            first = res
            res = _describe_and_pose(img, box, 1.0, index, model, cam, win.bbox, params, timer, grey, prefer=prefer)
            if res.verification is None:
                res.verification = first.verification
    # the whole image is searched when there is no window search, or when the window gave no
    # verified pose — also when it was nothing like the object (χ² beyond the gate): that
    # verdict is no evidence of absence where the query differs from the photos (a grey camera
    # and a colour-trained model: 10 of 31 frames; a camera with 4× the pixels; an object seen
    # 26° from its only photo, χ² 1.32), and it ended the search on few images without the object
    # anyway (the windows of 340 of 360 room and zoo backgrounds pass the gate). It is described
    # at the window's scale: the window's size is the best guess of the object's, even when its
    # place was wrong; a window beyond the gate, at the object's typical size; with no window
    # search, at full resolution
    if res.est is None and (not params.use_window or params.whole_image_fallback):
        searched = "image"
        if params.use_window and params.fallback_object_px is not None:
            scale = min(scale, sift_scale((0, 0, typical_object_px(model, w), 0), params.fallback_object_px))
        first = res
        whole = params
        if params.fallback_min_inliers is not None and params.fallback_min_inliers > params.pose.min_inliers:
            whole = replace(params, pose=replace(params.pose, min_inliers=params.fallback_min_inliers))
        res = _describe_and_pose(img, None, scale, index, model, cam, None, whole, timer, grey, shared, prefer)
        if res.verification is None:
            res.verification = first.verification
    est = res.est
    ver = None if res.verification is None else res.verification.to_json()

    timer["total"] = (time.perf_counter() - t_start) * 1e3
    inv = 1.0 / prep.scale
    window = None if win is None else tuple(float((v + 0.5) * inv - 0.5) if i < 2 else float(v * inv)
                                            for i, v in enumerate(win.bbox))
    if est is None:
        return Located(False, window, None if win is None else win.chi2, res.viewset, res.matches, 0, None,
                       time_ms=timer, reason=res.reason, searched=searched, verification=ver, object=model.name,
                       window=window)
    # found: the object's projected box, in the image — the contract's bbox — wherever the pose
    # came from (the window's box is on a 16-px grid, and beside the object when the pose came
    # from the whole image after the window's search failed). chi2 stays the window's.
    h0, w0 = np.shape(image)[:2]
    bbox = _image_box(camera, (w0, h0), model.mesh.vertices, np.array(est.t), np.array(est.q))
    return Located(
        True, bbox, None if win is None else win.chi2, res.viewset, res.matches, len(est.inliers), est.rms_px * inv,
        np.array(est.t), np.array(est.q), est.covariance, time_ms=timer, searched=searched, verification=ver,
        object=model.name, window=window,
    )


def locate_all(
    image: np.ndarray, camera: PinholeCamera, models: list[ObjectModel], params: LocateParams = LocateParams(),
) -> list[Located]:
    """Search every model in the image (Kragic & Kyrki's recognition among several objects):
    one :class:`Located` per model, in the models' order. Each object is found or not on its own
    evidence; when two found objects claim the same place (projected boxes overlapping by more
    than half), only the more confident one is reported found: one answer per place. The other
    is not dropped silently: it is listed in the found one's ``rivals`` (name, confidence, pose;
    every found answer has the list, empty without rivals), and its own ``reason`` names the
    winner. Why: the same print at another size (a box and its ×1.5 copy) looks the same to one
    camera at another distance, and the confidences of the two can differ by a few thousandths;
    the caller may know which size is there. The models share the whole-image
    SIFT passes of their fallbacks (:func:`shared_features`); a single model is searched exactly
    as :func:`locate` does."""
    if isinstance(models, ObjectModel):  # (was "object of type 'ObjectModel' has no len()")
        raise TypeError("models: a list of ObjectModels (locate() searches one)")
    models = list(models)
    for m in models:  # (a name among them was AttributeError 'viewsets' from index_for, before locate's check)
        check_inputs(camera, m)
    shared: dict | None = {} if len(models) > 1 else None
    results = [locate(image, camera, m, params, index_for(m), shared) for m in models]
    found = sorted((r for r in results if r.found), key=lambda r: -r.confidence)
    kept: list[tuple] = []  # (box, the found answer there)
    from .pose import iou, projected_bbox

    for r in found:
        r.rivals = []
        model = next(m for m in models if m.name == r.object)
        box = projected_bbox(camera, model.mesh.vertices, r.t, r.q_wxyz)
        overlap = [] if box is None else [(iou(box, b), w) for b, w in kept]
        best, winner = max(overlap, key=lambda o: o[0], default=(0.0, None))
        if best > 0.5:
            c = r.confidence  # (0 once not found)
            r.found = False
            r.reason = (f"{winner.object!r} was found at the same place with more confidence "
                        f"({winner.confidence:.3f} against {c:.3f})")
            winner.rivals.append({"object": r.object, "confidence": round(c, 4),
                                  "pose": {"t": [float(v) for v in r.t], "q_wxyz": [float(v) for v in r.q_wxyz]}})
            r.rivals = None
            continue
        if box is not None:
            kept.append((box, r))
    return results


def not_found(results: list[Located]) -> dict[str, str]:
    """``{object: reason}`` of :func:`locate_all`'s results that were not found (an object found
    but reported in a more confident rival's place among them: its reason names the rival)."""
    return {r.object: r.reason or "not found" for r in results if not r.found}

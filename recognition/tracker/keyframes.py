"""Keyframes: what the object looked like earlier in this run, to find it again after a loss.

Recognition (:func:`..locate.locate`) knows the object only from its trained views (and the
views learned into the stored model). A model trained from one photo cannot find it from a
side that photo does not show; so once the tracker had followed the object round to such a
side and then lost it (the object left the frame, a hand covered it), nothing could start the
track again although the object stood plainly in view (issue 12's report: the last 29 % of a
video lost). The tracker remembers instead: while it tracks with a confident pose, it keeps
*keyframes*, the frame's SIFT keypoints on the visible faces lifted onto the mesh at the pose
(the lifting of a learned view, :func:`quatrack.viewsets.learn.learned_viewset`):

- one per viewing direction: a frame whose direction (object frame, roll ignored, as SIFT is
  blind to it) lies at least ``keyframe_min_angle_deg`` from every keyframe's is added; one
  nearer than that *renews* the nearest keyframe when that is ``keyframe_renew_s`` old (the
  light may have changed since);
- at most ``keyframes_max``: the oldest goes.

After a loss the tracker's recognition searches the model's views and the keyframes together
(:meth:`Keyframes.refind_model`: one FLANN index over all of them), with recognition's own
window search, pose search and verification: one search per frame, whichever view is nearest.

SIFT matches a view only so far round (~20–30° for a textured face). An object that left the
frame comes back turned, and a camera moving round it soon sees its sides from further than that
from every keyframe: on the zoo walks the sides were 25–40° from the nearest keyframe after the
slide out of the frame, and nothing re-found them. So each keyframe keeps its frame's crop of the
object, and after a loss it gains *synthetic views* (:meth:`Keyframes.synthesise`): the crop
re-rendered on the mesh at the keyframe's pose turned by ``±a`` about the camera's x and y axes
(:func:`quatrack.viewsets.novel.turned_about_view`; the planar faces warped by the homographies
they induce, as training's novel views are), described and lifted like any view. They are made
lazily, a few keyframes per lost frame (the most recent first), since a run that is never lost
never needs them; re-anchoring while tracking does not search them
(:meth:`Keyframes.search_model`). Near-identical views split the shared index's votes, so the
tracker's recognition re-matches each tried view alone (``LocateParams.rematch_views``), and it
also tries the views of the latest keyframes (``locate(prefer=…)``): an object lost in a video
mostly comes back near where it went, and texture repeated on other faces can outvote it there.

A track re-found on keyframes is *second-hand* (``Tracker._second_hand``): its points were lifted at
a pose that carries the keyframe's error, so it keeps no keyframe or learned view of its own while
no trained point anchors its frame (``TrackerParams.capture_second_hand``): that passed the error
on, and it grew. After a loss it is re-acquired near its own last pose only as it started: judged
on the model's edges alone (session 44; ``Tracker._reacquire``).

Keyframes live in memory for the run only; the stored model changes only through learned views
(``TrackerParams.learn``), whose rules are stricter because they outlive the run.
"""

from __future__ import annotations

from concurrent.futures import Executor, Future
from dataclasses import dataclass, replace

import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import Mesh
from quatrack.viewsets.novel import synthetic_viewset, turned_about_view
from quatrack.viewsets.render import footprint
from quatrack.viewsets.store import ObjectModel
from quatrack.viewsets.viewset import Viewset, ViewsetParams

from quatrack.viewsets.texture import TextureReference

from ..appearance import RenderedAt, TextureAgreement, TextureRefit, texture_agreement, texture_refit
from ..match import ModelIndex


@dataclass(frozen=True)
class Keyframe:
    """One remembered view: when (``time_s``), from where (``direction``: unit vector, object
    frame, from the centre towards the camera) and what it saw (``viewset``, lifted points)."""

    time_s: float
    direction: np.ndarray
    viewset: Viewset
    # the frame's crop of the object and the camera of that crop (PinholeCamera.cropped), to
    # render synthetic views from; None: none kept
    crop: np.ndarray | None = None
    crop_camera: PinholeCamera | None = None
    synthetic: tuple[Viewset, ...] | None = None  # made by Keyframes.synthesise (None: not yet)


@dataclass
class Capture:
    """A view the tracker is keeping (``Tracker._capture``): the keyframe slot it goes to (None:
    not a keyframe), whether it is also learned, when and at which pose it was seen, the
    frame's crop of the object (for :meth:`Keyframes.synthesise`; keyframes only) and, while
    its lifting runs on the executor, the future that returns its :class:`Viewset`."""

    slot: int | None
    learn: bool
    time_s: float
    pose: Pose
    crop: np.ndarray | None = None
    crop_camera: PinholeCamera | None = None
    future: Future | None = None
    relayed: bool = False  # too few points of the model's own views anchored its frame (Viewset.relayed)


def object_crop(image: np.ndarray, camera: PinholeCamera, mesh: Mesh, pose: Pose,
                margin_px: int = 16) -> tuple[np.ndarray | None, PinholeCamera | None]:
    """A copy of the object's box in ``image`` (its mesh's :func:`~quatrack.viewsets.render.footprint`
    at ``pose``, plus ``margin_px``) and the camera of that crop; ``(None, None)`` if not in view."""
    box = footprint(mesh, camera, pose, margin_px)
    if box is None:
        return None, None
    x0, y0, x1, y1 = box
    return image[y0:y1, x0:x1].copy(), camera.cropped(x0, y0, x1, y1)


class Keyframes:
    """The bounded set of a run's keyframes (see the module) and the index to search them."""

    def __init__(self, centre: np.ndarray, max_keyframes: int, min_angle_deg: float, renew_s: float) -> None:
        self.centre = np.asarray(centre, float)
        self.max = int(max_keyframes)
        self.min_angle_deg = float(min_angle_deg)
        self.renew_s = float(renew_s)
        self.items: list[Keyframe] = []
        self._search: tuple[ObjectModel, ModelIndex, ObjectModel] | None = None  # (base, index, model)
        self._refind: tuple | None = None  # the same with synthetic views, + the latest keyframes' views
        self._job: tuple[Future, list[Keyframe]] | None = None  # synthetic views being made on an executor
        self._references: dict[int, tuple[Keyframe, TextureReference]] = {}  # each crop with its z-buffer

    def __len__(self) -> int:
        return len(self.items)

    def slot(self, pose: Pose, time_s: float) -> int | None:
        """Where a keyframe at ``pose`` would go: ``len(self)`` (a new direction: appended), the
        index of the nearest keyframe (to renew it, when ``renew_s`` old), or None (not wanted).

        >>> kf = Keyframes(np.zeros(3), 4, 15.0, 3.0)
        >>> front = Pose.from_rvec([0.0, 0.0, 0.0], [0.0, 0.0, 5.0])
        >>> kf.slot(front, 0.0)
        0
        >>> kf.add(Keyframe(0.0, front.viewing_direction(kf.centre), None), 0)
        >>> kf.slot(front, 1.0) is None, kf.slot(front, 3.5)  # too soon; then renewed
        (True, 0)
        >>> kf.slot(Pose.from_rvec([0.0, 0.5, 0.0], [0.0, 0.0, 5.0]), 1.0)  # 29° round: a new one
        1
        """
        if self.max <= 0:
            return None
        if not self.items:
            return 0
        d = pose.viewing_direction(self.centre)
        dirs = np.array([k.direction for k in self.items])
        ang = np.degrees(np.arccos(np.clip(dirs @ d, -1.0, 1.0)))
        j = int(np.argmin(ang))
        if ang[j] >= self.min_angle_deg:
            return len(self.items)
        if time_s - self.items[j].time_s >= self.renew_s:
            return j
        return None

    def add(self, keyframe: Keyframe, slot: int) -> None:
        """Put ``keyframe`` at ``slot`` (from :meth:`slot`); beyond ``max`` the oldest goes."""
        if slot < len(self.items):
            self.items[slot] = keyframe
        else:
            self.items.append(keyframe)
            if len(self.items) > self.max:
                self.items.pop(int(np.argmin([k.time_s for k in self.items])))
        self._search = self._refind = None

    def search_model(self, base: ObjectModel) -> tuple[ObjectModel, ModelIndex]:
        """``base`` with the keyframes added to its viewsets (labelled ``keyframeK``), and its
        matching index (built once per change of the keyframes or of ``base``)."""
        cached = self._search
        if cached is None or cached[0] is not base:
            model = replace(base, viewsets=list(base.viewsets) + self._views(synthetic=False)[0])
            cached = self._search = (base, ModelIndex(model), model)
        return cached[2], cached[1]

    def _views(self, synthetic: bool) -> tuple[list[Viewset], list[int]]:
        """The keyframes' views labelled ``keyframeK`` (and, with ``synthetic``, their synthetic
        views, ``keyframeK-camy+20`` …), and for each view the index of its keyframe."""
        views, owner = [], []
        for i, k in enumerate(self.items):
            extra = (k.synthetic or ()) if synthetic else ()
            views.append(replace(k.viewset, label=f"keyframe{i + 1}"))
            views += [replace(v, label=f"keyframe{i + 1}-{v.label}") for v in extra]
            owner += [i] * (1 + len(extra))
        return views, owner

    def refind_model(self, base: ObjectModel, recent: int = 2) -> tuple[ObjectModel, ModelIndex, np.ndarray]:
        """:meth:`search_model` plus the keyframes' synthetic views made so far (labelled
        ``keyframeK-camy+20`` …): what recognition searches after a loss; and the indices (in
        that model's viewsets) of the views of the ``recent`` latest keyframes, for
        ``locate(prefer=…)``: an object lost in a video mostly comes back near where it went."""
        cached = self._refind
        if cached is None or cached[0] is not base:
            views, owner = self._views(synthetic=True)
            model = replace(base, viewsets=list(base.viewsets) + views)
            latest = np.argsort([-k.time_s for k in self.items], kind="stable")[:recent]
            prefer = len(base.viewsets) + np.flatnonzero(np.isin(owner, latest))
            cached = self._refind = (base, ModelIndex(model), model, prefer)
        return cached[2], cached[1], cached[3]

    def texture_agreement(self, image: np.ndarray, camera: PinholeCamera, pose: Pose, mesh: Mesh) -> TextureAgreement:
        """How well ``image`` agrees at ``pose`` with the object as the keyframes' crops show it
        (:func:`..appearance.texture_agreement`); each crop's z-buffer is rendered once."""
        return texture_agreement(image, camera, pose, mesh, mesh.plane_ids, self._texture_references(mesh))

    def texture_refit(self, image: np.ndarray, camera: PinholeCamera, pose: Pose, mesh: Mesh,
                      rendered: RenderedAt | None = None) -> TextureRefit:
        """Where the keyframes' crops, rendered at ``pose`` and followed into ``image``, put the
        object (:func:`..appearance.texture_refit`; ``rendered``: :meth:`texture_agreement`'s
        renders at that pose, reused)."""
        return texture_refit(image, camera, pose, mesh, mesh.plane_ids, self._texture_references(mesh),
                             rendered=rendered)

    def _texture_references(self, mesh: Mesh) -> list[TextureReference]:
        """The keyframes' crops as texture references, each z-buffer rendered once and kept."""
        refs, kept = [], {}
        for k in self.items:
            if k.crop is None:
                continue
            cached = self._references.get(id(k))
            if cached is None or cached[0] is not k:
                cached = (k, TextureReference(k.crop, k.crop_camera, k.viewset.pose).rendered(mesh))
            kept[id(k)] = cached
            refs.append(cached[1])
        self._references = kept
        return refs

    def synthesise(self, mesh: Mesh, params: ViewsetParams, angles_deg: tuple[float, ...], budget: int,
                   min_cos: float = 0.3, executor: Executor | None = None) -> int:
        """Make the synthetic views (see the module) of at most ``budget`` keyframes that have a
        crop and none yet, the most recent first; returns how many keyframes got them (in this
        call). With an ``executor`` (live streams) they are made there, one batch at a time, and
        a later call attaches them: ~15 ms per view would otherwise stall the lost frame's step
        (2 keyframes × 8 views ≈ 0.25 s)."""
        done = 0
        job = self._job
        if job is not None and job[0].done():
            self._job = None
            done = self._attach(job[1], job[0].result())
        if self._job is not None:
            return done
        todo = sorted((i for i, k in enumerate(self.items) if k.synthetic is None and k.crop is not None),
                      key=lambda i: -self.items[i].time_s)[:max(int(budget), 0)]
        if not todo:
            return done
        keys = [self.items[i] for i in todo]
        work = (synthetic_views, keys, mesh, mesh.plane_ids, self.centre, params, tuple(angles_deg), min_cos)
        if executor is not None:
            self._job = (executor.submit(*work), keys)
            return done
        return done + self._attach(keys, work[0](*work[1:]))

    def _attach(self, keys: list[Keyframe], views: list[tuple[Viewset, ...]]) -> int:
        """Give each keyframe of ``keys`` (still kept: not renewed or dropped meanwhile) its views."""
        n = 0
        for key, made in zip(keys, views):
            for i, k in enumerate(self.items):
                if k is key:
                    self.items[i] = replace(k, synthetic=made)
                    n += 1
        self._refind = None
        return n


def synthetic_views(keyframes: list[Keyframe], mesh: Mesh, groups: np.ndarray, centre: np.ndarray,
                    params: ViewsetParams, angles_deg: tuple[float, ...], min_cos: float = 0.3) -> list[tuple[Viewset, ...]]:
    """Each keyframe's synthetic views (:func:`~quatrack.viewsets.novel.synthetic_viewset` at its
    pose turned by :func:`~quatrack.viewsets.novel.turned_about_view`, a face textured where the
    crop sees it at ``|cos| ≥ min_cos``); a view with fewer than 12 lifted keypoints is not kept
    (12: recognition's minimum inliers). Pure: runs on any thread."""
    out = []
    for k in keyframes:
        pose, camera = k.viewset.pose, k.viewset.camera
        made = []
        for label, turned in turned_about_view(pose, centre, angles_deg):
            vs = synthetic_viewset(label, mesh, groups, k.crop, k.crop_camera, pose, camera, turned, params, min_cos)
            if vs is not None and len(vs) >= 12:
                made.append(vs)
        out.append(tuple(made))
    return out

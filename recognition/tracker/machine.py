"""The tracker: a small state machine over measurement sources, on Ude's quaternion filter.

States and transitions (Kragic & Kyrki's Fig. 1 loop):

- **init** (no filter state): the user's pose (:meth:`Tracker.init_pose`), re-acquisition near
  the last good pose within ``reacquire_s`` of a loss (:mod:`.reacquire`: KLT from that frame,
  after following the object's image; the model's edges must confirm it) or recognition
  (:func:`recognition.locate.locate`) starts the filter with unknown velocities; SIFT anchors
  model points near that pose and one adjustment checks them → *tracking*, or stays *init*
  (the step answers ``lost``) when they do not agree. Recognition searches this run's keyframes
  (:mod:`.keyframes`) with the model's views: a side the tracker followed earlier but no trained
  view shows is found again; with no trained point near such a pose, the track starts on
  corners born on the mesh once the edges confirm it.
- **tracking**: each frame is *predict → measure → adjust*: the motion model gives the prior;
  every source measures the frame — the trained points and the points born on the mesh by KLT
  from the previous frame, starting from their projections at the prediction (:mod:`.sources`,
  :mod:`.mesh_points`), the model's sharp edges by their gradients (:mod:`.edges`), the
  object's outline by its colours (:mod:`.contour`); gated by ``rᵀ(J P Jᵀ + C)⁻¹r < χ²``; one
  adjustment (:meth:`PoseFilter.update`, eq. 24, Huber weights) takes every block; measurements
  still off after it are outliers, removed and the adjustment redone. Re-anchoring
  (:mod:`.anchor`) refreshes the trained points every ``refresh_every`` frames or when they
  thin out, in the step or on the caller's executor.
- **keyframes** (not a state: a side job of *tracking*): when the pose is confident, the
  frame's SIFT keypoints on the visible faces, lifted onto the mesh, are remembered for the run,
  one per viewing direction (:mod:`.keyframes`), for *init* after a loss.
- **learning** (``params.learn``, not a state: a side job of *tracking*): when the pose is
  confident, the frame's SIFT keypoints on the visible faces, lifted onto the mesh at the pose,
  become a *learned viewset* if they see the object from a new direction
  (:mod:`quatrack.viewsets.learn`); the tracker's model then holds it, so re-anchoring and
  re-initialisation (recognition) search the trained and the learned views
  (:meth:`Tracker.learned_viewsets` gives them to the caller, which may store them).
- **in doubt** (not a state: a pause of *tracking*): a pose the model's edges refit too far (the
  audit every ``audit_every`` frames — ``audit_every_anchored`` while trained points anchor the
  track —, or the strict test of a track on probation) is withheld —
  the step answers ``lost`` — while the track goes on, tested strictly every frame, for up to
  ``doubt_frames`` frames; the first the edges confirm (by the stricter ``doubt_confirm_shift``)
  is reported again (:meth:`Tracker._doubt`).
- **lost**: too few measurements agree, residuals too large, the pose implausible
  (:func:`recognition.pose.plausible`: behind the camera, too little of it in the image), or
  repeated refreshes find no texture → the state is dropped and the next frame is *init* again.
"""

from __future__ import annotations

import copy
import threading
import time
from concurrent.futures import Executor
from dataclasses import replace

import cv2
import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.adjust import SingularProblemError, adjust
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.filter import PoseFilter
from quatrack.tracking.measurements import project_model_points
from quatrack.tracking.motion import make_motion_model
from quatrack.tracking.pose import Pose
from quatrack.tracking.state import FilterState
from quatrack.tracking.systematic import carried_covariance, image_floor, systematic_floor
from quatrack.viewsets.camera import check_lens
from quatrack.viewsets.errors import SpecError
from quatrack.viewsets.learn import is_new_direction, learned_viewset, view_angles_deg, with_learned
from quatrack.viewsets.rfch import texture_zoom
from quatrack.viewsets.store import ObjectModel
from quatrack.viewsets.viewset import Viewset, params_from_manifest

from ..images import MIN_SIDE, ImageError, size_mismatch, to_bgr8, too_small
from ..klt import Frame, make_frame
from ..locate import check_inputs, locate
from ..match import ModelIndex, index_for
from ..evidence import pose_shift, silhouette_inside
from ..pose import PoseParams, plausible
from ..visibility import merge_points
from .anchor import Anchor, AnchorJob
from .params import INITIAL_VELOCITY_SIGMA, TrackerParams, TrackStep
from .points import PointBlock, Tracks, disagreement_factor, mahalanobis2, score_statistic
from .contour import Contour
from .edge_tests import edge_refit, edges_agree_at, settle_on_edges
from .edges import ModelEdges
from .keyframes import Capture, Keyframe, Keyframes, object_crop
from .mesh_points import MeshPoints, birth_mask, confident
from .reacquire import LastSeen, hull_mask, object_shift, shifted_pose
from .sources import FrameContext, MeasurementSource, TrainedPoints, follow_together

__all__ = ["Tracker"]


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def _seconds(time_s) -> float:
    """A frame's time: a finite number of seconds (a string or None raised float()'s own error)."""
    try:
        t = float(time_s)
    except (TypeError, ValueError):
        raise ValueError(f"time_s must be a number of seconds, got {time_s!r}"[:120]) from None
    if not np.isfinite(t):
        raise ValueError("time_s must be finite")
    return t


def _check_pose(t, q) -> Pose:
    """The user's pose; Pose's own errors say what is wrong (a shape, not finite, a zero quaternion)."""
    if q is None:
        raise ValueError("give t and q_wxyz, or a Pose")
    return Pose(q, t)


class Tracker:
    """Tracks one object in the frames of one camera; not thread-safe (one per video stream).

    ``executor``: where re-anchoring runs in the background when ``params.pipelined_refresh``
    (the caller owns it: the service's pool; without one it runs in the step)."""

    def __init__(self, model: ObjectModel, camera: PinholeCamera, params: TrackerParams = TrackerParams(),
                 index: ModelIndex | None = None, executor: Executor | None = None) -> None:
        check_inputs(camera, model)  # (a camera's dict, a model's name: a TypeError that says so)
        if not isinstance(params, TrackerParams):  # (a dict: AttributeError 'motion_model' deep inside)
            raise TypeError(f"params: a TrackerParams (quatrack.recognition.video), got {type(params).__name__}")
        model = model.at_run_time()  # (a scan's mesh: tracked on its decimation, Mesh.run_time)
        self.model = model
        self.camera = camera
        self.params = params
        self.index = index
        self.executor = executor
        self.diameter = float(model.mesh.extent)
        # the object's points for the image floor (_pose_step): its vertices, at most 256 of them
        V = model.mesh.vertices
        self._floor_points = V[np.linspace(0, len(V) - 1, min(len(V), 256)).astype(int)]
        self.motion = make_motion_model(params.motion_model, **params.motion_noise_params(self.diameter))
        self.filter = PoseFilter(self.motion, params.adjust)
        pts = np.concatenate([vs.points3d for vs in model.viewsets]) if model.viewsets else np.zeros((0, 3))
        self.points = merge_points(pts, params.merge_tol * self.diameter)
        self.trained = TrainedPoints(model.mesh, params)
        self.mesh_points = MeshPoints(model.mesh, params)
        # the trained points always exist (re-anchoring and initialisation fill them); without
        # "trained" in params.sources they are not measured after the first frame
        self.edges = ModelEdges(model.mesh, params)
        self.contour = Contour(model.mesh, params)
        self.sources: list[MeasurementSource] = [s for s in (self.trained, self.mesh_points, self.edges, self.contour)
                                                 if s.name in params.sources]
        # the outline's sources in use: they carry the pose, but only texture says it is this object's
        self._shape_sources = tuple(s for s in (self.edges, self.contour) if s in self.sources)
        self._anchor: Anchor | None = None
        # while tracking, the measurements judge: the object may lie mostly outside the image
        self._plausibility = replace(PoseParams(), min_visible_fraction=params.min_inside)
        self.learned: list[Viewset] = []  # learned in this run (also in self.model once learned)
        # the object points of the model's own views (as given: trained, or learned first-hand in
        # earlier runs: built when first asked, _anchoring, which only learning asks; ~4 ms for a
        # model of 20 views), and of the relayed views (Viewset.relayed: learned at a frame too few
        # own points anchored; TrackerParams.relayed_views_anchor), which inherit a track's drift
        self._own_points: set[tuple] | None = None
        self._given_views = tuple(model.viewsets)  # (self.model gains this run's learned views)
        relayed = [] if params.relayed_views_anchor else [vs for vs in model.viewsets if vs.relayed]
        self._relayed: set[tuple] = {tuple(x) for vs in relayed for x in vs.points3d.tolist()}
        self._relayed_views: set[str] = {vs.label for vs in relayed}  # (a re-finding on one is second-hand)
        self._first_hand = False  # the latest frame's points of the model's own views anchored it
        self._learn_wait = 0
        # what the object looked like earlier in this run, to find it again after a loss; kept
        # across losses and resets (same object, same camera; reset(new_run=True) starts them afresh)
        self._new_run()
        self._pending: tuple[Pose, float | None] | None = None
        # (reset: _relocated_at, the frame time of the latest recognition while lost
        # (TrackerParams.relocate_interval_s), None once a track holds: the first frame of the
        # next loss searches at once; _last_time, the latest frame's time)
        self.reset()
        self._stepping = threading.Lock()  # held by step(): a second thread's call is refused
        if params.pipelined_refresh and params.refresh_every and executor is not None:
            executor.submit(lambda: self._index()._matcher())  # warm the anchor thread's index

    # -- public -------------------------------------------------------------------------------
    def _new_run(self) -> None:
        """What a run remembers beyond its state (its keyframes, frame count), as at its start."""
        p = self.params
        self.keyframes = Keyframes(self.model.mesh.centre, p.keyframes_max, p.keyframe_min_angle_deg,
                                   p.keyframe_renew_s)
        self._keyframe_wait = 0
        self._frame = -1
        # the track was started on this run's keyframes (re-found after a loss), not on the model's
        # own views nor the user's pose: it keeps no view (TrackerParams.capture_second_hand)
        self._second_hand = False
        # the object points of the latest anchors taken from the keyframes' texture
        # (_texture_audit; TrackerParams.texture_anchors): measured, they do not anchor a frame
        self._keyframe_anchors: set[tuple] = set()

    def reset(self, new_run: bool = False) -> None:
        """Forget the state and the last pose: the next frame re-initialises by recognition (at
        once: the ``relocate_interval_s`` clock restarts), and its time may start again (a new
        stream: until then frame times must not go back, lost or not). The run's keyframes (how
        the object looked earlier, to re-find it after a loss) and its frame count are kept — the
        same object before the same camera — unless ``new_run``: another scene or camera, whose
        first frame is then frame 0 and re-found on the model's views alone, as a new Tracker's
        (the views learned so far, :meth:`learned_viewsets`, are kept either way)."""
        if new_run:
            self._new_run()
        self._relocated_at: float | None = None
        self._last_time: float | None = None
        self.filter.state = None
        self.filter.prior = None
        for s in (self.trained, self.mesh_points, self.edges, self.contour):  # tracks, what each learned
            s.reset()
        self._prev: Frame | None = None
        self._since_refresh = 0
        self._failed_refreshes = 0
        # a second-hand track's birth: (R, covariance) of the pose it was re-found at, whose error
        # it carries while no trained point is in view (_pose_step); None for a first-hand track
        self._birth: tuple[np.ndarray, np.ndarray] | None = None
        self._anchored = False  # the latest frame's trained points were enough to anchor it
        self._pending = None
        self._anchor_job: AnchorJob | None = None
        self._full_retry = False  # the latest background re-anchoring found too little shrunk: look at full size
        self._tracked = 0  # frames tracked since the last (re-)initialisation
        self._probation = 0  # frames left in which the edges must confirm every pose
        self._doubted = 0  # consecutive frames whose pose the edges doubted (withheld; _doubt)
        self._unconfirmed: str | None = None  # a start withheld until a frame confirms it: its reason
        self._seen: LastSeen | None = None  # the last good frame before the latest loss (_reacquire)
        self._capture_job: Capture | None = None  # a view being lifted on the executor (_capture)

    def learned_viewsets(self) -> list[Viewset]:
        """The viewsets learned so far in this run (``params.learn``), oldest first. A view being
        lifted on the executor is waited for; one still queued there is dropped instead: the
        caller may be running on that executor's only thread (the service stores a session's
        views from its pool), where waiting for it would never end."""
        job, self._capture_job = self._capture_job, None
        if job is not None and not job.future.cancel():
            self._keep_view(job.future.result(), job)
        return list(self.learned)

    def init_pose(self, t, q_wxyz=None, time_s: float | None = None) -> None:
        """Start from a user-given pose (object → camera) at the next frame (or at ``time_s``):
        ``t`` (3 numbers) and ``q_wxyz`` (4), or a :class:`~quatrack.tracking.pose.Pose` as ``t``.
        With ``time_s``, a frame (or :meth:`skip`) before it is refused as a frame going back in
        time is (ValueError); the pose stays pending for the next frame at or after it."""
        pose = t if isinstance(t, Pose) and q_wxyz is None else _check_pose(t, q_wxyz)
        if time_s is not None:
            time_s = _seconds(time_s)
        self.reset()
        self._pending = (pose, time_s)

    def skip(self, time_s: float, reason: str) -> TrackStep:
        """A frame taken at ``time_s`` that could not be read (an image sequence's unreadable
        file): counted, so the next frame keeps its own number, and answered ``lost`` with
        ``reason``. The track is kept: the next frame predicts across the gap, as after a
        dropped frame."""
        time_s = _seconds(time_s)
        self._check_clock(time_s)  # (as step: a skipped frame went back in time unnoticed)
        self._frame += 1
        self._last_time = time_s
        return TrackStep(self._frame, time_s, "lost", reason=reason)

    def _check_clock(self, time_s: float) -> None:
        """Refuse a frame time before the latest one the tracker holds: the track's, the latest
        frame's while lost (a clock gone back), or the time a pose was given at
        (``init_pose(..., time_s)``: a frame before it was started from the pose all the same,
        as if taken at the pose's time)."""
        last = self.filter.state.t if self.filter.state is not None else self._last_time
        if last is not None and time_s < last:
            raise ValueError(f"time goes backwards ({time_s} s after {last} s)")
        given = self._pending[1] if self._pending is not None else None
        if given is not None and time_s < given:
            raise ValueError(f"time goes backwards ({time_s} s before the pose given at {given} s by init_pose; "
                             f"give it no time_s to start from the next frame)")

    @property
    def tracking(self) -> bool:
        """Whether a track is held (the filter has a state): the next frame is predicted from it."""
        return self.filter.state is not None

    @property
    def phase(self) -> str:
        """The machine's state: ``init`` (the next frame starts a track) or ``tracking``."""
        return "tracking" if self.tracking else "init"

    def step(self, image: np.ndarray, time_s: float) -> TrackStep:
        """Process one frame taken at ``time_s`` (seconds, non-decreasing; a repeated time is a
        second look at the same instant) and answer it (:class:`TrackStep`).

        ``image``: a numpy array (H, W, 3) in OpenCV's **BGR** order, as ``cv2.VideoCapture`` and
        ``cv2.imread`` give it — convert RGB frames (PIL, imageio, ROS ``rgb8``) with
        ``cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)`` or ``rgb[..., ::-1]``: nothing can tell them apart
        and the colours the tracker learns are then swapped; or grey (H, W) or (H, W, 1), or BGRA.
        ``uint8``; ``uint16`` as full-range 16-bit (its top 8 bits: scale a 10- or 12-bit camera's
        values to 16 bits first, ``img << 4`` for 12 bits, else it reads as nearly black);
        ``float32``/``float64`` in 0..1 (up to 1.1, the overshoot clipped), or 0..255 when the
        largest value is 2 or more (refused above 280.5; :mod:`~quatrack.recognition.images`). Any strides (slices,
        views, Fortran order) are fine. The image must be the camera's size (a camera without one
        takes the first frame's). Raises :class:`~quatrack.recognition.images.ImageError` (a
        ValueError) for an image it cannot use, ValueError for a time that is not a finite number
        or goes back (call :meth:`reset` between two streams), and RuntimeError when called while
        another thread is inside ``step`` of the same tracker (one tracker per stream, one call at
        a time)."""
        if not self._stepping.acquire(blocking=False):
            raise RuntimeError("Tracker.step was called while another call of it (another thread) is running: "
                               "a tracker follows one stream, one frame at a time; use one Tracker per thread")
        try:
            return self._step(image, time_s)
        finally:
            self._stepping.release()

    def __getstate__(self):
        # (copy, deepcopy and pickle failed with "cannot pickle '_thread._local' object" from the
        # matching index's per-thread matchers)
        raise TypeError("a Tracker cannot be copied or pickled (it holds per-thread matchers and the "
                        "stream's frames); make another Tracker(model, camera, params) for another stream")

    def _step(self, image: np.ndarray, time_s: float) -> TrackStep:
        t_start = time.perf_counter()
        time_s = _seconds(time_s)
        img = to_bgr8(image)
        h, w = img.shape[:2]
        cam = self.camera
        if cam.width is not None and cam.height is not None and (cam.width, cam.height) != (w, h):
            raise size_mismatch(cam, w, h, "frame")
        if min(h, w) < MIN_SIDE:
            # (as locate's: the frame was refused only when recognition ran — a frame after
            # init_pose, or while tracking, went through KLT and the sources on 1 × N pixels)
            raise ImageError(too_small(w, h))
        if cam.width is None or cam.height is None:
            sized = replace(cam, width=w, height=h)
            try:
                check_lens(sized)  # (a camera sized by its frames: its lens model checked at their size, as locate's)
            except SpecError as exc:
                raise ImageError(str(exc)) from None
            self.camera = cam = sized
        state = self.filter.state
        self._check_clock(time_s)
        self._last_time = time_s
        self._frame += 1
        timings: dict[str, float] = {}
        frame = make_frame(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
        gap = None if state is None else time_s - state.t
        if gap is not None and self.params.max_gap_s is not None and gap > self.params.max_gap_s:
            # (a clock jump, a pause: nothing to predict from; the track is dropped — no
            # re-acquisition near a pose that old — and this frame searched afresh)
            self._lost(time_s, "")
            self._seen = self._relocated_at = None
        else:
            gap = None
        if self.phase == "init":
            step = self._initialise(img, frame, time_s, timings)
            if gap is not None and step.status == "lost":
                step.reason = f"the track was dropped after {gap:.3g} s without a frame (max_gap_s); {step.reason}"
        else:
            seen = LastSeen(self.filter.state, self._prev, self.trained.tracks, copy.copy(self.mesh_points),
                            second_hand=self._second_hand, birth=self._birth, doubted=self._doubted > 0)
            held = self._tracked >= self.params.reacquire_min_run  # (a loss resets the count)
            step = self._track(img, frame, time_s, timings)
            if self._unconfirmed is not None and step.status == "tracking":  # (a start withheld: _initialise)
                step.status, step.reason, self._unconfirmed = "init", self._unconfirmed, None
            if not self.tracking and seen.frame is not None and held and self._determined(seen.state.pose):
                # a track that held: re-acquire near it (reacquire_min_run)
                self._seen = seen
        self._prev = frame if self.tracking else None  # (a withheld pose's frame too: the track goes on)
        if step.status == "tracking":
            self._relocated_at = None
        timings["total"] = _ms(t_start)
        step.timings_ms = timings
        return step

    # -- internals ----------------------------------------------------------------------------
    def _index(self) -> ModelIndex:
        if self.index is None:
            self.index = index_for(self.model)
        return self.index

    def _keyframe_matches(self, feats, pose: Pose):
        """``feats`` matched to the model's views and this run's keyframes
        (:meth:`Keyframes.search_model`), keeping the matches to keyframes seen from within
        ``anchor_keyframe_max_deg`` of ``pose``'s viewing direction: SIFT matches a view only
        so far round (a keyframe 40° away gave consistent wrong matches that dragged a fast
        orbit 2 % off, and the keyframes it kept there were off in turn). None when
        ``params.anchor_keyframes`` is off or there is no keyframe near."""
        p = self.params
        if not (p.anchor_keyframes and len(self.keyframes)):
            return None
        dirs = np.array([k.direction for k in self.keyframes.items])
        d = pose.viewing_direction(self.model.mesh.centre)
        near = np.degrees(np.arccos(np.clip(dirs @ d, -1.0, 1.0))) <= p.anchor_keyframe_max_deg
        if not near.any():
            return None
        _, index = self.keyframes.search_model(self.model)
        m = index.match(feats)
        usable = np.concatenate([np.ones(len(self.model.viewsets), bool), near])
        return m.subset(usable[m.viewset])

    def _anchors(self) -> Anchor:
        if self._anchor is None:
            self._anchor = Anchor(self.model.mesh, self._index(), self.params)
        return self._anchor

    def _lost(self, time_s: float, reason: str, inliers: int = 0) -> TrackStep:
        kept = self._pending, self._seen, self._relocated_at, self._last_time
        self.reset()
        self._pending, self._seen, self._relocated_at, self._last_time = kept
        return TrackStep(self._frame, time_s, "lost", inliers=inliers, reason=reason)

    def _doubt(self, time_s: float, why: str, inliers: int) -> TrackStep:
        """The edges doubt this frame's pose (the audit, or the strict test of a track on
        probation or already in doubt): its pose is withheld — the step answers ``lost`` — but
        the track goes on for up to ``doubt_frames`` frames, each tested strictly, and is reported
        again from the first frame the edges confirm (and tested strictly for ``doubt_frames``
        frames more: on the zoo's wide box in the blur, one confirmation let the next three
        frames through unjudged, 5.2–8.4° off); after that many it is lost. To confirm, the
        refit must move the pose by at most ``doubt_confirm_shift`` (0.25) of the criterion,
        half what a pose never doubted may move: each doubted frame is one more draw of a noisy
        judge, and a wrong track 17 % off was reported again on a draw of 0.42 (zoo flat box,
        session 39), while the refit moved the true poses of those frames by 0.06–0.34.

        Why not lost at once: the edges' refit is a noisy judge where the image is blurred or
        dim, and a right track it ended was mostly lost for good: nothing re-finds the object on
        sides no view shows (zoo walks: tracks 0.8–1.3° from the truth ended by one audit or
        probation test, then 50–130 frames lost). A wrong pose is never reported meanwhile."""
        self._doubted += 1
        if self._doubted > self.params.doubt_frames:
            return self._lost(time_s, why, inliers)
        return TrackStep(self._frame, time_s, "lost", inliers=inliers,
                         reason=f"{why}: the pose is withheld while the track goes on")

    def _disagreement(self, blocks: list[PointBlock], inl: np.ndarray) -> float:
        """This frame's :func:`~.points.disagreement_factor` over every source's inliers at the
        filter's pose (1 with ``disagreement_scale`` off)."""
        if not self.params.disagreement_scale:
            return 1.0
        kept = [b.keep(m) for b, m in zip(blocks, PointBlock.split(blocks, inl))]
        return disagreement_factor(self.camera, kept, self.filter.state)

    def _pose_step(self, time_s: float, status: str, inliers: int, reason: str | None = None,
                   scale: float = 1.0) -> TrackStep:
        """The step that reports the filter's pose, with the filter's covariance (× ``scale``, the
        sources' disagreement: :meth:`_disagreement`) plus the systematic floors
        (:mod:`quatrack.tracking.systematic`: the pose-level one,
        ``params.systematic_pct`` / ``_depth_ratio`` / ``_deg``, and the image one of
        ``params.systematic_px`` shared by the object's points), plus,
        in a second-hand track's frame without trained points in view, the error it carries from
        its birth (:func:`~quatrack.tracking.systematic.carried_covariance` of the re-found pose's
        covariance). There the points born on the mesh were lifted at the track's own poses: they
        measure its motion since the re-finding, not where the object is, and the filter, which
        counts them as absolute, claims the accuracy of the motion (zoo walks: NEES median 6–37
        in those frames, 2–5 in the other frames of the same walks; bench/RESULTS.md, session 27).
        The track is the same."""
        s, p = self.filter.state, self.params
        cov = scale * s.pose_covariance + systematic_floor(s.R, s.p, self.model.mesh.centre, self.diameter,
                                                           p.systematic_pct / 100.0, p.systematic_depth_ratio,
                                                           np.radians(p.systematic_deg))
        if p.systematic_px:
            cov = cov + image_floor(self.camera, s.R, s.p, self._floor_points, p.systematic_px)
        if self._birth is not None and not self._anchored:
            cov = cov + carried_covariance(s.R, *self._birth)
        # exactly symmetric, as the written outputs were made (recognition/trackio._covariance6):
        # the filter's products leave it off by ~1e-17, and a caller's C == C.T (or ROS's) failed
        cov = (cov + cov.T) / 2
        return TrackStep(self._frame, time_s, status, s.p.copy(), quat.canonical(s.q), s.v.copy(), s.omega.copy(),
                         cov, inliers, reason=reason)

    def _initial_covariance(self) -> np.ndarray:
        sp = self.params.initial_sigma_p * self.diameter
        sa = np.radians(self.params.initial_sigma_deg)
        return np.diag([sp**2] * 3 + [sa**2] * 3)

    def _start_filter(self, time_s0: float, pose: Pose, cov: np.ndarray) -> None:
        """Initialise the filter; velocities unknown in the object's scale
        (:data:`~.params.INITIAL_VELOCITY_SIGMA` diameters/s and rad/s)."""
        self.filter.initialize(time_s0, pose, cov)
        if self.motion.estimates_velocity:
            s = INITIAL_VELOCITY_SIGMA
            c = self.filter.state.covariance
            c[6:9, 6:9] = (s * self.diameter) ** 2 * np.eye(3)
            c[9:12, 9:12] = s**2 * np.eye(3)

    def _forget_velocity(self) -> None:
        """Velocities back to zero and unknown (:data:`~.params.INITIAL_VELOCITY_SIGMA`), the pose
        kept. After a restart from a pose a few frames old and a percent off, one update cannot
        tell the object's motion from the start's error and puts both into the velocity
        (``(p_k − p_start)/Δt``): extrapolated, it sent the next prediction several percent of
        the diameter away and the points' KLT with it. Held, the next frame starts where the
        object was, as the re-acquisition itself does."""
        s = self.filter.state
        if s is None or not self.motion.estimates_velocity:
            return
        c = np.zeros_like(s.covariance)
        c[:6, :6] = s.covariance[:6, :6]
        c[6:9, 6:9] = (INITIAL_VELOCITY_SIGMA * self.diameter) ** 2 * np.eye(3)
        c[9:12, 9:12] = INITIAL_VELOCITY_SIGMA**2 * np.eye(3)
        self.filter.state = s.replace(v=np.zeros(3), omega=np.zeros(3), covariance=c)

    def _reacquire(self, img: np.ndarray, frame: Frame, time_s: float, timings: dict) -> TrackStep | None:
        """Re-acquisition near the last pose (:mod:`.reacquire`), within ``reacquire_s`` of a loss.
        The filter restarts at the last good posterior with its velocities unknown — held, not
        extrapolated: the object may have stopped or turned back meanwhile — moved first by the
        displacement of the object's image since that frame (:func:`object_shift`, when the
        match is clear), else held where it was; the point sources get back their tracks of that
        frame, and one tracking step follows them by KLT from that frame to this one. It counts
        only if that step tracks (enough points agree, small residuals, a plausible pose), at
        least ``reacquire_min_inside`` of the object is inside the image (a pose from a sliver
        at the border is poorly determined) and the model's edges confirm the pose; else None
        (and recognition runs).

        A track re-found on keyframes (second-hand) is picked up so too, and stays second-hand;
        its edges are judged alone (its points were lifted at its own poses). Near a pose
        withheld in doubt the edges must confirm it as a doubted pose is confirmed
        (``doubted_shift``). Second-hand tracks were left to recognition until session 44, which
        found the sides no photo shows ~100 frames later, if at all; picked up with their points
        in the judgement, wide boxes came back 7–15 % off (bench/RESULTS.md, session 44)."""
        seen, p = self._seen, self.params
        if seen is None or p.reacquire_s <= 0 or time_s - seen.state.t > p.reacquire_s:
            return None
        t0 = time.perf_counter()
        s, mesh = seen.state, self.model.mesh
        shift, score = object_shift(seen.frame.gray, frame.gray, hull_mask(self.camera, mesh.vertices, s.pose))
        starts = [s.pose]
        if score >= p.reacquire_min_ncc and np.hypot(*shift) > 0.5 * p.klt.win:  # beyond KLT's easy reach
            starts.insert(0, shifted_pose(s.pose, mesh.centre, self.camera, shift))
        step = None
        options = self.filter.options
        # from a start this far off, Gauss–Newton needs more than the tracking step's iterations
        self.filter.options = replace(options, max_iterations=max(options.max_iterations, 12))
        followed = None  # a pose the measurements support while too little is inside to report it
        # near a pose withheld in doubt, the bar a doubted pose must pass to be reported again
        # (doubted_shift): picked up there at the usual bar, second-hand tracks (points lifted at
        # their own poses) came back 7 % off and drifted on (zoo wide box, bench/RESULTS.md, session 44)
        limit = p.doubted_shift if seen.doubted else p.max_edge_shift
        if seen.followed:  # one frame ago: continue that track, velocities and all, first
            starts.insert(0, None)
        try:
            for pose in starts:
                if pose is None:
                    self.filter.state, self.filter.prior = s, None
                else:
                    self._start_filter(s.t, pose, s.pose_covariance)
                self.trained.tracks = seen.trained
                vars(self.mesh_points).update(vars(seen.mesh))  # (its arrays are rebound, never mutated)
                self._prev = seen.frame
                # the same track, picked up again: first- or second-hand as it was, and judged so
                self._second_hand, self._birth = seen.second_hand, seen.birth
                step = self._track(img, frame, time_s, {})
                # (a second-hand track's points were lifted at its own poses: they agree with it
                # whatever it is, so its edges are judged alone, as at its start: _start_on_mesh)
                shift = np.inf if step.status == "lost" else self._edge_shift(frame.gray, self.filter.state.pose,
                                                                              points=not seen.second_hand)
                if shift <= PoseParams().max_edge_shift:  # the measurements and the edges support it
                    self._forget_velocity()
                    if (shift <= limit and silhouette_inside(mesh, self.camera, self.filter.state.pose)[0]
                            >= p.reacquire_min_inside):
                        break
                    if followed is None:
                        if self.mesh_points in self.sources:  # corners on what came into view
                            self.mesh_points.spawn(FrameContext(img, frame, None, self.camera, self.filter.state),
                                                   self.filter.state, vouched=False)
                        # (the same track: second-hand, birth and doubt as it was lost)
                        followed = replace(seen, state=self.filter.state, frame=frame, trained=self.trained.tracks,
                                           mesh=copy.copy(self.mesh_points), followed=True)
                self._lost(time_s, "")
                step = None
        finally:
            self.filter.options = options
        timings["reacquire"] = _ms(t0)
        if step is not None:
            step.status, step.reason = "init", "re-acquired near the last pose"
            self._probation = max(p.probation_frames, p.doubt_frames if seen.doubted else 0)
        elif followed is not None:
            # Followed, not reported: the next frame's attempt starts from this one, one frame
            # away, instead of from the frame before the loss, which KLT cannot bridge once the
            # object has turned and slid for a few frames (it comes back into view gradually).
            self._seen = followed
        return step

    def _initialise(self, img: np.ndarray, frame: Frame, time_s: float, timings: dict) -> TrackStep:
        """*init*: the user's pose, re-acquisition near the last pose (:meth:`_reacquire`) or
        recognition; then anchor model points and refine."""
        if self._pending is None:
            step = self._reacquire(img, frame, time_s, timings)
            if step is not None:
                return step
        if self._pending is not None:
            pose, t_given = self._pending
            self._pending = None
            z = pose.apply(self.model.mesh.vertices)[:, 2]
            if np.any(z <= 1e-9):
                # (t = 0, a pose behind the camera: "only 0 model points matched near the pose"
                # said nothing of why; the next frame is searched by recognition, as before)
                return self._lost(time_s, f"given pose refused: the object would be (partly) behind the camera "
                                          f"(its nearest vertex at z = {z.min():.3g} mesh units)")
            cov, how = self._initial_covariance(), "given pose"
            self._second_hand, self._birth = False, None
            time_s0 = time_s if t_given is None else t_given  # (a frame before t_given: refused, _check_clock)
        else:
            wait = self.params.relocate_interval_s
            if wait and self._relocated_at is not None and time_s - self._relocated_at < wait:
                return self._lost(time_s, f"not searched: recognition runs every {wait:g} s while lost "
                                          f"(relocate_interval_s)")
            self._relocated_at = time_s
            t0 = time.perf_counter()
            model, index, prefer = self.model, self._index(), None
            if len(self.keyframes):  # the sides seen earlier in this run too (keyframes.py)
                p = self.params
                if p.keyframe_synthetic_deg:
                    self.keyframes.synthesise(self.model.mesh, params_from_manifest(self.model.manifest),
                                              p.keyframe_synthetic_deg, p.keyframe_synthetic_per_frame,
                                              p.keyframe_synthetic_min_cos,
                                              executor=self.executor if p.pipelined_refresh else None)
                    timings["synthesise"] = _ms(t0)
                model, index, prefer = self.keyframes.refind_model(self.model)
            loc = locate(img, self.camera, model, self.params.locate, index=index, prefer=prefer)
            if loc.found and loc.viewset.startswith("keyframe"):
                how = f"re-found on this run's {loc.viewset}"
            elif loc.found and loc.viewset in self._relayed_views:  # (as second-hand: Viewset.relayed)
                how = f"re-found on the relayed view {loc.viewset}"
            else:
                how = "recognition"
            self._second_hand = how != "recognition"
            timings["locate"] = _ms(t0)
            if not loc.found:
                return self._lost(time_s, f"not found: {loc.reason}")
            pose, cov, time_s0 = Pose(loc.q_wxyz, loc.t), loc.covariance, time_s
            why = self._unlike_keyframes(frame.gray, pose, timings)
            if why:
                return self._lost(time_s, f"{how}, refused: {why}")
            cov = 0.5 * (cov + cov.T) + 1e-9 * np.eye(6)
            self._birth = (pose.R, cov) if self._second_hand else None
        self._start_filter(time_s0, pose, cov)
        prior = self.filter.predict(time_s)
        t0 = time.perf_counter()
        tracks, _, _ = self._anchors().now(img, self.camera, prior.pose, Tracks.empty(), True,
                                                lambda f: self._keyframe_matches(f, prior.pose))
        timings["replenish"] = _ms(t0)
        ok, why, inl = False, f"only {len(tracks)} model points matched near the pose", np.zeros(0, bool)
        if len(tracks) >= self.params.min_inliers:
            t0 = time.perf_counter()
            block = PointBlock.isotropic(self.trained.name, tracks, self.params.sigma_px)
            ok, why, inl = self._adjust(block)
            timings["adjust"] = _ms(t0)
            if not ok:  # they disagree (texture repeated on other faces matched them): as if none
                self._start_filter(time_s0, pose, cov)  # (the failed adjustment moved the state)
                prior, tracks = self.filter.predict(time_s), Tracks.empty()
        if not ok:
            if self._start_on_mesh(img, frame, prior, tracks):
                self._probation = self.params.probation_frames
                reason = f"{how}: {self._why_on_mesh(prior.pose, why)}; points born on the mesh, confirmed by its edges"
                if how == "given pose":
                    return self._pose_step(time_s, "init", len(self.mesh_points), reason=reason)
                # Found (recognition, keyframes), not given: only the edges vouch for it (the
                # points were just born at it, they agree with it whatever it is), and edges alone
                # leave open a turn about an axis of symmetry. It is withheld in this frame and
                # reported from the next one that tracks, with that frame's measurements in it
                # (step()). The zoo's tall boxes re-found on their keyframes 5.3° and 5.7° off
                # about their long axis, both confirmed by the edges; one frame later 2.8° off,
                # or lost; a tall box found by recognition at frame 0 2.8 % off was 0.5 % off in
                # the next frame (bench/RESULTS.md, session 47).
                self._unconfirmed = reason
                return TrackStep(self._frame, time_s, "lost", inliers=len(self.mesh_points),
                                 reason=f"{reason}: the pose is withheld until the next frame confirms it")
            return self._lost(time_s, f"{how}: {why}", int(inl.sum()))
        self.trained.tracks = tracks.keep(inl)
        self._anchored = len(self.trained) >= self.params.min_inliers
        if how != "given pose" and not self._edges_confirm(frame.gray, self.filter.state.pose, strict=True):
            # recognition allows its edge refit to move a pose by the whole 5 %/5° criterion; a
            # pose the tracker reports must pass its own, stricter test (max_edge_shift)
            return self._lost(time_s, f"{how}: the model's edges refit the pose by more than "
                              f"{self.params.max_edge_shift:g} of the 5 %/5° criterion", int(inl.sum()))
        self._since_refresh = 0
        if self.mesh_points in self.sources:  # the first corners on the mesh, at the refined pose
            self.mesh_points.spawn(FrameContext(img, frame, None, self.camera, prior), self.filter.state)
        return self._pose_step(time_s, "init", int(inl.sum()), reason=how)

    def _why_on_mesh(self, pose: Pose, why: str) -> str:
        """Why a start (at ``pose``) is on points born on the mesh rather than on trained points,
        ``why`` being what the trained points' attempt said: "no trained view shows this side"
        only when every view of the model sees the object from at least recognition's
        ``max_view_angle_deg`` away; otherwise that attempt's reason, with the nearest view. Why:
        a 300 × 30 × 15 mm bar found at the exact pose of its training photo 0 (on another
        background, 0° from that view) was told no trained view showed its side (user report,
        finding 5)."""
        views = self.model.viewsets
        angles = view_angles_deg(pose, self.model.mesh.centre, views)
        if not len(angles) or angles.min() >= self.params.locate.pose.max_view_angle_deg:
            return "no trained view shows this side"
        k = int(np.argmin(angles))
        return f"{why}, though the model's view {views[k].label} sees this side from {angles[k]:.0f}° away"

    def _unlike_keyframes(self, grey: np.ndarray, pose: Pose, timings: dict) -> str | None:
        """Why a pose found after a loss does not look as the object looked in this run's
        keyframes (their crops rendered at the pose correlate with the frame below
        ``refind_min_texture_ncc``: :mod:`..appearance`), or None (it does, or no keyframe saw
        what the pose shows). SIFT consensus and the edges cannot tell apart faces that share
        texture and outline; the rest of the texture can."""
        return self._keyframe_texture(grey, pose, timings)[0]

    def _keyframe_texture(self, grey: np.ndarray, pose: Pose, timings: dict):
        """:meth:`_unlike_keyframes`' answer and the agreement it read (None: not checked)."""
        p = self.params
        if not p.refind_min_texture_ncc or not len(self.keyframes):
            return None, None
        t0 = time.perf_counter()
        agreement = self.keyframes.texture_agreement(grey, self.camera, pose, self.model.mesh)
        timings["texture"] = timings.get("texture", 0.0) + _ms(t0)
        if agreement.pixels and agreement.ncc < p.refind_min_texture_ncc:
            return (f"the keyframes' texture rendered at the pose correlates {agreement.ncc:.2f} with the frame "
                    f"over {agreement.pixels} px (at least {p.refind_min_texture_ncc:g} needed)"), agreement
        return None, agreement

    def _texture_audit(self, ctx: FrameContext, timings: dict) -> str | None:
        """The keyframes' texture as a judge where no trained point anchors the frame (or the
        track was re-found on keyframes): why the pose does not look as this run's keyframes
        show the object (:meth:`_unlike_keyframes`, the re-finding's test), or None. Why: such a
        track's points were lifted at its own poses and drift with it, and the edges' refit,
        which includes them, passed a pose drifting in depth (the live configuration's wide box
        walk #1: 5.1–6.0 % off at frames 172–175, keyframe texture 0.31–0.42 at 174–175, where
        poses within 2.5 %/2.5° of the truth never read below 0.65 on ten live walks of five
        objects). Checked every such frame, not every third as the edges are: a drift of
        0.6 % a frame crosses 5 % between two audits. Off with ``audit_texture`` False; no
        keyframe seeing what the pose shows: no evidence, no doubt. Cost: one texture check
        (~6–11 ms) in the frames it runs in, 0.2–0.7 ms a frame on average over a walk.

        Where the texture reads below ``1 − texture_refit_gain``, it is also followed into the
        frame (:meth:`.keyframes.Keyframes.texture_refit`): a pose the refit moves by more than
        ``texture_refit_shift`` of the criterion, where the texture correlates better by the
        gain, is withheld too, and (``texture_refit_restart``) the track goes on from the
        refit's pose with its mesh points lifted again there. Why: the correlation sees a drift
        only as a lower maximum (a flat box 5.4 % off in depth read 0.87–0.93, the truth 0.996);
        the refit finds where that maximum is (bench/RESULTS.md, session 49). A refit that leaves
        the pose reported, in a frame with fewer than ``min_inliers`` trained points, hands its
        consensus to the trained source as anchors that never anchor (``texture_anchors``: a
        track born on its own poses then follows texture placed by the keyframes; session 50)."""
        p = self.params
        if not p.audit_texture or (ctx.anchored and not self._second_hand):
            return None
        pose = self.filter.state.pose
        why, agreement = self._keyframe_texture(ctx.frame.gray, pose, timings)
        if (why or agreement is None or not agreement.pixels or not p.texture_refit_shift
                or agreement.ncc > 1.0 - p.texture_refit_gain  # (no pose could correlate better by the gain)
                or (self._tracked % max(p.texture_refit_every, 1) and not (self._doubted or self._probation))):
            return why
        # the texture followed from the pose to where the frame shows it (see params)
        t0 = time.perf_counter()
        mesh = self.model.mesh
        fit = self.keyframes.texture_refit(ctx.frame.gray, self.camera, pose, mesh, agreement.rendered)
        timings["texture"] += _ms(t0)
        if fit.pose is None or fit.inliers < p.texture_refit_min_inliers:
            return None
        shift = pose_shift(fit.pose, pose, mesh)
        if shift <= p.texture_refit_shift:
            if p.texture_anchors and len(self.trained) < p.min_inliers:
                # the keyframes' texture, where this frame shows it: anchors that never anchor (params)
                self.trained.tracks = Tracks(fit.X, fit.uv)
                self._keyframe_anchors = {tuple(x) for x in fit.X.tolist()}
            return None
        t0 = time.perf_counter()
        there = self.keyframes.texture_agreement(ctx.frame.gray, self.camera, fit.pose, mesh)
        timings["texture"] += _ms(t0)
        if there.pixels and there.ncc >= agreement.ncc + p.texture_refit_gain:
            if p.texture_refit_restart:  # (the track goes on from where the texture put it)
                self.filter.state = self.filter.state.replace(p=np.asarray(fit.pose.t, float),
                                                              q=np.asarray(fit.pose.q_wxyz, float))
                self._forget_velocity()
                self.mesh_points.relift(self.camera, self.filter.state)
            return (f"the keyframes' texture puts the object {shift:.2f} of the 5 %/5° criterion away "
                    f"({fit.inliers} points; it correlates {agreement.ncc:.2f} at the pose, {there.ncc:.2f} there)")
        return None

    def _start_on_mesh(self, img: np.ndarray, frame: Frame, prior, tracks: Tracks) -> bool:
        """A pose (the user's, or found again on a keyframe) on a side no trained view shows
        (SIFT anchors nothing there): start on corners born on the mesh at that pose, if at least
        ``min_inliers`` are born and the model's edges confirm the pose (:meth:`_edges_confirm`,
        the test a track carried by mesh points passes, :meth:`_carried`); a wrong pose fails it.

        A pose re-found on the tracker's own keyframes (second-hand) must pass the strict test,
        the edge refit moving it by at most ``max_edge_shift`` of the 5 %/5° criterion, on the
        edges *alone*, before any point is born: points lifted at the pose under test agree with
        it whatever it is, and during the probation that follows (strict tests with the born
        points in the refit) they held a flat box re-found on a synthetic view 3.6 %/5.3° off
        (zoo walk, learned model). Four renderings of the six walks (truth pass): poses beyond
        5 %/5° 4 → 1, lost while ≥ 30 % visible 3474 → 3565 (+2.6 %), the wide boxes' mean error
        0.86 → 0.50 % and 0.78 → 0.35 % (bench/RESULTS.md, session 27)."""
        if self.mesh_points not in self.sources or self.edges not in self.sources:
            return False
        if self._second_hand:  # (re-found on its own keyframes: see the docstring)
            settled = self._edge_settled(frame.gray, prior.pose)
            if settled is None:
                return False
            if settled is not prior.pose:  # (the filter restarts there, the re-found covariance kept)
                cov = self.filter.state.pose_covariance
                self._start_filter(prior.t, settled, cov)
                prior = self.filter.predict(prior.t)
                self._birth = (settled.R, cov)
        elif not self._edges_confirm(frame.gray, prior.pose):
            return False
        n = self.mesh_points.spawn(FrameContext(img, frame, None, self.camera, prior), self.filter.state)
        if n < self.params.min_inliers:
            self.mesh_points.reset()
            return False
        self.trained.tracks = tracks
        self._since_refresh = 0
        self._anchored = False
        return True

    def _track(self, img: np.ndarray, frame: Frame, time_s: float, timings: dict) -> TrackStep:
        """*tracking*: predict → measure (every source) → adjust → settle → re-anchor."""
        p = self.params
        t0 = time.perf_counter()
        posterior_before = self.filter.state.pose  # the previous frame's posterior
        prior = self.filter.predict(time_s)
        timings["predict"] = _ms(t0)
        if np.any(prior.pose.apply(self.model.mesh.centre[None])[:, 2] < p.min_depth * self.diameter):
            return self._lost(time_s, "prediction puts the object behind or at the camera")

        if self._anchor_job is not None and self._anchor_job.future.done():
            # a re-anchoring run in the background on an earlier frame: its matches join the
            # tracks, which live in the previous frame, where KLT starts from
            t0 = time.perf_counter()
            job, self._anchor_job = self._anchor_job, None
            feats, m = job.future.result()
            if len(m) < p.min_anchor_matches:  # as _anchor_now, judged on the raw matches
                m_kf = self._keyframe_matches(feats, job.pose)
                m = m_kf if m_kf is not None and len(m_kf) > len(m) else m
            pose_then = job.pose
            if job.frame is not self._prev:  # found on an older frame: carry the keypoints over
                feats, m, pose_then = self._anchors().carry(feats, m, self.camera, job.frame, self._prev, posterior_before)
            self.trained.tracks, n, _ = self._anchors().merge(feats, m, self.camera, pose_then, self.trained.tracks, wide=False)
            if n < p.min_anchor_matches and not job.full and self._anchors().reduced:
                # The shrunk window found too little: look again at full resolution with every
                # feature, as the offline tracker does, at once (below), and count the attempt
                # by that look. Why: a face seen at a grazing angle loses its features first when
                # shrunk; the zoo flat box #31 (live) failed two background refreshes in a row at
                # 320 px, went 10 frames without anchors and drifted to 6°; looked at again in
                # full it held within 3.5°. 24 live walks: frames lost 2293 → 2260, beyond 2 %/2°
                # 261 → 250; box.mp4 unchanged (no shrunk look fails there); bench/RESULTS.md,
                # session 46.
                self._full_retry = True
            else:
                self._count_refresh(n)
            timings["replenish"] = _ms(t0)
            if self._failed_refreshes >= p.max_failed_refreshes and not self._carried(None, None, None):
                return self._lost(time_s, "the object's texture is no longer found where it is tracked")

        t0 = time.perf_counter()
        ctx = FrameContext(img, frame, self._prev, self.camera, prior)
        follow_together(ctx, self.sources, timings)  # one KLT call for every point source
        ctx.anchored = False
        measured: dict = {}
        for s in self.sources:  # the points first (the trained first: whether they anchor this
            if s in self._shape_sources:  # frame is known to the mesh points)
                continue
            measured[s] = s.measure(ctx, timings)
            if s is self.trained:
                ctx.anchored = self._anchored = self._anchoring(measured[s]) >= p.min_inliers
                # (whether a view learned now would be first-hand: only asked while learning)
                self._first_hand = p.learn and ctx.anchored and self._anchoring(measured[s], own=True) >= p.min_inliers
        shape_ctx = self._recentred(ctx, list(measured.values()), timings)
        for s in self.sources:
            if s in self._shape_sources:
                measured[s] = s.measure(shape_ctx, timings)
        blocks = [measured[s] for s in self.sources]
        block = PointBlock.stack(blocks)
        timings["measure"] = _ms(t0)  # visibility + KLT + gating
        if len(block) < p.min_inliers:
            return self._lost(time_s, f"only {len(block)} points tracked", len(block))

        t0 = time.perf_counter()
        good, why, inl = self._adjust(block)
        timings["adjust"] = _ms(t0)
        n_inl = int(inl.sum())
        if not good:
            return self._lost(time_s, why, n_inl)
        # edges refine and carry the pose, but clutter has edges everywhere: the object's own
        # texture (trained or mesh-born points) must still be there to vouch for it
        n_points = self._inliers_of(blocks, inl, exclude=self._shape_sources)
        n_textured = sum(len(b) for s, b in zip(self.sources, blocks) if s not in self._shape_sources)
        if n_points < p.min_inliers and len(blocks) > 1 and self._shape_sources:
            return self._lost(time_s, f"only {n_points} textured points agree", n_inl)
        conflict = None
        if p.texture_chi2 and self._shape_sources and len(blocks) > 1:
            inl, conflict = self._unless_outvoted(blocks, block, inl)
            n_inl = int(inl.sum())
        why = self._implausible(self.filter.state.pose)
        if why:
            return self._lost(time_s, f"pose: {why}", n_inl)
        ctx.vouched = not self._doubted  # (a track in doubt learns nothing: Tracker._doubt)
        shape_ctx.vouched = ctx.vouched
        for s, b, m in zip(self.sources, blocks, PointBlock.split(blocks, inl)):
            s.settle(shape_ctx if s in self._shape_sources else ctx, b, m, self.filter.state)
        self._tracked += 1
        if conflict is not None:
            return self._doubt(time_s, f"the textured points and the model's edges put the object {conflict:.2f} of "
                               f"the 5 %/5° criterion apart", n_inl)
        t0 = time.perf_counter()  # (the edges' judgement: the "judge" stage)
        if self._probation > 0 or self._doubted:
            # a track started without trained points (probation), or one the edges doubted in an
            # earlier frame: the edges must confirm every pose
            self._probation = max(self._probation - 1, 0)
            limit = p.doubted_shift if self._doubted else None  # (a doubted pose: stronger evidence)
            confirmed = self._edges_confirm(frame.gray, self.filter.state.pose, strict=True, limit=limit)
            timings["judge"] = _ms(t0)
            if not confirmed:
                return self._doubt(time_s, "the model's edges do not confirm the pose", n_inl)
        elif (every := self._audit_interval(ctx)) and self._tracked % every == 0:
            # The audit: points lifted at a pose that was off, or edges locked on the wrong
            # gradient, agree among themselves with a pose that is off; the edge refit is
            # evidence from the model's shape that they cannot fake.
            shift = self._edge_shift(frame.gray, self.filter.state.pose, agreement=False)
            timings["judge"] = _ms(t0)
            if shift is not None and shift > p.max_edge_shift:
                return self._doubt(time_s, f"the model's edges refit the pose by {shift:.2f} of the 5 %/5° criterion", n_inl)
        if why := self._texture_audit(ctx, timings):  # (every frame no trained point anchors)
            return self._doubt(time_s, why, n_inl)
        if self._doubted:  # confirmed again: reported from this frame on, each frame tested
            self._doubted = 0  # strictly for doubt_frames more: one confirmation in the blur let
            self._probation = max(self._probation, p.doubt_frames)  # the next frames through unjudged
        if self.trained not in self.sources:  # (a source alone: nothing to re-anchor)
            self._capture(ctx, n_points, n_textured, time_s, timings)
            return self._pose_step(time_s, "tracking", n_inl, scale=self._disagreement(blocks, inl))
        self._since_refresh += 1
        due = p.refresh_every and self._since_refresh >= p.refresh_every
        # thin: replenish now; but after a refresh that found no texture (a side no view shows),
        # retry only when due: SIFT in every frame would find nothing at great cost
        thin = len(self.trained) < p.min_points and (self._failed_refreshes == 0 or due)
        scarce = len(self.trained) < 2 * p.min_inliers  # too few to wait for the background
        retry = self._full_retry
        if (due or thin or retry) and not scarce and p.pipelined_refresh and self.executor is not None:
            if self._anchor_job is None:  # (one at a time: a busy executor is not queued up)
                job = self._anchors().submit(self.executor, img, self.camera, self.filter.state.pose, frame, full=retry)
                self._full_retry = False
                if job is not None:
                    self._anchor_job = job
                    self._since_refresh = 0
        elif thin or due:
            t0 = time.perf_counter()
            before, kept = self.filter.state, self.trained.tracks
            pose = self.filter.state.pose
            tracks, n, replaced = self._anchors().now(img, self.camera, pose, self.trained.tracks, False,
                                                      lambda f: self._keyframe_matches(f, pose))
            self.trained.tracks = tracks
            if replaced:  # the KLT tracks had slid: adjust this frame again to the fresh matches
                redo = PointBlock.isotropic(self.trained.name, tracks, p.sigma_px)
                good, why, inl_redo = self._adjust(redo)
                if good:
                    inl, n_inl = inl_redo, int(inl_redo.sum())
                    self.trained.tracks = tracks.keep(inl_redo)
                elif self._inliers_of(blocks, inl, only=self.mesh_points) >= p.min_inliers:
                    # the fresh matches agree among themselves but not with this frame (texture
                    # repeated on another face matched them) while the points born on the mesh
                    # carry the pose every source agreed on: it stays, and the refresh found
                    # nothing (repeated failures go to the edges' judgement, _carried)
                    self.filter.state, self.trained.tracks, n = before, kept, 0
                else:
                    timings["replenish"] = _ms(t0)
                    return self._lost(time_s, f"re-anchoring: {why}", int(inl_redo.sum()))
            timings["replenish"] = _ms(t0)
            self._since_refresh = 0
            self._count_refresh(n)
            if self._failed_refreshes >= p.max_failed_refreshes and not self._carried(ctx, blocks, inl):
                return self._lost(time_s, "the object's texture is no longer found where it is tracked", n_inl)
        self._capture(ctx, n_points, n_textured, time_s, timings)
        return self._pose_step(time_s, "tracking", n_inl, scale=self._disagreement(blocks, inl))

    def _audit_interval(self, ctx: FrameContext) -> int:
        """Tracked frames between audits: ``audit_every_anchored`` while this frame's trained
        points anchor the track (at least ``min_inliers`` measured, the last re-anchoring found
        the trained texture, and the track was not re-found on this run's keyframes), else
        ``audit_every``. Why: what the audit catches — points lifted at a pose that was off,
        edges locked onto the print, agreeing among themselves — the trained points, matched
        afresh by SIFT every ``refresh_every`` frames, already judge (:meth:`_unless_outvoted`);
        where they are absent the audit is the only judge. On the 24 zoo walks auditing anchored
        frames every 6th frame instead of every 3rd changed no status and no pose (one withheld
        frame was withheld by the strict test instead of the audit); on
        ``box.mp4`` (always anchored) it left the poses the same and saved ~1 ms a frame
        (bench/RESULTS.md, session 32). Unanchored frames are audited every frame since session
        39 (``audit_every`` 1): a second-hand track drifted past 5 % between two audits."""
        p = self.params
        if p.audit_every_anchored and ctx.anchored and not (self._second_hand or self._failed_refreshes):
            return p.audit_every_anchored
        return p.audit_every

    def _capture(self, ctx: FrameContext, n_points: int, n_textured: int, time_s: float, timings: dict) -> None:
        """Keep this frame's view, lifted onto the mesh at the pose (:func:`learned_viewset`): as a
        keyframe (:mod:`.keyframes`, every ``keyframe_every`` frames when it is wanted and the
        pose's 1-σ is below ``mesh_spawn_sigma_p`` / ``_deg``) and, with ``params.learn``, as a
        learned viewset (every ``learn_every`` frames when it sees the object from a new
        direction and the pose is tighter: ``learn_sigma_p`` / ``_deg``). Either needs
        ``learn_min_inliers`` textured points agreeing, ``learn_min_share`` of those measured
        (nothing covers the object), and the model's edges to agree with the image. The cheap
        tests come first; one SIFT + lifting serves both. (Its time is the ``learn`` stage.) A
        track re-found on this run's keyframes keeps nothing unless trained points anchor the
        frame (``capture_second_hand``). A keyframe keeps the frame's crop of the object, from
        which its synthetic views are made after a loss (:meth:`.keyframes.Keyframes.synthesise`).

        With an executor and ``pipelined_refresh`` (live streams), the SIFT + lifting (~45 ms)
        runs on the executor, as re-anchoring does, and a later step keeps its result: inside the
        step it set the p99 of two 30 fps streams (bench/RESULTS.md, serving, session 24). One
        at a time; a loss drops it."""
        p = self.params
        job = self._capture_job
        if job is not None and job.future.done():
            self._capture_job = None
            self._keep_view(job.future.result(), job)
        self._learn_wait -= 1
        self._keyframe_wait -= 1
        if self._tracked < p.learn_after or self._capture_job is not None:
            return
        if self._second_hand and not (p.capture_second_hand or ctx.anchored):
            return
        state = self.filter.state
        pose = state.pose
        mesh = self.model.mesh
        slot = None
        if self._keyframe_wait <= 0:
            slot = self.keyframes.slot(pose, time_s)
            if slot is not None and not confident(state, self.diameter, p.mesh_spawn_sigma_p, p.mesh_spawn_sigma_deg):
                slot = None
        learn = (p.learn and self._learn_wait <= 0
                 and sum(vs.learned for vs in self.model.viewsets) < p.learn_max_views
                 and is_new_direction(pose, mesh.centre, self.model.viewsets, p.learn_min_angle_deg)
                 and confident(state, self.diameter, p.learn_sigma_p, p.learn_sigma_deg))
        if slot is None and not learn:
            return
        if n_points < p.learn_min_inliers or n_points < p.learn_min_share * n_textured:
            return
        t0 = time.perf_counter()
        if slot is not None:
            self._keyframe_wait = p.keyframe_every
        if learn:
            self._learn_wait = p.learn_every
        if not self._edges_confirm(ctx.frame.gray, pose, strict=True):
            timings["learn"] = _ms(t0)
            return
        mask = birth_mask(mesh, self.camera, pose, p)
        args = (f"learned{len(self.learned) + 1}", ctx.image, mask, self.camera, pose, mesh,
                params_from_manifest(self.model.manifest), p.learn_min_cos, self.model.rfch if learn else None,
                texture_zoom(self.model.training_width, self.camera.width))
        cap = Capture(slot, learn, time_s, pose, relayed=not self._first_hand)
        if slot is not None and p.keyframe_synthetic_deg:  # (the crop: its synthetic views, after a loss)
            cap.crop, cap.crop_camera = object_crop(ctx.image, self.camera, mesh, pose)
        if p.pipelined_refresh and self.executor is not None:
            cap.future = self.executor.submit(learned_viewset, *args)
            self._capture_job = cap
            timings["learn"] = _ms(t0)
            return
        vs = learned_viewset(*args)
        timings["learn"] = _ms(t0)
        self._keep_view(vs, cap)

    def _keep_view(self, vs: Viewset, cap: Capture) -> None:
        """The view lifted by :meth:`_capture` (:class:`Capture`: at ``cap.pose``, taken at
        ``cap.time_s``): a keyframe in ``cap.slot`` and, with ``cap.learn``, a learned viewset,
        if it holds enough keypoints."""
        p, mesh = self.params, self.model.mesh
        if len(vs) < p.learn_min_keypoints:
            return
        if cap.slot is not None:
            self.keyframes.add(Keyframe(cap.time_s, cap.pose.viewing_direction(mesh.centre), replace(vs, cooccurrence=None),
                                        cap.crop, cap.crop_camera), cap.slot)
        if not cap.learn:
            return
        model = with_learned(self.model, [replace(vs, relayed=cap.relayed)], p.learn_max_views, p.learn_min_angle_deg)
        if model is self.model:
            return
        self.model = model
        self.learned.append(replace(model.viewsets[-1], cooccurrence=vs.cooccurrence))  # (as labelled in the model)
        if cap.relayed and not p.relayed_views_anchor:  # (Viewset.relayed: see __init__)
            self._relayed |= {tuple(x) for x in vs.points3d.tolist()}
            self._relayed_views.add(self.learned[-1].label)
        self.index, self._anchor = None, None  # rebuilt with the learned view when next needed

    def _edges_confirm(self, gray: np.ndarray, pose: Pose, strict: bool = False, limit: float | None = None) -> bool:
        """The evidence a pose carried by points born on the mesh must show (:mod:`.edge_tests`):
        its edges agree with the image; ``strict`` (a re-acquired pose, a view about to be kept, a
        track on probation) also asks that the edge refit move it by at most ``max_edge_shift`` of
        the 5 % / 5° criterion (:meth:`_edge_shift`), or ``limit`` if given."""
        if strict:
            return self._edge_shift(gray, pose) <= (self.params.max_edge_shift if limit is None else limit)
        return edges_agree_at(gray, self.model.mesh, self.camera, pose)

    def _edge_settled(self, gray: np.ndarray, pose: Pose) -> Pose | None:
        """A pose re-found on this run's keyframes, settled on the model's edges alone (no point
        may vouch for it: :meth:`_start_on_mesh`): :func:`.edge_tests.settle_on_edges` with
        ``max_edge_shift`` and ``doubted_shift``."""
        p = self.params
        return settle_on_edges(lambda q: self._edge_refit(gray, q, points=False), pose, p.max_edge_shift,
                               p.doubted_shift)

    def _edge_shift(self, gray: np.ndarray, pose: Pose, agreement: bool = True, points: bool = True) -> float | None:
        """How far the edge refit (:meth:`_edge_refit`) moves ``pose``, as a share of the 5 % / 5°
        criterion; ``inf`` when the edges do not agree with the image at all (with ``agreement``);
        None when too few edge samples are found to judge."""
        fit = self._edge_refit(gray, pose, agreement, points)
        if fit is None:
            return np.inf if agreement else None
        return fit.shift

    def _edge_refit(self, gray: np.ndarray, pose: Pose, agreement: bool = True, points: bool = True):
        """:func:`.edge_tests.edge_refit` with the points that may vouch for the pose — the trained
        ones and the mesh points born where the pose was vouched for — or, without ``points``,
        the edges alone."""
        tracks = self.trained.tracks + self.mesh_points.tracks.keep(self.mesh_points.vouched) if points else Tracks.empty()
        return edge_refit(gray, self.model.mesh, self.camera, pose, tracks.X, tracks.uv, agreement)

    def _recentred(self, ctx: FrameContext, point_blocks: list[PointBlock], timings: dict) -> FrameContext:
        """Where the outline's sources search: at the prediction, unless the points say it is off.

        The edges and the outline search a few px across the predicted outline (at most
        ``contour_max_reach_px``); when the motion changes abruptly (an object stopped, a camera
        jolted) the prediction can be tens of px off, and there they lock onto the print or the
        background next to the prediction, agree with it and outvote the points, which KLT
        followed from the previous frame to where the object is (the cookie box stopping after a
        slide at 47 px a frame: lost, "only 2 textured points agree"). So when the points' median
        innovation exceeds ``recentre_px`` they are adjusted alone first (a *pilot*, by
        :meth:`_two_passes` as :meth:`_adjust`); when that moves the model's
        vertices in the image by more than ``recentre_px``, the outline's sources search
        around the pilot's pose, with the prediction's covariance (how far to search is the
        prediction's business). The joint adjustment still starts from the prediction."""
        p = self.params
        if not p.recentre_px or not self._shape_sources:
            return ctx
        points = PointBlock.stack(point_blocks)
        if len(points) < p.min_inliers:
            return ctx
        t0 = time.perf_counter()
        uv, _ = project_model_points(self.camera, points.X, ctx.prior.p, ctx.prior.R, False)
        if np.median(np.linalg.norm(points.uv - uv, axis=1)) <= p.recentre_px:
            return ctx  # (the points agree with the prediction: no pilot needed, the usual case)
        state, _, _, _ = self._two_passes(points, lambda m: adjust(ctx.prior, [m], self.filter.options,
                                                                  self.motion.estimates_velocity).state)
        timings["pilot"] = _ms(t0)
        if state is None:
            return ctx
        V = self.model.mesh.vertices
        A, B = ctx.prior.pose.apply(V), state.pose.apply(V)
        if not (np.all(A[:, 2] > 1e-9) and np.all(B[:, 2] > 1e-9)):
            return ctx
        if np.max(np.linalg.norm(self.camera.project(B) - self.camera.project(A), axis=1)) <= p.recentre_px:
            return ctx
        moved = replace(ctx.prior, p=state.p.copy(), q=state.q.copy())
        return replace(ctx, prior=moved, _zbuffer=None)

    def _two_passes(self, block: PointBlock, solve) -> tuple[FilterState | None, str | None, np.ndarray, np.ndarray]:
        """Adjust to the block by ``solve`` (measurements → state), then once more without the
        outliers (posterior Mahalanobis residual beyond ``outlier_px / sigma_px``). Returns
        ``(state, None, inlier mask, squared residuals)``, or ``(None, why, mask, …)``."""
        p = self.params
        keep = np.ones(len(block), bool)
        inl, m2, state = keep, np.zeros(len(block)), None
        limit2 = (p.outlier_px / p.sigma_px) ** 2
        for _ in range(2):
            if keep.sum() < p.min_inliers:
                return None, f"only {int(keep.sum())} points agree", keep, m2
            try:
                state = solve(block.keep(keep).measurements(self.camera))
            except (SingularProblemError, np.linalg.LinAlgError):
                return None, "the points do not determine the pose", keep, m2
            uv, _ = project_model_points(self.camera, block.X, state.p, state.R, False)
            m2 = mahalanobis2(uv - block.uv, block.C)
            inl = m2 < limit2
            if np.array_equal(inl, keep) or inl.sum() < p.min_inliers:
                break
            keep = inl
        return state, None, inl, m2

    def _adjust(self, block: PointBlock) -> tuple[bool, str | None, np.ndarray]:
        """Adjust the prior to the block; redo without the outliers (posterior Mahalanobis
        residual beyond ``outlier_px / sigma_px``). Returns ``(ok, why, inlier mask)``."""
        p = self.params
        s, why, inl, m2 = self._two_passes(block, lambda m: self.filter.update([m]).state)
        if s is None:
            return False, why, inl
        n = int(inl.sum())
        if n < p.min_inliers:
            return False, f"only {n} points agree", inl
        rms = float(np.sqrt(np.mean(m2[inl]))) * p.sigma_px  # px at the trained points' noise
        if rms > p.max_rms_px:
            return False, f"residuals too large (RMS {rms:.1f} px)", inl
        if not np.all(np.isfinite(s.covariance[:6, :6])):
            return False, "the pose covariance is not finite", inl
        return True, None, inl

    def _unless_outvoted(self, blocks: list[PointBlock], block: PointBlock,
                         inl: np.ndarray) -> tuple[np.ndarray, float | None]:
        """The edges must not outvote the textured points. Edge samples outnumber the points
        several times, and a model edge whose search locked onto the wrong gradient (a
        cylinder's rim onto the print beside it) pulls the pose along it frame after frame
        while every point, within its gate, still counts as an inlier. The judges' score
        statistic at the joint pose (:func:`~.points.score_statistic`, ``T ~ χ²₆`` when they
        agree with it) tells: beyond ``texture_chi2`` this frame is adjusted again without the
        edges (when that succeeds).

        The judges are the trained points, the anchors, while at least ``min_inliers`` of them
        are inliers — and only while SIFT still finds the trained texture where it is tracked
        (the last re-anchoring succeeded): trained tracks on faces turning away slide, and then
        the edges are right. Points born on the mesh do not judge beside them: they were lifted
        at the tracker's own poses and may be the ones that are off (on a side no photo shows
        the edges are then right). In a *second-hand* track (re-found on keyframes) without
        trained points in view the points born on the mesh are all the texture there is, and
        they judge: there the edges, under a lighting change, locked onto the print next to the
        outline and turned the zoo cube 1.6 → 4.2 % in one frame while the points alone kept
        1.1 % (four renderings of the six walks: poses beyond 5 %/5° 7 → 4, bench/RESULTS.md,
        session 27).

        Returns the inlier mask of the adjustment kept, and how far apart the points and the
        edges put the object when the points outvoted the edges by more than
        ``outvote_max_shift`` of the 5 %/5° criterion (:func:`~..evidence.pose_shift` of the
        joint pose and the points' own), else None. Such a frame's pose is withheld in doubt
        (:meth:`_doubt`; the track goes on from the points' pose, and the edges must confirm it
        strictly). Why: that far apart, neither is a pose to report. Over the 48 zoo walks'
        frames where the rule fired and the two lay more than 0.7 apart (100 harsh, 77 calm),
        the points' pose was the nearer to the truth in 13 % and 36 % of them, with mean errors
        (the larger of % and °) of 8.0 and 6.9 against the joint pose's 4.1 and 6.0. Reported,
        the points' pose drifted on: the calm flat box #1, anchored by 44 trained points on its
        frontal face, turned 2.7 → 6.0° in four frames (66–70) until the audit caught it. Going
        on from the joint pose instead put 14 poses beyond 5 %/5° on the harsh cylinder #3
        (bench/RESULTS.md, session 67)."""
        owners = list(zip(self.sources, blocks))
        sizes = [len(b) for _, b in owners]
        judges = np.repeat([s is self.trained for s, _ in owners], sizes).astype(bool)
        mesh = np.repeat([s is self.mesh_points for s, _ in owners], sizes).astype(bool)
        textured = np.repeat([s not in self._shape_sources for s, _ in owners], sizes).astype(bool)
        min_inl = self.params.min_inliers
        if int((judges & inl).sum()) >= min_inl:
            if self._failed_refreshes:
                return inl, None
        elif self._second_hand:
            judges = mesh
        if int((judges & inl).sum()) < min_inl:
            return inl, None
        if score_statistic(self.camera, block.keep(judges & inl), self.filter.state) <= self.params.texture_chi2:
            return inl, None
        joint = self.filter.state
        good, _, inl_tex = self._adjust(block.keep(textured))
        if not good:
            self.filter.state = joint
            return inl, None
        out = np.zeros(len(block), bool)
        out[textured] = inl_tex
        limit = self.params.outvote_max_shift
        shift = pose_shift(self.filter.state.pose, joint.pose, self.model.mesh) if limit else 0.0
        return out, (shift if shift > limit else None)

    def _determined(self, pose: Pose) -> bool:
        """At least ``reacquire_min_inside`` of the silhouette inside the image (no render when every
        vertex projects inside): a last pose to re-acquire near. An object sliding out of the
        frame leaves the track's points on one strip of it, and the pose drifts while the points
        still agree among themselves: the zoo cube's rotation went 0.5 → 3.6° (5.9° on another
        rendering) in the six frames before it was lost at 19 % inside. Re-acquired near that
        pose, it came back 1.7 % / 6.9° off with edges that agreed (a cube's edges match a turned
        cube) and was reported. After such a loss recognition alone restarts the track."""
        if self._box_in_image(pose) is not None:
            return True
        return silhouette_inside(self.model.mesh, self.camera, pose)[0] >= self.params.reacquire_min_inside

    def _box_in_image(self, pose: Pose) -> float | None:
        """The area (px²) of the box round the mesh's projected vertices when every vertex is in
        front of the camera and projects inside the image (the whole object is in view: the
        silhouette tests need no render), else None."""
        Xc = pose.apply(self.model.mesh.vertices)
        if not np.all(Xc[:, 2] > 1e-9):
            return None
        uv = self.camera.project(Xc)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        if lo[0] >= 0 and lo[1] >= 0 and hi[0] <= self.camera.width - 1 and hi[1] <= self.camera.height - 1:
            return float(np.prod(hi - lo))
        return None

    def _implausible(self, pose: Pose) -> str | None:
        """:func:`recognition.pose.plausible`, whose silhouette render is skipped when every
        vertex projects well inside the image (then the whole object is in view) and the
        projection is large (then its area passes): the common case costs no render."""
        area = self._box_in_image(pose)
        if area is not None and area >= 0.05 * self.camera.width * self.camera.height:
            return None
        return plausible(self.camera, self.model.mesh, pose, self._plausibility)

    def _carried(self, ctx: FrameContext | None, blocks, inl) -> bool:
        """SIFT no longer finds the trained texture: is the pose still carried by the points born
        on the mesh (at least ``min_inliers`` of them agree) *and* confirmed by the object's
        edges (:func:`recognition.evidence.edge_agreement`: the visible model edges lie on aligned
        image gradients, well above this image's chance level)? Then the object has turned to
        a side no view shows, and the track goes on; otherwise it is lost."""
        if ctx is None or self.mesh_points not in self.sources:
            return False
        n_mesh = self._inliers_of(blocks, inl, only=self.mesh_points)
        if n_mesh < self.params.min_inliers:
            return False
        ok = self._edges_confirm(ctx.frame.gray, self.filter.state.pose)
        if ok:
            self._failed_refreshes = 0
        return ok

    def _anchoring(self, block: PointBlock, own: bool = False) -> int:
        """The trained source's measured points that anchor a frame: all but the anchors taken
        from the keyframes' texture (``_keyframe_anchors``, ``TrackerParams.texture_anchors``) and
        the points of views this tracker learned at frames the model's own views did not anchor
        (``_relayed``, ``TrackerParams.relayed_views_anchor``). ``own``: only the points of the
        model's own views count (those it was given; not this run's keyframes or learned views)."""
        if own:
            if self._own_points is None:
                self._own_points = {tuple(x) for vs in self._given_views if not vs.relayed for x in vs.points3d.tolist()}
            return sum(x in self._own_points for x in map(tuple, block.X.tolist()))
        if not (self._keyframe_anchors or self._relayed):
            return len(block)
        return sum(x not in self._keyframe_anchors and x not in self._relayed for x in map(tuple, block.X.tolist()))

    def _inliers_of(self, blocks, inl, only=None, exclude: tuple = ()) -> int:
        """Inliers among the blocks of one source (``only``) or of all but some (``exclude``)."""
        return sum(int(m.sum()) for s, m in zip(self.sources, PointBlock.split(blocks, inl))
                   if (only is None or s is only) and s not in exclude)

    def _count_refresh(self, n_matches: int) -> None:
        ok = n_matches >= self.params.min_anchor_matches
        self._failed_refreshes = 0 if ok else self._failed_refreshes + 1

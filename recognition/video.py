"""Tracking an object through a video: Kragic & Kyrki's Fig. 1 loop on Ude's quaternion filter.

    tracker = Tracker(model, camera, TrackerParams(motion_model="ude"))
    for image, t in frames:
        step = tracker.step(image, t)      # "init" | "tracking" | "lost"

Without a state, a frame goes to :func:`recognition.locate.locate` (or to a pose the user gave
with :meth:`Tracker.init_pose`); the filter starts there with unknown velocities. With a state,
each frame is *predict → measure → adjust*:

- predict: the motion model (``ude``, ``m1``, ``m2``, ``m3``) gives the prior pose and covariance;
- measure: the tracked model points (3-D points of the viewsets, anchored by SIFT matches) are
  followed from the previous frame by pyramidal KLT, starting from their projections at the
  predicted pose, with a forward–backward check; points hidden at the prediction are dropped;
  the rest are gated by their Mahalanobis distance under the predicted measurement covariance
  ``J P Jᵀ + σ² I``;
- adjust: :meth:`PoseFilter.update` (eq. 24, prior = prediction, Huber weights); points whose
  posterior residual is still large are outliers: they are removed and the adjustment redone.

Tracks are replenished from the model — SIFT matches in the object's predicted window whose model
points project near their keypoints — when they thin out and every ``refresh_every`` frames,
so a long sequence stays anchored to the model instead of drifting with KLT. The track is
declared lost when too few points agree, the residuals are too large, the pose is implausible
(behind the camera, out of the image), or repeated refreshes find the object's texture absent.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.adjust import AdjustOptions, SingularProblemError
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.filter import PoseFilter
from quatrack.tracking.measurements import PointMeasurements, project_model_points
from quatrack.tracking.motion import make_motion_model
from quatrack.tracking.pose import Pose
from quatrack.viewsets.store import ObjectModel

from .images import ImageError, to_bgr8
from .klt import Frame, KLTParams, make_frame, track_points
from .locate import LocateParams, locate
from .match import ModelIndex, index_for
from .visibility import VisibilityParams, merge_points, visible_points

_ANCHOR_POOL: ThreadPoolExecutor | None = None
_ANCHOR_POOL_LOCK = threading.Lock()


def _anchor_pool() -> ThreadPoolExecutor:
    """One thread shared by every tracker of the process for pipelined re-anchoring: SIFT and
    FLANN release the interpreter lock, so it runs beside the tracking steps, and its FLANN
    index (thread-local) is built once per model."""
    global _ANCHOR_POOL
    with _ANCHOR_POOL_LOCK:
        if _ANCHOR_POOL is None:
            _ANCHOR_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="quatrack-anchor")
        return _ANCHOR_POOL

# Plant noise per motion model, free of units: translation terms are per diameter² of the object
# (its bounding-box diagonal, :attr:`Mesh.extent`), rotation terms in rad². A noise in diameters
# moves the object's image by the same share of its apparent size whatever the mesh unit, the
# object's size, distance or the focal length, so one default fits a die and a car, in mm or m.
# ude/m3 are random accelerations (diameters²/s³, rad²/s³), m1/m2 random walks (diameters²/s,
# rad²/s). (Measured on the 32.8 cm cookie box, hand-held: a = 2000 cm²/s³ = 1.85 diameters²/s³.)
DEFAULT_MOTION_NOISE: dict[str, dict[str, float]] = {
    "ude": {"a": 1.85, "alpha": 20.0},
    "m3": {"sigma_p2": 1.85, "sigma_phi2": 20.0},
    "m1": {"sigma_p2": 0.093, "sigma_phi2": 0.3},
    "m2": {"sigma_p2": 0.093, "sigma_phi2": 0.3},
}
_TRANSLATION_NOISE = {"a", "sigma_p2"}  # the terms in length², scaled by the diameter²
# Velocities start unknown: standard deviation 100 diameters/s and 100 rad/s (Ude's 1e8 variance
# was in his units; in diameters it is the same "unknown" for every mesh unit).
INITIAL_VELOCITY_SIGMA = 100.0


def motion_noise(motion_model: str, diameter: float, overrides: dict | None = None) -> dict[str, float]:
    """The motion model's noise in mesh units: :data:`DEFAULT_MOTION_NOISE` with its translation
    terms times ``diameter²``, overridden by ``overrides`` (given in mesh units, as the CLI's
    ``--motion-noise``)."""
    rel = DEFAULT_MOTION_NOISE[motion_model]
    out = {k: v * (diameter**2 if k in _TRANSLATION_NOISE else 1.0) for k, v in rel.items()}
    out.update({k: float(v) for k, v in (overrides or {}).items()})
    return out


STATUSES = ("init", "tracking", "lost")


@dataclass(frozen=True)
class TrackerParams:
    """How the tracker runs. ``motion_noise`` overrides the model's default noise, in mesh units
    (:func:`motion_noise`).

    No default carries a length: pixel quantities are for the image as given (measurement
    noise and gates of image features), 3-D quantities are fractions of the object's diameter.
    """

    motion_model: str = "ude"
    motion_noise: dict = field(default_factory=dict)
    sigma_px: float = 0.7  # standard deviation of a KLT measurement
    gate_chi2: float = 13.8  # Mahalanobis gate on the innovation (χ²₂ at 99.9 %)
    outlier_px: float = 3.0  # posterior residual beyond which a point is an outlier
    max_points: int = 200  # tracked points at most
    min_points: int = 120  # below this, replenish from the model
    refresh_every: int = 10  # frames between SIFT re-anchorings (0: only when thin)
    # Live streams (the service) re-anchor on the window shrunk to 320 px with its 400 strongest
    # SIFT features: 45 → 32 ms per refresh; offline, full resolution and all features keep the
    # rendered benchmark's error at 0.27 % instead of ~0.35 %. None = no limit.
    anchor_max_side: int | None = None
    anchor_max_features: int | None = None
    # Live streams: re-anchoring runs in a background thread beside the next frames' steps, so
    # no frame waits for SIFT (the service: p99 latency 65 → 34 ms at 30 fps). Offline, frames
    # come back to back, the thread only competes for the cores, and late anchors cost accuracy
    # (rendered benchmark: 0.27 → 0.41 % error, losses at 1/4 rate): off by default.
    pipelined_refresh: bool = False
    anchor_radius_px: float = 6.0  # a SIFT match must project this close (at the current pose)
    min_inliers: int = 12  # fewer agreeing points: lost
    max_rms_px: float = 2.5  # larger inlier RMS residual: lost
    max_failed_refreshes: int = 3  # consecutive refreshes finding no texture: lost
    min_anchor_matches: int = 6
    initial_sigma_p: float = 0.01  # × extent, for init_pose without a covariance
    initial_sigma_deg: float = 2.0
    klt: KLTParams = field(default_factory=KLTParams)
    visibility: VisibilityParams = field(default_factory=VisibilityParams)
    locate: LocateParams = field(default_factory=LocateParams)
    adjust: AdjustOptions = field(
        # Gauss–Newton from the prediction converges in 2–3 steps here; 4 is a measured margin.
        # The stop rule ‖∇F‖ < ε mixes 1/length (position) and 1/rad terms, so ε is tiny: the
        # iterations stop at convergence, not earlier in one mesh unit than in another.
        default_factory=lambda: AdjustOptions(method="gauss-newton", robust="huber", max_iterations=4,
                                              gradient_tolerance=1e-7)
    )

    def __post_init__(self) -> None:
        noise = DEFAULT_MOTION_NOISE.get(self.motion_model)
        if noise is None:
            raise ValueError(f"unknown motion model {self.motion_model!r}; expected one of {sorted(DEFAULT_MOTION_NOISE)}")
        unknown = set(self.motion_noise) - set(noise)
        if unknown:
            raise ValueError(f"motion model {self.motion_model!r} has no parameter(s) {sorted(unknown)}; "
                             f"expected {sorted(noise)}")

    def noise(self, diameter: float) -> dict[str, float]:
        """The motion model's noise parameters (mesh units) for an object of this diameter."""
        return motion_noise(self.motion_model, diameter, self.motion_noise)


@dataclass
class TrackStep:
    """One frame's answer. Pose object → camera (``t`` mesh units, ``q_wxyz`` with w ≥ 0),
    ``v`` mesh units/s and ``omega`` rad/s in the camera frame; ``covariance`` 6×6 over
    ``[p, δθ]``. Pose fields are None when ``status`` is ``lost``."""

    frame: int
    time_s: float
    status: str  # "init" | "tracking" | "lost"
    t: np.ndarray | None = None
    q_wxyz: np.ndarray | None = None
    v: np.ndarray | None = None
    omega: np.ndarray | None = None
    covariance: np.ndarray | None = None
    inliers: int = 0
    timings_ms: dict = field(default_factory=dict)
    reason: str | None = None  # why lost (or how initialised)

    @property
    def has_pose(self) -> bool:
        return self.status != "lost"


@dataclass
class _Tracks:
    """Tracked model points: object-frame points (n, 3) and their pixels in the last frame (n, 2)."""

    X: np.ndarray
    uv: np.ndarray

    @classmethod
    def empty(cls) -> "_Tracks":
        return cls(np.zeros((0, 3)), np.zeros((0, 2)))

    def __len__(self) -> int:
        return len(self.X)

    def keep(self, mask: np.ndarray) -> "_Tracks":
        return _Tracks(self.X[mask], self.uv[mask])


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def _check_pose(t, q) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, float).reshape(3)
    q = np.asarray(q, float).reshape(4)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise ValueError("the pose must be finite")
    nq = np.linalg.norm(q)
    if not nq > 1e-9:
        raise ValueError("the quaternion must not be zero")
    return t, q / nq


class Tracker:
    """Tracks one object in the frames of one camera; not thread-safe (one per video stream)."""

    def __init__(self, model: ObjectModel, camera: PinholeCamera, params: TrackerParams = TrackerParams(),
                 index: ModelIndex | None = None) -> None:
        self.model = model
        self.camera = camera
        self.params = params
        self.index = index
        self.motion = make_motion_model(params.motion_model, **params.noise(model.mesh.extent))
        self.filter = PoseFilter(self.motion, params.adjust)
        pts = np.concatenate([vs.points3d for vs in model.viewsets]) if model.viewsets else np.zeros((0, 3))
        self.points = merge_points(pts, 0.005 * model.mesh.extent)
        self._frame = -1
        self._pending: tuple[np.ndarray, np.ndarray, float | None] | None = None
        self.reset()
        if params.pipelined_refresh and params.refresh_every:
            _anchor_pool().submit(lambda: self._index()._matcher())  # warm the anchor thread's index

    # -- public -------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the state: the next frame re-initialises (by recognition)."""
        self.filter.state = None
        self.filter.prior = None
        self._tracks = _Tracks.empty()
        self._prev: Frame | None = None
        self._since_refresh = 0
        self._failed_refreshes = 0
        self._pending = None
        self._anchor_job: tuple[Future, Pose, Frame] | None = None  # SIFT + matching of an earlier frame

    def init_pose(self, t, q_wxyz, time_s: float | None = None) -> None:
        """Start from a user-given pose (object → camera) at the next frame (or at ``time_s``)."""
        t, q = _check_pose(t, q_wxyz)
        self.reset()
        self._pending = (t, q, None if time_s is None else float(time_s))

    @property
    def tracking(self) -> bool:
        return self.filter.state is not None

    def step(self, image: np.ndarray, time_s: float) -> TrackStep:
        """Process one frame taken at ``time_s`` (seconds, non-decreasing)."""
        t_start = time.perf_counter()
        time_s = float(time_s)
        if not np.isfinite(time_s):
            raise ValueError("time_s must be finite")
        img = to_bgr8(image)
        h, w = img.shape[:2]
        cam = self.camera
        if cam.width is not None and cam.height is not None and (cam.width, cam.height) != (w, h):
            raise ImageError(f"the camera is for {cam.width}×{cam.height} px images but the frame is {w}×{h} px")
        if cam.width is None or cam.height is None:
            from dataclasses import replace

            self.camera = cam = replace(cam, width=w, height=h)
        state = self.filter.state
        if state is not None and time_s < state.t:
            raise ValueError(f"time goes backwards ({time_s} s after {state.t} s)")
        self._frame += 1
        timings: dict[str, float] = {}
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        pyr = make_frame(gray)
        if self.filter.state is None:
            step = self._initialise(img, pyr, time_s, timings)
        else:
            step = self._track(img, pyr, time_s, timings)
        self._prev = pyr if step.status != "lost" else None
        timings["total"] = _ms(t_start)
        step.timings_ms = timings
        return step

    # -- internals ----------------------------------------------------------------------------
    def _index(self) -> ModelIndex:
        if self.index is None:
            self.index = index_for(self.model)
        return self.index

    def _lost(self, time_s: float, reason: str, inliers: int = 0) -> TrackStep:
        pending = self._pending
        self.reset()
        self._pending = pending
        return TrackStep(self._frame, time_s, "lost", inliers=inliers, reason=reason)

    def _pose_step(self, time_s: float, status: str, inliers: int, reason: str | None = None) -> TrackStep:
        s = self.filter.state
        q = quat.canonical(s.q)
        return TrackStep(self._frame, time_s, status, s.p.copy(), q, s.v.copy(), s.omega.copy(),
                         s.pose_covariance.copy(), inliers, reason=reason)

    def _initial_covariance(self) -> np.ndarray:
        sp = self.params.initial_sigma_p * self.model.mesh.extent
        sa = np.radians(self.params.initial_sigma_deg)
        return np.diag([sp**2] * 3 + [sa**2] * 3)

    def _unknown_velocity(self) -> None:
        """Velocity variances in the object's scale (see :data:`INITIAL_VELOCITY_SIGMA`)."""
        if self.motion.estimates_velocity:
            s = INITIAL_VELOCITY_SIGMA
            cov = self.filter.state.covariance
            cov[6:9, 6:9] = (s * self.model.mesh.extent) ** 2 * np.eye(3)
            cov[9:12, 9:12] = s**2 * np.eye(3)

    def _initialise(self, img: np.ndarray, pyr: Frame, time_s: float, timings: dict) -> TrackStep:
        """No state: the user's pose or recognition; then anchor model points and refine."""
        if self._pending is not None:
            t, q, t_given = self._pending
            self._pending = None
            cov, how = self._initial_covariance(), "given pose"
            if t_given is not None and t_given > time_s:
                time_s0 = time_s
            else:
                time_s0 = time_s if t_given is None else t_given
        else:
            t0 = time.perf_counter()
            loc = locate(img, self.camera, self.model, self.params.locate, index=self._index())
            timings["locate"] = _ms(t0)
            if not loc.found:
                return self._lost(time_s, f"not found: {loc.reason}")
            t, q, cov, how, time_s0 = loc.t, loc.q_wxyz, loc.covariance, "recognition", time_s
            cov = 0.5 * (cov + cov.T) + 1e-9 * np.eye(6)
        self.filter.initialize(time_s0, Pose(q, t), cov)
        self._unknown_velocity()
        self.filter.predict(time_s)
        t0 = time.perf_counter()
        tracks, n_matches, _ = self._anchor(img, _Tracks.empty(), wide=True)
        timings["replenish"] = _ms(t0)
        if len(tracks) < self.params.min_inliers:
            return self._lost(time_s, f"{how}: only {len(tracks)} model points matched near the pose")
        t0 = time.perf_counter()
        ok, why, inliers = self._adjust(tracks)
        timings["adjust"] = _ms(t0)
        if not ok:
            return self._lost(time_s, f"{how}: {why}", inliers)
        self._tracks = tracks.keep(self._last_inliers)
        self._since_refresh = 0
        return self._pose_step(time_s, "init", inliers, reason=how)

    def _pose(self, state=None) -> Pose:
        s = state or self.filter.state
        return s.pose

    def _track(self, img: np.ndarray, pyr: Frame, time_s: float, timings: dict) -> TrackStep:
        p = self.params
        t0 = time.perf_counter()
        self._pose_before_predict = self._pose(self.filter.state)  # the previous frame's posterior
        prior = self.filter.predict(time_s)
        timings["predict"] = _ms(t0)
        why = self._implausible(prior)
        if why:
            return self._lost(time_s, f"prediction {why}")

        if self._anchor_job is not None and self._anchor_job[0].done():
            # a re-anchoring run in the background on an earlier frame: its matches join the
            # tracks, which live in the previous frame, where KLT starts from
            t0 = time.perf_counter()
            fut, pose_then, pyr_then = self._anchor_job
            self._anchor_job = None
            feats, m = fut.result()
            if pyr_then is not self._prev:  # found on an older frame: carry the keypoints over
                feats, m, pose_then = self._carry(feats, m, pyr_then)
            self._tracks, n_matches, _ = self._anchor_merge(feats, m, pose_then, self._tracks, wide=False)
            self._count_refresh(n_matches)
            timings["replenish"] = _ms(t0)
            if self._failed_refreshes >= p.max_failed_refreshes:
                return self._lost(time_s, "the object's texture is no longer found where it is tracked")

        t0 = time.perf_counter()
        tracks = self._tracks
        vis, uv_pred = visible_points(self.model.mesh, self.camera, self._pose(prior), tracks.X, p.visibility)
        tracks, uv_pred = tracks.keep(vis), uv_pred[vis]
        timings["visibility"] = _ms(t0)
        t1 = time.perf_counter()
        new_uv, ok, _ = track_points(self._prev, pyr, tracks.uv, uv_pred, p.klt)
        timings["klt"] = _ms(t1)
        tracks = _Tracks(tracks.X[ok], new_uv[ok])
        gate = self._gate(tracks, prior)
        if gate.sum() >= p.min_inliers:
            tracks = tracks.keep(gate)
        timings["measure"] = _ms(t0)  # visibility + KLT + gating
        if len(tracks) < p.min_inliers:
            return self._lost(time_s, f"only {len(tracks)} points tracked", len(tracks))

        t0 = time.perf_counter()
        good, why, inliers = self._adjust(tracks)
        timings["adjust"] = _ms(t0)
        if not good:
            return self._lost(time_s, why, inliers)
        why = self._implausible(self.filter.state)
        if why:
            return self._lost(time_s, f"pose {why}", inliers)
        self._tracks = tracks.keep(self._last_inliers)

        self._since_refresh += 1
        thin = len(self._tracks) < p.min_points
        due = p.refresh_every and self._since_refresh >= p.refresh_every
        scarce = len(self._tracks) < 2 * p.min_inliers  # too few to wait for the background
        if (due or thin) and not scarce and p.pipelined_refresh:
            if self._anchor_job is None:  # (one at a time: a busy anchor thread is not queued up)
                job = self._anchor_features_job(img, pyr)
                if job is not None:
                    self._anchor_job = job
                    self._since_refresh = 0
        elif thin or due:
            t0 = time.perf_counter()
            self._tracks, n_matches, replaced = self._anchor(img, self._tracks, wide=False)
            if replaced:  # the KLT tracks had slid: adjust this frame again to the fresh matches
                good, why, inliers = self._adjust(self._tracks)
                if not good:
                    timings["replenish"] = _ms(t0)
                    return self._lost(time_s, f"re-anchoring: {why}", inliers)
                self._tracks = self._tracks.keep(self._last_inliers)
            timings["replenish"] = _ms(t0)
            self._since_refresh = 0
            self._count_refresh(n_matches)
            if self._failed_refreshes >= p.max_failed_refreshes:
                return self._lost(time_s, "the object's texture is no longer found where it is tracked", inliers)
        return self._pose_step(time_s, "tracking", inliers)

    def _implausible(self, state) -> str | None:
        """Why a pose cannot be the object's (None if it can)."""
        mesh = self.model.mesh
        c = state.R @ mesh.centre + state.p
        if not np.all(np.isfinite(c)) or c[2] < 0.5 * mesh.extent:
            return "puts the object behind or at the camera"
        uv = self.camera.project(c[None])[0]
        w, h = self.camera.width, self.camera.height
        if not (-0.25 * w < uv[0] < 1.25 * w and -0.25 * h < uv[1] < 1.25 * h):
            return "puts the object out of the image"
        return None

    def _gate(self, tracks: _Tracks, prior) -> np.ndarray:
        """Innovation gate: ``rᵀ (J P Jᵀ + σ² I)⁻¹ r < χ²`` per point, at the prediction."""
        if len(tracks) == 0:
            return np.zeros(0, bool)
        uv, J = project_model_points(self.camera, tracks.X, prior.p, prior.R, True)
        r = tracks.uv - uv
        S = J @ prior.pose_covariance @ np.swapaxes(J, 1, 2) + self.params.sigma_px**2 * np.eye(2)
        a, b, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
        det = a * d - b * b
        m2 = (d * r[:, 0] ** 2 - 2 * b * r[:, 0] * r[:, 1] + a * r[:, 1] ** 2) / det
        return m2 < self.params.gate_chi2

    def _adjust(self, tracks: _Tracks) -> tuple[bool, str | None, int]:
        """Adjust the prior to the points; redo without the outliers. Sets ``_last_inliers``."""
        p = self.params
        self._last_inliers = np.zeros(len(tracks), bool)
        keep = np.ones(len(tracks), bool)
        for _ in range(2):
            if keep.sum() < p.min_inliers:
                return False, f"only {int(keep.sum())} points agree", int(keep.sum())
            meas = PointMeasurements.create(self.camera, tracks.X[keep], tracks.uv[keep], p.sigma_px)
            try:
                result = self.filter.update([meas])
            except (SingularProblemError, np.linalg.LinAlgError):
                return False, "the points do not determine the pose", int(keep.sum())
            s = result.state
            uv, _ = project_model_points(self.camera, tracks.X, s.p, s.R, False)
            err = np.linalg.norm(uv - tracks.uv, axis=1)
            inl = err < p.outlier_px
            if np.array_equal(inl, keep) or inl.sum() < p.min_inliers:
                break
            keep = inl
        n = int(inl.sum())
        self._last_inliers = inl
        if n < p.min_inliers:
            return False, f"only {n} points agree", n
        rms = float(np.sqrt(np.mean(err[inl] ** 2)))
        if rms > p.max_rms_px:
            return False, f"residuals too large (RMS {rms:.1f} px)", n
        if not np.all(np.isfinite(s.covariance[:6, :6])):
            return False, "the pose covariance is not finite", n
        return True, None, n

    def _window(self, pose: Pose, margin: float = 0.15) -> tuple[int, int, int, int] | None:
        """Pixel box (x0, y0, x1, y1) of the projected mesh, enlarged by ``margin``."""
        Xc = pose.apply(self.model.mesh.vertices)
        if np.any(Xc[:, 2] <= 0):
            return None
        uv = self.camera.project(Xc)
        x0, y0 = uv.min(axis=0)
        x1, y1 = uv.max(axis=0)
        mx, my = margin * (x1 - x0), margin * (y1 - y0)
        w, h = self.camera.width, self.camera.height
        box = (int(max(0, x0 - mx)), int(max(0, y0 - my)), int(min(w, x1 + mx + 1)), int(min(h, y1 + my + 1)))
        if box[2] - box[0] < 16 or box[3] - box[1] < 16:
            return None
        return box

    def _count_refresh(self, n_matches: int) -> None:
        ok = n_matches >= self.params.min_anchor_matches
        self._failed_refreshes = 0 if ok else self._failed_refreshes + 1

    def _anchor_features(self, img: np.ndarray, box) -> tuple:
        """SIFT in ``box`` and its matches to the model: the costly half of re-anchoring."""
        p = self.params
        index = self._index()
        feats = index.describe(img, box, max_side=p.anchor_max_side, max_features=p.anchor_max_features)
        return feats, index.match(feats)

    def _carry(self, feats, m, pyr_then: Frame):
        """Keypoints found on an older frame, tracked by KLT into the previous frame (which the
        next KLT step starts from); those that do not follow are dropped with their matches."""
        kp = feats.keypoints[m.query_idx].astype(np.float64)
        pose_prev = self._pose_before_predict  # the previous frame's posterior
        guess = self.camera.project(pose_prev.apply(np.asarray(m.points3d, float)))
        moved, ok, _ = track_points(pyr_then, self._prev, kp, guess, self.params.klt)
        keep = np.flatnonzero(ok)
        kp_new = np.zeros_like(feats.keypoints)
        kp_new[m.query_idx[keep]] = moved[keep]
        feats = type(feats)(kp_new.astype(np.float32), feats.descriptors, feats.sizes, feats.angles)
        return feats, m.subset(keep), pose_prev

    def _anchor_features_job(self, img: np.ndarray, pyr: Frame) -> tuple[Future, Pose, Frame] | None:
        """Start the costly half on the anchor thread, for the frame ``img`` at the current pose."""
        pose = self._pose(self.filter.state)
        box = self._window(pose, 0.15)
        if box is None:
            return None
        crop = np.ascontiguousarray(img[box[1] : box[3], box[0] : box[2]])
        shifted = (0, 0, box[2] - box[0], box[3] - box[1])

        def work():
            feats, m = self._anchor_features(crop, shifted)
            kp = feats.keypoints + np.array([box[0], box[1]], np.float32)
            return type(feats)(kp, feats.descriptors, feats.sizes, feats.angles), m

        return _anchor_pool().submit(work), pose, pyr

    def _anchor(self, img: np.ndarray, tracks: _Tracks, wide: bool) -> tuple[_Tracks, int, bool]:
        """Re-anchor to the model now: SIFT in the object's window, matched to the viewsets,
        made consistent by :meth:`_anchor_merge`."""
        pose = self._pose(self.filter.state)
        box = self._window(pose, 0.3 if wide else 0.15)
        if box is None:
            return tracks, 0, False
        feats, m = self._anchor_features(img, box)
        return self._anchor_merge(feats, m, pose, tracks, wide)

    def _anchor_merge(self, feats, m, pose: Pose, tracks: _Tracks, wide: bool) -> tuple[_Tracks, int, bool]:
        """Make SIFT matches consistent by RANSAC PnP started at ``pose`` (the pose of the frame
        they were found in) and merge them into ``tracks``.

        Returns ``(tracks, consistent matches, replaced)``. Fresh matches are exact
        correspondences, so they replace tracks within 3 px of them; if the pose disagrees with
        them (median reprojection > ``anchor_radius_px / 2``) while they are many, the KLT
        tracks have slid (occlusion, drift) and are all replaced (``replaced``).
        """
        p = self.params
        if len(m) < max(p.min_anchor_matches, 6):
            return tracks, 0, False
        kp = feats.keypoints[m.query_idx].astype(np.float64)
        X = np.asarray(m.points3d, np.float64)
        cam = self.camera
        # OpenCV's PnP stops on absolute tolerances: it is given lengths in diameters, so that
        # the same scene in mm, cm or m gives the same consensus
        d = self.model.mesh.extent
        rvec0 = cv2.Rodrigues(pose.R)[0]
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X / d, kp, cam.matrix, cam.dist_coeffs, rvec0.copy(), pose.t.reshape(3, 1) / d, useExtrinsicGuess=True,
            iterationsCount=100, reprojectionError=3.0, confidence=0.99, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or inl is None or len(inl) < p.min_anchor_matches:
            return tracks, 0, False
        inl = inl.ravel()
        pnp = Pose.from_rvec(rvec, tvec * d)
        vis, _ = visible_points(self.model.mesh, cam, pnp, X[inl], p.visibility)
        X, kp = X[inl][vis], kp[inl][vis]
        if len(X) < p.min_anchor_matches:
            return tracks, 0, False
        uv_cur = cam.project(pose.apply(X))
        disagree = float(np.median(np.linalg.norm(uv_cur - kp, axis=1))) > 0.5 * p.anchor_radius_px
        replaced = disagree and len(X) >= 2 * p.min_inliers and not wide
        if len(tracks) and not replaced:
            d = np.linalg.norm(tracks.uv[:, None, :] - kp[None, :, :], axis=2)
            tracks = tracks.keep(d.min(axis=1) > 3.0)
        elif replaced:
            tracks = _Tracks.empty()
        merged = _Tracks(np.concatenate([X, tracks.X]), np.concatenate([kp, tracks.uv]))
        return merged.keep(np.arange(len(merged)) < p.max_points), len(X), replaced

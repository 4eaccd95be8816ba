"""What the tracker is told (:class:`TrackerParams`) and what it answers (:class:`TrackStep`).

No default carries a length: pixel quantities are for the image as given (noise, gates and
windows of image measurements); 3-D quantities are fractions of the object's diameter (the
bounding-box diagonal, :attr:`~quatrack.viewsets.mesh.Mesh.extent`), so a mesh in mm, cm or m,
a die or a car, gives the same track up to the unit (tests/test_tracker_units.py).
"""

from __future__ import annotations

import types
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from quatrack.tracking.adjust import AdjustOptions
from quatrack.tracking.pose import Pose

from ..fields import check_field_kinds, is_number
from ..klt import KLTParams
from ..locate import LocateParams
from ..pose import PoseParams, value_key
from ..visibility import VisibilityParams

__all__ = ["TrackerParams", "TrackStep", "motion_noise", "noise_defaults", "DEFAULT_MOTION_NOISE", "MAX_MOTION_NOISE", "STATUSES",
           "INITIAL_VELOCITY_SIGMA"]

# Plant noise per motion model, free of units: translation terms are per diameter² of the object,
# rotation terms in rad². A noise in diameters moves the object's image by the same share of its
# apparent size whatever the mesh unit, the object's size, its distance or the focal length.
# ude/m3 are random accelerations (diameters²/s³, rad²/s³), m1/m2 random walks (diameters²/s,
# rad²/s). (Measured on the 32.8 cm cookie box, hand-held: a = 2000 cm²/s³ = 1.85 diameters²/s³.)
DEFAULT_MOTION_NOISE: dict[str, dict[str, float]] = {
    "ude": {"a": 1.85, "alpha": 20.0},
    "m3": {"sigma_p2": 1.85, "sigma_phi2": 20.0},
    "m1": {"sigma_p2": 0.093, "sigma_phi2": 0.3},
    "m2": {"sigma_p2": 0.093, "sigma_phi2": 0.3},
}
_TRANSLATION_NOISE = {"a", "sigma_p2"}  # the terms in length², scaled by the diameter²
# The largest noise value taken (mesh units² or rad², per s or s³): the filter's covariances are
# multiplied together, and from about 1e154 (the square root of the largest float) numpy's
# "overflow encountered in multiply" came out on every frame. 1e100 leaves a margin of 1e54 for
# the time steps (dt³) and the products, and is beyond any noise in any unit (the defaults are
# ~2 diameters²/s³ and 20 rad²/s³: 2000 cm²/s³ for a 33 cm box).
MAX_MOTION_NOISE = 1e100
# Velocities start unknown: standard deviation 100 diameters/s and 100 rad/s (Ude's 1e8 variance
# was in his units; in diameters it is the same "unknown" for every mesh unit).
INITIAL_VELOCITY_SIGMA = 100.0

STATUSES = ("init", "tracking", "lost")

# TrackerParams' fields holding settings objects, by their annotation (TrackerParams._check_kinds)
_SETTINGS = {"KLTParams": KLTParams, "VisibilityParams": VisibilityParams, "LocateParams": LocateParams,
             "AdjustOptions": AdjustOptions}


def motion_noise(motion_model: str, diameter: float, overrides: dict | None = None) -> dict[str, float]:
    """The motion model's noise in mesh units: :data:`DEFAULT_MOTION_NOISE` with its translation
    terms times ``diameter²``, overridden by ``overrides`` (given in mesh units, as the CLI's
    ``--motion-noise``)."""
    rel = DEFAULT_MOTION_NOISE[motion_model]
    out = {k: v * (diameter**2 if k in _TRANSLATION_NOISE else 1.0) for k, v in rel.items()}
    out.update({k: float(v) for k, v in (overrides or {}).items()})
    return out


def noise_defaults(motion_model: str) -> str:
    """The motion model's default noise in words, for messages: ``ude's defaults: a = 1.85 ×
    the object's diameter², alpha = 20``."""
    rel = DEFAULT_MOTION_NOISE[motion_model]
    return f"{motion_model}'s defaults: " + ", ".join(
        f"{k} = {v:g}" + (" × the object's diameter²" if k in _TRANSLATION_NOISE else "") for k, v in rel.items())


class _defaults_on_class:
    """A method that, called on the class, runs on its defaults: ``TrackerParams.for_live_streams()``,
    as the README and the contract write it (it raised "missing 1 required positional argument:
    'self'"), is ``TrackerParams().for_live_streams()``."""

    def __init__(self, f) -> None:
        self.f = f
        self.__doc__ = f.__doc__

    def __get__(self, obj, cls=None):
        return types.MethodType(self.f, cls() if obj is None else obj)


@dataclass(frozen=True)
class TrackerParams:
    """How the tracker runs. ``motion_noise`` overrides the model's default noise, in mesh units
    (:func:`motion_noise`). Pixel quantities are for the image as given; 3-D ones × diameter."""

    motion_model: str = "ude"
    motion_noise: dict = field(default_factory=dict)
    sigma_px: float = 0.7  # standard deviation of a KLT measurement
    gate_chi2: float = 13.8  # Mahalanobis gate on the innovation (χ²₂ at 99.9 %)
    outlier_px: float = 3.0  # posterior residual (at sigma_px; Mahalanobis beyond) of an outlier
    max_points: int = 200  # tracked model points at most
    min_points: int = 120  # below this, replenish from the model
    refresh_every: int = 10  # frames between SIFT re-anchorings (0: only when thin)
    # Live streams (the service) re-anchor on the window shrunk to 320 px with its 400 strongest
    # SIFT features: 45 → 32 ms per refresh; offline, full resolution and all features keep the
    # rendered benchmark's error at 0.27 % instead of ~0.35 %. None = no limit.
    anchor_max_side: int | None = None
    anchor_max_features: int | None = None
    # Live streams: re-anchoring runs on the caller's executor beside the next frames' steps, so
    # no frame waits for SIFT (the service: p99 latency 65 → 34 ms at 30 fps). Offline, frames
    # come back to back, the thread only competes for the cores, and late anchors cost accuracy
    # (rendered benchmark: 0.27 → 0.41 % error, losses at 1/4 rate): off by default. Without an
    # executor given to the tracker, re-anchoring runs in the step whatever this says.
    pipelined_refresh: bool = False
    anchor_radius_px: float = 6.0  # a SIFT match must project this close (at the current pose)
    min_inliers: int = 12  # fewer agreeing points: lost
    max_rms_px: float = 2.5  # larger inlier RMS residual: lost
    max_failed_refreshes: int = 3  # consecutive refreshes finding no texture: lost
    min_anchor_matches: int = 6
    merge_tol: float = 0.005  # × diameter: the viewsets' 3-D points closer than this are one point
    min_depth: float = 0.5  # × diameter: the object's centre nearer the camera is implausible
    min_inside: float = 0.2  # a tracked pose with less of its silhouette inside the image is lost
    # measurement sources (recognition/tracker/sources.py): "trained" (the viewsets' points, the
    # anchors), "mesh" (corners born on the mesh at the current pose: recognition/tracker/mesh_points.py),
    # "edges" (sharp model edges searched along their normals: recognition/tracker/edges.py),
    # "contour" (the outline located by colour statistics: recognition/tracker/contour.py)
    sources: tuple[str, ...] = ("trained", "mesh", "edges", "contour")
    mesh_max_points: int = 100
    mesh_spawn_every: int = 5  # frames between births
    mesh_spawn_sigma_p: float = 0.01  # births only when the pose's 1-σ error is below (× diameter)
    mesh_spawn_sigma_deg: float = 1.0  # … and below this rotation
    mesh_min_distance_px: float = 10.0  # between corners (and from every tracked mesh point)
    mesh_quality: float = 0.01  # goodFeaturesToTrack's quality level
    mesh_edge_margin_px: float = 8.0  # corners this far from silhouette and depth edges at least
    mesh_retire_px: float = 1.5  # a point whose average posterior residual exceeds this retires
    edge_crease_deg: float = 30.0  # "edges": faces meeting at more than this make a sharp edge
    edge_step_px: float = 6.0  # sample spacing along projected edges
    edge_sigma_px: float = 1.0  # standard deviation across the edge
    edge_min_grad: float = 6.0  # grey levels per pixel (Sobel /8 of the σ = 1 blurred image)
    # a sample whose search finds a second aligned gradient maximum (> 2 px from the strongest)
    # this strong is dropped: a crease beside a parallel line of the print (edges.edge_candidates;
    # None: the strongest is taken whatever else is in reach)
    edge_ambiguity: float | None = 0.5
    # "contour": the object's outline located by colour statistics along lines across it
    # (recognition/tracker/contour.py, after SRT3D): a line every contour_step_px of the outline,
    # searching ± 3σ of the prediction (at most contour_max_reach_px) with contour_margin_px more
    # read beyond; smoothed step functions of amplitude contour_alpha and slope contour_slope_px
    # (SRT3D's 0.43 and 1.3); at least contour_sigma_min_px across; colour histograms learned at
    # the rates contour_rate_f (object) and contour_rate_b (surroundings) per frame
    contour_step_px: float = 8.0
    contour_max_reach_px: float = 20.0
    contour_margin_px: float = 8.0
    contour_alpha: float = 0.43
    contour_slope_px: float = 1.3
    contour_sigma_min_px: float = 0.5
    contour_rate_f: float = 0.1
    contour_rate_b: float = 0.2
    # read the outline's pixels relative to the frame's mean colour (contour.frame_gains), so that
    # a change of light keeps the learned colours valid. Off: on the zoo walks it kept a wide box
    # tracked through the dimming (137 → 72 frames lost) whose unanchored track then drifted past
    # 5 % in the blur (bench/RESULTS.md, session 33): it waits on a judge of such tracks
    contour_normalise: bool = False
    # the outline's sources (edges, contour) search around the points' own pose when that moves
    # the mesh's vertices by more than recentre_px from the prediction (Tracker._recentred; 0: never)
    recentre_px: float = 3.0
    # views learned while tracking (quatrack.viewsets.learn; Tracker.learned_viewsets()): when the
    # pose is confident (1-σ below learn_sigma_p × diameter and learn_sigma_deg), at least
    # learn_min_inliers textured points agree and are learn_min_share of those measured (nothing
    # covers the object), and the model's edges agree (recognition.evidence.edge_agreement), the
    # frame's SIFT keypoints on the visible faces become a learned viewset, if it sees the object
    # from ≥ learn_min_angle_deg away from every viewset so far; at most learn_max_views per model;
    # an attempt (SIFT + lifting) at most every learn_every frames
    learn: bool = False
    learn_max_views: int = 24
    learn_min_angle_deg: float = 25.0
    learn_sigma_p: float = 0.005  # × diameter
    learn_sigma_deg: float = 0.5
    learn_min_inliers: int = 30
    learn_min_share: float = 0.8
    learn_min_keypoints: int = 30  # lifted keypoints a learned view needs
    learn_min_cos: float = 0.4  # its points' rays meet their faces within ~66° of the normal
    learn_every: int = 5
    learn_after: int = 5  # frames of tracking before the first (the velocities settle)
    # keyframes (recognition/tracker/keyframes.py): while the pose is confident (mesh_spawn_sigma_p/
    # _deg), learn_min_inliers textured points agree and are learn_min_share of those measured,
    # and the model's edges agree, every keyframe_every frames the frame's lifted SIFT keypoints
    # are kept in memory, one per keyframe_min_angle_deg of viewing direction (the nearest renewed
    # after keyframe_renew_s), at most keyframes_max (0: none); after a loss, recognition searches
    # them with the model's views
    keyframes_max: int = 24
    # re-anchoring (SIFT) falls back on the keyframes where the model's views give fewer than
    # min_anchor_matches consistent matches (a side no trained or learned view shows): the points
    # the tracker itself saw there become anchors too. Zoo truth passes (bench/RESULTS.md, session
    # 22): poses beyond 5 %/5° 10 → 2, mean error 0.51 → 0.39 % of the diameter; losses ±7 frames
    anchor_keyframes: bool = True
    anchor_keyframe_max_deg: float = 20.0  # only keyframes seen from this near the current direction
    keyframe_min_angle_deg: float = 15.0
    keyframe_renew_s: float = 3.0
    keyframe_every: int = 10
    # after a loss, each keyframe gains synthetic views: its crop re-rendered on the mesh at its
    # pose turned by ± each of these angles about the camera's x and y axes (keyframes.py; () none),
    # made for at most keyframe_synthetic_per_frame keyframes per lost frame (~15 ms per view).
    # Zoo walks (bench/RESULTS.md, session 26): re-found after the slide out of the frame on the
    # sides seen before it
    keyframe_synthetic_deg: tuple[float, ...] = (20.0, 40.0)
    keyframe_synthetic_per_frame: int = 2
    # a face of the crop is textured in a synthetic view where the crop sees it at |cos| ≥
    # keyframe_synthetic_min_cos: the views stay within 40° of the keyframe, where a face it saw
    # obliquely is seen about as obliquely (training's 0.3 dropped the zoo flat box's large face,
    # seen at cos 0.3 from below, from every view near that one: nothing re-found it after the slide)
    keyframe_synthetic_min_cos: float = 0.1
    # a pose found after a loss (recognition, or re-found on keyframes) must look, where the
    # keyframes saw the object, as it looked then: their crops rendered at the pose correlate
    # with the frame at least this well (recognition/appearance.py: the median NCC of blocks;
    # ~1 right, ~0 another face's texture, e.g. the same outline turned by a symmetry). It does
    # not catch texture that truly repeats (a zoo walk's cube re-found 90° off reads 0.98: the
    # matched face carries the pixels of the face it is taken for). 0: off
    refind_min_texture_ncc: float = 0.5
    # ... and every frame that no trained point anchors, or of a track re-found on keyframes, must
    # pass the same test, else its pose is withheld (Tracker._texture_audit). Live streams only
    # (for_live_streams): there re-anchoring comes two frames late and such tracks drifted in
    # depth past 5 % (bench/RESULTS.md, sessions 35 and 37); offline no pose got that far
    audit_texture: bool = False
    # ... and, in those frames, the keyframes' texture rendered at the pose is followed into the
    # frame and the pose solved there (recognition/appearance.py: texture_refit); where that pose
    # lies more than texture_refit_shift of the 5 %/5° criterion away, on at least
    # texture_refit_min_inliers points, and the texture correlates better there by at least
    # texture_refit_gain, the pose is withheld: points born on the mesh at a drifting pose, and
    # the edge refit that includes them, agreed with a flat box drifting to 5.4 % in depth
    # (bench/RESULTS.md, session 49). Only a pose whose texture correlates below 1 − gain is
    # refitted (no other could gain that much), every texture_refit_every-th tracked frame (it
    # costs ~5–9 ms; 2 let a pose 9 % off through under a passing hand, in the frame it
    # skipped), and every frame of a track on probation or in doubt. 15 points, not 40: that
    # hand left 19 (the refit put the object 1.3 % from the truth there). 0: off
    texture_refit_shift: float = 0.6
    texture_refit_min_inliers: int = 15
    texture_refit_gain: float = 0.03
    texture_refit_every: int = 1
    # ... and the track goes on from the refit's pose, its mesh points lifted again there
    # (MeshPoints.relift), in doubt (the edges must confirm it, strictly, before it is reported):
    # withheld only, the drift went on and the track was lost a few frames later; 24 live walks,
    # lost while ≥ 30 % visible 2239 → 2224, none beyond 5 %/5° (bench/RESULTS.md, session 49)
    texture_refit_restart: bool = True
    # ... and where the trained points are fewer than min_inliers and the refit leaves the pose
    # (it does not withhold it), the refit's consensus becomes the trained source's tracks:
    # points on the mesh where the keyframes saw that texture, matched to where this frame shows
    # it — anchors from this run's first-hand views, followed by KLT and measured like trained
    # points from the next frame on. They never count as anchoring a frame
    # (Tracker._keyframe_anchors): every judge stays as for a frame no trained point anchors.
    # Why: a track on sides no photo shows has only points born on the mesh at its own poses,
    # which drift with it (zoo flat box #11: 2.3–4.1 % off for 20 frames while the refit put the
    # object 0.4–1.5 % from the truth). 24 live walks: frames lost while ≥ 30 % visible
    # 2224 → 2060, none beyond 5 %/5°; the frames tracked before are as accurate as before
    # (bench/RESULTS.md, session 50)
    texture_anchors: bool = True
    # a track re-found on this run's keyframes keeps no keyframe nor learned view of its own while
    # no trained point anchors its frame (FrameContext.anchored): its points were lifted at a pose
    # that inherits the keyframe's error, and a view taken from it would pass that error on again
    # (zoo cube: a keyframe taken 1.5-3 % off after a restart re-found the object 6.9 % off, 24
    # poses beyond 5 %/5°); nor is it re-acquired near its last pose after a loss (the same drift,
    # picked up again and again: 10 % in depth on the zoo's prism)
    capture_second_hand: bool = False
    # a view learned at a frame that fewer than min_inliers points of the model's own views (the
    # views the tracker was given, not this run's keyframes or learned views) anchored is relayed
    # (Viewset.relayed, stored with the model): it inherits the track's drift, so its points are
    # measured but never count as anchoring a frame (Tracker._anchoring), views learned at frames
    # they carry are relayed in turn, and a re-finding on it is second-hand. Why: on a calm orbit
    # of the zoo's cylinder each learned view anchored the next one's frame; the chain drifted
    # about the axis, which no outline shows, and 7 poses 5-11° off were reported
    # (bench/RESULTS.md, session 66). True: every learned view anchors (before session 66)
    relayed_views_anchor: bool = False
    # after a loss, for reacquire_s the tracker first tries to pick the track up again near the
    # last good pose (Tracker._reacquire: KLT from that frame, the edges confirming) before recognition
    reacquire_s: float = 2.0
    # a frame more than this many seconds after the track's latest frame ends the track and is
    # searched afresh by recognition (None: the motion model predicts across any gap). Ude's model
    # extrapolates its velocities over the gap: a clock jumping by hours moved the prediction of
    # a still object metres away (behind the camera: that frame was "lost"); a scene cut over a
    # pause is a new start anyway. A minute, not less: a time-lapse or a slow live camera (a frame
    # every 10–30 s of a still object) keeps its track and its smoothing; no frame of a video or
    # the benchmarks is that far apart
    max_gap_s: float | None = 60.0
    reacquire_min_ncc: float = 0.5  # the object's patch matched this well: start from where it went
    reacquire_min_inside: float = 0.5  # share of the silhouette inside the image a re-acquired pose needs
    # re-acquire only near a track that had run this many tracked frames before the loss: a track
    # lost within a few frames of its start was not holding (the wide box's walk, session 23: a
    # track started under a passing occluder drifted 0.2 → 2.3 % in two frames, was lost, and
    # re-acquiring near that drifted pose reported 9 % / 9°); recognition starts afresh instead
    reacquire_min_run: int = 5
    # while lost, recognition (a full ``locate`` over the model's and the keyframes' views) runs
    # at most once per this many seconds of the frames' time; the frames between are answered
    # ``lost`` at once (re-acquisition near the last pose still runs in each). None: every frame.
    # Why: a failed recognition costs 100–600 ms of CPU (the zoo's 24 live walks: frames not
    # tracked p50 142 ms, p90 331 ms, against 18 ms for a tracked one; 79 % of all their CPU), so a stream
    # whose object is out of view or unrecognisable holds a worker's core — the other streams on
    # it wait (bench/RESULTS.md, session 54). Set for a service with many streams per core; a
    # video file, where nothing waits, is best searched every frame
    relocate_interval_s: float | None = None
    # a track re-acquired, or started on mesh-born corners, carries no trained point to vouch for
    # it: for its first probation_frames frames the model's edges must confirm every pose
    probation_frames: int = 15
    # A reported pose must survive recognition's edge refit (recognition.evidence.edge_fit): a
    # re-acquired pose, a view about to be kept, a track on probation, and every audit_every-th
    # tracked frame (the audit). Refused when the refit moves it by more than max_edge_shift of
    # the 5 %/5° criterion. On the six zoo walks (745 tracked frames, six shapes, mm/cm/m) right
    # poses (< 1.5 %/1.5°) moved 0.26 at most; of the poses beyond 5 %/5°, 55 of 80 moved more
    # than 0.5 (the rest: a cube turned by 90°, whose edges are the same; slow drifts). Recognition
    # itself allows 1.0 (PoseParams.max_edge_shift): a re-acquired track follows the object at
    # that level while too little of it is inside the image to report it.
    max_edge_shift: float = 0.5
    # the textured points' score statistic at the joint pose beyond which a frame is adjusted
    # again without the edges (Tracker._unless_outvoted): χ²₆ at 0.999; 0 turns the test off
    texture_chi2: float = 22.46
    # ... and where the points' own pose lies more than outvote_max_shift of the 5 %/5° criterion
    # from the joint one (recognition.evidence.pose_shift), that frame's pose is withheld in doubt
    # (Tracker._unless_outvoted). 0.7: the harsh walks as before, frame for frame (0.5 and 0.6 put 5 and 3
    # poses beyond 5 %/5° there, tracks that went another way); the calm walks' poses beyond
    # 5 %/5° 27 → 23 (bench/RESULTS.md, session 67). 0: off
    outvote_max_shift: float = 0.7
    # tracked frames between audits (0: none); each costs an edge refit. 3 until session 39: a
    # track that no trained point anchors, re-found 2–3 % off, drifted 1.5 → 5.1 % between two
    # audits (zoo flat box, live; bench/RESULTS.md); such a track is now audited every frame
    audit_every: int = 1
    # … while the frame's trained points anchor the track (None: audit_every; Tracker._audit_interval)
    audit_every_anchored: int | None = 6
    # a pose the edges doubt (the audit, a strict test on probation) is withheld, not ended: the
    # track goes on for up to doubt_frames frames, each tested strictly, and is reported again
    # from the first the edges confirm (Tracker._doubt); 0: lost at once
    doubt_frames: int = 5
    # … and reported again only when the edge refit moves it by at most this share of the 5 %/5°
    # criterion (a hysteresis; None: max_edge_shift): each doubted frame is another draw, and a
    # wrong track 17 % off passed the 0.5 of a pose never doubted by drawing 0.42 (Tracker._doubt)
    # — and the bound on the second refit that confirms a pose settled on the edges (Tracker._edge_settled)
    doubt_confirm_shift: float | None = 0.25
    # The reported covariance is the filter's plus a systematic floor (quatrack.tracking.systematic:
    # the error the measurements share, which the filter's independent-measurement covariance
    # leaves out): the centre's 1-σ error systematic_pct % of the diameter across the line of
    # sight, systematic_depth_ratio × that along it, and systematic_deg about every axis. Chosen
    # so that the centre's NEES and the rotation's NEES, each apart (3 dof: one 6-dof NEES let a
    # far too cautious position hide a far too confident rotation), have χ²₃'s median and 95th
    # percentile on the zoo walks: 0.1 % and 0.15° fitted on rendering 0's six walks; the depth
    # ratio fitted there (1) failed on a held-out cylinder walk with a 1.4 % depth error (centre
    # NEES 76), so monocular depth keeps its 4× (renderings 1–3, 18 walks: objective 369 → 95,
    # 95 % ellipsoid median 78 → 91 %; bench/RESULTS.md, session 31; was 0.4 %, 4, 0.057° from
    # the 6-dof NEES of three walks). 0, 1, 0 (and systematic_px None): the filter's own.
    # Session 34 (bench/RESULTS.md): plus an image floor (quatrack.tracking.systematic.image_floor):
    # systematic_px pixels of error shared by all the object's points, whose effect on the pose
    # follows the object's shape and distance (a tall box's or a cylinder's turn about its long
    # axis, a far object's depth), which a floor per pose cannot know. Refitted together by the
    # same objective on rendering 0's walks, chosen among the near-best there by renderings 1–3:
    # 0.05 %, 4, 0.10°, 0.3 px (were 0.1 %, 4, 0.15°, none). None or 0: no image floor.
    systematic_pct: float = 0.05
    systematic_depth_ratio: float = 4.0
    systematic_deg: float = 0.10
    systematic_px: float | None = 0.3
    # The filter's part of the reported covariance is multiplied by the sources' disagreement
    # (quatrack.recognition.tracker.points.disagreement_factor: the Birge ratio², ≥ 1) — how much
    # more the trained points, the points born on the mesh, the edges and the outline disagree
    # about the pose than their covariances allow. An outline locked on the print, points lifted
    # at a pose that was off: an error no source's covariance holds, which the filter, combining
    # those covariances, cannot know; the sources' spread shows it. Only the reported covariance
    # changes (poses, statuses, reasons, the filter's state: the same). False: the filter's own.
    disagreement_scale: bool = True
    initial_sigma_p: float = 0.01  # × diameter, for init_pose without a covariance
    initial_sigma_deg: float = 2.0
    klt: KLTParams = field(default_factory=KLTParams)
    visibility: VisibilityParams = field(default_factory=VisibilityParams)
    # recognition after a loss re-matches each tried view alone (LocateParams.rematch_views): the
    # keyframes and their synthetic views repeat the same points and split the shared index's votes.
    # A pose the points leave too uncertain is not fixed by the edges here
    # (PoseParams.edge_covariance_inflation None): on the 24 walks, tracks re-found so went on to
    # report poses 18 % / 11° off (flat box #11) where waiting for the points did not (session 41)
    locate: LocateParams = field(default_factory=lambda: LocateParams(
        rematch_views=True, pose=PoseParams(edge_covariance_inflation=None)))
    adjust: AdjustOptions = field(
        # Gauss–Newton from the prediction converges in 2–3 steps here; 4 is a measured margin.
        # The stop rule ‖∇F‖ < ε mixes 1/length (position) and 1/rad terms, so ε is tiny: the
        # iterations stop at convergence, not earlier in one mesh unit than in another. (The
        # unit-free rule, AdjustOptions.decrement_tolerance = 1e-3, stops a step below ~3 % of a
        # standard deviation and saves ~1.2 ms of the ~4 ms adjust stage on box.mp4; not the
        # default: its slightly different poses sent one zoo walk's unanchored track in the dim
        # phase to 5.1 % before the audit caught it, bench/RESULTS.md, session 33.)
        default_factory=lambda: AdjustOptions(method="gauss-newton", robust="huber", max_iterations=4,
                                              gradient_tolerance=1e-7)
    )

    def __post_init__(self) -> None:
        self._check_kinds()
        noise = DEFAULT_MOTION_NOISE.get(self.motion_model)
        if noise is None:
            raise ValueError(f"unknown motion model {self.motion_model!r}; expected one of {sorted(DEFAULT_MOTION_NOISE)}")
        if isinstance(self.sources, str):  # ("edges" was read as the letters e, d, g, …)
            raise ValueError(f"sources: a tuple of names, e.g. ({self.sources!r},), not a string")
        bad = set(self.sources) - {"trained", "mesh", "edges", "contour"}
        if bad or not self.sources:
            raise ValueError((f"unknown measurement source(s) {sorted(bad)}" if bad else "sources: none given") +
                             "; expected some of 'trained', 'mesh', 'edges', 'contour'")
        if self.max_gap_s is not None and not self.max_gap_s > 0:  # (0 or less: every frame ended the track)
            raise ValueError(f"max_gap_s must be None or a number of seconds above 0, not {self.max_gap_s!r}")
        if self.relocate_interval_s is not None and not (is_number(self.relocate_interval_s)
                                                          and np.isfinite(self.relocate_interval_s)
                                                          and self.relocate_interval_s >= 0):
            raise ValueError(f"relocate_interval_s must be None or a number of seconds >= 0, "
                             f"not {self.relocate_interval_s!r}")
        unknown = set(self.motion_noise) - set(noise)
        if unknown:
            raise ValueError(f"motion model {self.motion_model!r} has no parameter(s) {sorted(unknown)}; "
                             f"expected {sorted(noise)}")
        for key, value in self.motion_noise.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (np.isfinite(value) and value >= 0):
                raise ValueError(f"motion_noise[{key!r}] must be a finite number >= 0, not {value!r}")
            if value > MAX_MOTION_NOISE:
                raise ValueError(f"motion_noise[{key!r}] = {value:g} is too large: at most {MAX_MOTION_NOISE:g} "
                                 f"({noise_defaults(self.motion_model)})")
        if not (is_number(self.sigma_px) and np.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise ValueError(f"sigma_px must be a number of pixels above 0, not {self.sigma_px!r}")
        for name in ("max_points", "min_points", "min_inliers"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be at least 1, not {getattr(self, name)!r}")

    def _check_kinds(self) -> None:
        """Every field of the kind its annotation says, or a ValueError (TypeError for a settings
        object) naming it: ``min_points="5"`` ended in "'<' not supported between 'int' and 'str'"
        at the first refresh, ``gate_chi2="13"`` in a numpy UFuncTypeError, ``refresh_every=2.5``
        and ``-1`` were run as given, ``motion_noise=None`` was "'NoneType' object is not iterable".
        ``motion_noise=None`` now means no overrides, as ``{}``."""
        if self.motion_noise is None:
            object.__setattr__(self, "motion_noise", {})
        if not isinstance(self.motion_noise, Mapping):
            raise ValueError(f"motion_noise must be a dict of noise parameters (mesh units), "
                             f"not {type(self.motion_noise).__name__}")
        check_field_kinds(self, _SETTINGS)

    def motion_noise_params(self, diameter: float) -> dict[str, float]:
        """The motion model's noise parameters (mesh units) for an object of this diameter."""
        return motion_noise(self.motion_model, diameter, self.motion_noise)

    @property
    def doubted_shift(self) -> float:
        """The edge refit's bound for a doubted pose: ``doubt_confirm_shift``, or ``max_edge_shift``
        when that is None (Tracker._track's doubted frames, Tracker._edge_settled)."""
        return self.max_edge_shift if self.doubt_confirm_shift is None else self.doubt_confirm_shift

    @_defaults_on_class
    def for_live_streams(self) -> "TrackerParams":
        """These settings as a live stream runs them (the service's sessions; ``bench track-zoo``'s
        live pass): re-anchoring and the lifting of views on the caller's executor beside the
        next frames' steps (``pipelined_refresh``), SIFT on the window shrunk to 320 px with its
        400 strongest features, so that no frame waits for SIFT; and every frame no trained point
        anchors judged by the keyframes' texture (``audit_texture``) (see the fields' comments)."""
        return replace(self, pipelined_refresh=True, anchor_max_side=320, anchor_max_features=400, audit_texture=True)


@dataclass
class TrackStep:
    """One frame's answer. Pose object → camera (``t`` mesh units, ``q_wxyz`` with w ≥ 0; both
    as :attr:`pose`), ``v`` mesh units/s and ``omega`` rad/s in the camera frame; ``covariance``
    6×6 over ``[p, δθ]`` (``δθ`` the rotation error in the camera frame: ``q_true = exp(δθ/2) ⊗
    q``), symmetric positive definite (to rounding). Pose fields are None when ``status`` is ``lost``.
    Picklable and copyable; ``timings_ms`` is the step's time per stage (milliseconds).

    Steps compare by value (``==``: every field, arrays number for number, exactly; not
    ``timings_ms``, which measures the machine: one video tracked twice gives equal steps), as
    :class:`~quatrack.recognition.locate.Located` does; not hashable (a step's fields may be set)."""

    frame: int
    time_s: float
    status: str  # "init" | "tracking" | "lost"
    t: np.ndarray | None = None
    q_wxyz: np.ndarray | None = None
    v: np.ndarray | None = None
    omega: np.ndarray | None = None
    covariance: np.ndarray | None = None
    inliers: int = 0
    timings_ms: dict = field(default_factory=dict, compare=False)
    reason: str | None = None  # why lost (or how initialised)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, TrackStep):
            return NotImplemented
        return self is other or value_key(self) == value_key(other)

    __hash__ = None  # (mutable, as a dataclass that compares by value)

    @property
    def has_pose(self) -> bool:
        """Whether the step carries a pose (``status`` is ``init`` or ``tracking``, not ``lost``)."""
        return self.status != "lost"

    @property
    def pose(self) -> Pose | None:
        """The pose as a :class:`~quatrack.tracking.pose.Pose` (object → camera; ``as_matrix()``,
        ``inverse()``, ``@``), as :attr:`Located.pose <quatrack.recognition.locate.Located.pose>`
        gives it; None when there is none (``lost``)."""
        return None if self.t is None or self.q_wxyz is None else Pose(self.q_wxyz, self.t)

"""Keyframes: the tracker finds the object again after a loss, on a side no photo shows (issue 12).

A 6 cm cube (zoo "small-cube-cm", texture from a real photo) is trained from ONE rendered photo
(azimuth 35°, elevation 25°) without synthetic views. A rendered camera orbits it by 180°, round
to two faces the photo never shows, tracked from the true first pose *without* learning. Then
the object leaves the view (empty frames: the track is lost) and comes back on the far side:

- the tracker kept keyframes along the way, far apart in direction, at poses close to the truth;
- it finds the object again there by itself ("re-found on this run's keyframe…"), within 5 % of
  the diameter and 5° of the truth, and goes on tracking; with keyframes off it finds nothing
  (recognition on the one photo cannot see those sides);
- an object that is not there is not "re-found": the empty frames stay lost;
- re-acquisition: when it comes back near where it went, the track is picked up at once from
  the last good frame (KLT), before any recognition.

Everything is rendered and seeded; the orbit is short (40 frames at 640×480).
"""

from __future__ import annotations


import cv2
import numpy as np
import pytest

from conftest import one_photo_orbit
from quatrack.recognition.match import index_for
from quatrack.recognition.tracker.reacquire import shifted_pose
from quatrack.recognition.video import Tracker, TrackerParams
from quatrack.testing import zoo as Z
from quatrack.testing.scenes import pose_errors

NAME = "small-cube-cm"
FPS = 30.0
N_FRAMES = 40
SPAN_DEG = 180.0


def _pose(obj, cam, azimuth: float, k: int = 0):
    return Z.orbit_pose(obj, cam, azimuth, 25.0 + 10.0 * np.sin(np.pi * k / N_FRAMES))


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    return one_photo_orbit(tmp_path_factory.mktemp("keyframes"), SPAN_DEG, N_FRAMES, NAME)


def _far_side(walk):
    """The object seen from 200°–206° round (the far side; elevation 30°), 20° back from where
    the walk ended: found again only by what the tracker saw (keyframes)."""
    return [Z.orbit_pose(walk.obj, walk.cam, 200.0 + 2.0 * i, 30.0) for i in range(4)]


def _walk_on(walk):
    """The walk going on after the gap, the camera turning at a third of the walk's 4.6°/frame
    while the object was unseen: it comes back where it went, turned 6° further, and goes on."""
    end = 35.0 + SPAN_DEG
    return [_pose(walk.obj, walk.cam, end + SPAN_DEG / (N_FRAMES - 1) / 3 * (4 + i), N_FRAMES) for i in range(4)]


def _track(walk, params: TrackerParams, back=None, before_back=None):
    """The orbit from the true first pose, then 3 frames without the object, then 4 frames of it
    at the poses ``back`` (:func:`_far_side` by default): (tracker, steps, ``back``).
    ``before_back(tracker, i)`` is called before the i-th of those frames."""
    cv2.setRNGSeed(7)
    tracker = Tracker(walk.model, walk.cam, params, index=index_for(walk.model))
    tracker.init_pose(walk.poses[0].t, walk.poses[0].q_wxyz)
    steps = [tracker.step(f, k / FPS) for k, f in enumerate(walk.frames)]
    k0 = len(steps)
    for i in range(3):
        steps.append(tracker.step(walk.bg, (k0 + i) / FPS))
    back = _far_side(walk) if back is None else back
    for i, p in enumerate(back):
        if before_back is not None:
            before_back(tracker, i)
        img = Z.degrade(Z.compose(*walk.obj.render(walk.cam, p), walk.bg), np.random.default_rng(40 + i))
        steps.append(tracker.step(img, (k0 + 3 + i) / FPS))
    return tracker, steps, back


def test_keyframes_are_kept_along_the_walk_far_apart_and_right(walk):
    tracker, steps, _ = _track(walk, TrackerParams())
    assert all(s.has_pose for s in steps[:N_FRAMES]), [(s.frame, s.reason) for s in steps[:N_FRAMES] if not s.has_pose][:3]
    kf = tracker.keyframes.items
    p = TrackerParams()
    assert 3 <= len(kf) <= p.keyframes_max
    dirs = np.array([k.direction for k in kf])
    ang = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1, 1)))[np.triu_indices(len(kf), 1)]
    assert ang.min() >= p.keyframe_min_angle_deg - 1e-9
    d = walk.model.mesh.extent
    for k in kf:  # each at a tracked pose near the truth: its points lie where the truth puts them
        frame = int(round(k.time_s * FPS))
        dp, da = pose_errors(k.viewset.pose.t, k.viewset.pose.q_wxyz, walk.poses[frame], walk.model.mesh)
        assert dp < 0.01 * d and da < 1.0
        uv = walk.cam.project(walk.poses[frame].apply(k.viewset.points3d))
        assert np.median(np.linalg.norm(uv - k.viewset.keypoints, axis=1)) < 1.5
    # the last keyframes see the faces the photo never showed
    photo = walk.model.viewsets[0].pose.viewing_direction(walk.model.mesh.centre)
    assert np.degrees(np.arccos(dirs @ photo)).max() > 90.0


def test_with_an_executor_keyframes_are_lifted_off_the_step(walk):
    """Live streams (``pipelined_refresh`` with the caller's executor, as the service runs it): a
    keyframe's SIFT + lifting (~45 ms, which set the p99 of two streams when it ran in the step)
    runs on the executor and a later step keeps it; the keyframes are kept all the same, right."""
    from concurrent.futures import ThreadPoolExecutor

    from quatrack.viewsets.learn import learned_viewset

    submitted = []

    class Counting(ThreadPoolExecutor):
        def submit(self, fn, *args, **kwargs):
            submitted.append(fn)
            return super().submit(fn, *args, **kwargs)

    cv2.setRNGSeed(7)
    with Counting(1) as pool:
        tracker = Tracker(walk.model, walk.cam, TrackerParams(pipelined_refresh=True), index=index_for(walk.model),
                          executor=pool)
        tracker.init_pose(walk.poses[0].t, walk.poses[0].q_wxyz)
        steps = [tracker.step(f, k / FPS) for k, f in enumerate(walk.frames)]
    # (with re-anchoring pipelined too, this fast walk (4.6°/frame) round to faces no photo
    # shows is lost before its end, as the service's settings were before keyframes moved)
    assert all(s.has_pose for s in steps[:25]), [(s.frame, s.reason) for s in steps if not s.has_pose][:3]
    kf = tracker.keyframes.items
    assert submitted.count(learned_viewset) >= len(kf) >= 3
    d = walk.model.mesh.extent
    for k in kf:  # each lifted at the pose of the frame it was taken in
        frame = int(round(k.time_s * FPS))
        dp, da = pose_errors(k.viewset.pose.t, k.viewset.pose.q_wxyz, walk.poses[frame], walk.model.mesh)
        assert dp < 0.01 * d and da < 1.0


def test_the_object_is_found_again_on_a_side_no_photo_shows(walk):
    tracker, steps, back = _track(walk, TrackerParams(reacquire_s=0.0))  # (keyframes alone)
    gone, returned = steps[N_FRAMES : N_FRAMES + 3], steps[N_FRAMES + 3 :]
    assert not any(s.has_pose for s in gone), [s.reason for s in gone]  # nothing is "re-found" where nothing is
    assert returned[0].status == "init" and "keyframe" in returned[0].reason, returned[0].reason
    assert [s.status for s in returned[1:]] == ["tracking"] * 3, [(s.status, s.reason) for s in returned]
    d = walk.model.mesh.extent
    for s, truth in zip(returned, back):
        dp, da = pose_errors(s.t, s.q_wxyz, truth, walk.model.mesh)
        assert dp < 0.05 * d and da < 5.0, (s.frame, dp / d, da)


def test_a_re_found_track_reports_the_error_it_carries_from_its_birth(walk):
    """Re-found on keyframes, the track is carried by points lifted at its own poses: while no
    trained point is in view its reported covariance adds the re-found pose's covariance, turned
    with the object (carried_covariance); with trained points in view it does not; a first-hand
    track never does. The truth lies within the reported covariance's 99.9 % ellipsoid."""
    from quatrack.tracking import quaternion as quat
    from quatrack.tracking.systematic import carried_covariance

    tracker, steps, back = _track(walk, TrackerParams(reacquire_s=0.0))
    assert tracker._second_hand and tracker._birth is not None
    s = tracker.filter.state
    tracker._anchored = True
    anchored = tracker._pose_step(1.0, "tracking", 0)
    tracker._anchored = False
    carried = tracker._pose_step(1.0, "tracking", 0).covariance - anchored.covariance
    np.testing.assert_allclose(carried, carried_covariance(s.R, *tracker._birth), rtol=1e-9, atol=1e-15)
    assert np.trace(carried[:3, :3]) > 0.5 * np.trace(tracker._birth[1][:3, :3])
    for st, truth in zip(steps[N_FRAMES + 3 :], back):
        dq = quat.multiply(truth.q_wxyz, quat.conjugate(np.asarray(st.q_wxyz)))
        e = np.concatenate([truth.t - st.t, quat.to_rotvec(quat.canonical(dq))])
        assert e @ np.linalg.solve(st.covariance, e) < 22.46, st.frame  # χ²₆ at 99.9 %
    first, _, _ = _track(walk, TrackerParams(), _walk_on(walk))  # re-acquired near its last pose
    assert first._birth is None


def test_a_pose_re_found_on_the_mesh_alone_is_reported_from_the_next_frame(walk):
    """A pose re-found after a loss that no SIFT point anchors (a start on the mesh: its points
    are born at it, only the edges vouch for it) is withheld in its first frame — ``lost``, the
    reason saying so — and reported from the next frame that tracks, as ``init`` with the
    start's reason; the track is the same (edges alone leave a turn about an axis of symmetry
    open: the zoo's tall boxes were re-found so 5.3–5.7° off, 2.8° one frame later)."""
    from quatrack.recognition.tracker.points import Tracks

    def sift_anchors_nothing_at_first(tracker, i):
        anchors = tracker._anchors()
        if i == 0:
            anchors.now = lambda img, camera, pose, tracks, *a, **kw: (Tracks.empty(), 0, False)
        else:
            vars(anchors).pop("now", None)  # (the class's own method again)

    _, returned, back = _track(walk, TrackerParams(reacquire_s=0.0), before_back=sift_anchors_nothing_at_first)
    assert not any(s.has_pose for s in returned[N_FRAMES : N_FRAMES + 3])
    steps = returned[N_FRAMES + 3 :]
    first, then = steps[0], steps[1:]
    assert first.status == "lost" and not first.has_pose, (first.status, first.reason)
    assert "keyframe" in first.reason and first.reason.endswith("withheld until the next frame confirms it"), first.reason
    assert then[0].status == "init" and then[0].reason == first.reason.split(": the pose is withheld")[0], then[0].reason
    assert [s.status for s in then[1:]] == ["tracking"] * (len(then) - 1), [(s.status, s.reason) for s in then]
    d = walk.model.mesh.extent
    for s, truth in zip(then, back[1:]):
        dp, da = pose_errors(s.t, s.q_wxyz, truth, walk.model.mesh)
        assert dp < 0.05 * d and da < 5.0, (s.frame, dp / d, da)


def test_a_pose_re_found_on_keyframes_is_settled_on_the_edges_alone(walk):
    """A second-hand start on the mesh (re-found on the tracker's own keyframes, no trained view
    of that side) is judged by the edge refit on the edges alone, before any point is born at
    it (points born at the pose under test agree with it whatever it is): the true pose starts
    where it is; one turned 3° about the centre and 2 % off — as a re-finding on a synthetic
    view can be — starts where the edges put it, near the truth (Tracker._edge_settled: the
    refit, confirmed by a second refit from there); one 4° and 2.5 % off, whose edges the
    agreement test passed while the far outline of faces seen at a grazing angle counted as
    hidden (before session 39), and one 15° and 10 % off are refused."""
    from quatrack.recognition.klt import make_frame
    from quatrack.recognition.tracker.points import Tracks
    from quatrack.tracking import quaternion as quat
    from quatrack.tracking.pose import Pose

    tracker, _, back = _track(walk, TrackerParams(reacquire_s=0.0))
    truth = back[-1]
    img = Z.degrade(Z.compose(*walk.obj.render(walk.cam, truth), walk.bg), np.random.default_rng(43))
    frame = make_frame(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    mesh = walk.model.mesh
    c, d = mesh.centre, mesh.extent

    def turned(deg, share):
        q = quat.multiply(quat.from_rotvec(np.radians([deg, 0.0, 0.0])), truth.q_wxyz)
        return Pose(q, truth.R @ c + truth.t - quat.to_matrix(q) @ c + np.array([share * d, 0.0, 0.0]))

    def start(pose):
        tracker.reset()
        tracker._second_hand = True
        tracker._start_filter(0.0, pose, tracker._initial_covariance())
        return tracker._start_on_mesh(img, frame, tracker.filter.predict(1.0 / FPS), Tracks.empty())

    def error(pose):
        return pose_errors(pose.t, pose.q_wxyz, truth, mesh)

    assert start(Pose(truth.q_wxyz, truth.t))
    dp, da = error(tracker.filter.state.pose)
    assert dp < 0.005 * d and da < 0.5
    off = turned(3.0, 0.02)
    assert start(off)
    dp, da = error(tracker.filter.state.pose)
    assert dp < 0.01 * d and da < 1.0, (dp / d, da)  # (it was 2 % and 3° off)
    assert tracker._birth[0] is not off.R and np.allclose(tracker._birth[0], tracker.filter.state.pose.R)
    assert not start(turned(4.0, 0.025))  # (its outline no longer agrees with the image's edges)
    assert not start(turned(15.0, 0.10))


def test_the_track_is_picked_up_again_near_the_last_pose(walk):
    """Re-acquisition: the object comes back near where it went (turned 6° further while
    unseen); KLT from the last good frame picks the track up at once, the edges confirming."""
    tracker, steps, back = _track(walk, TrackerParams(), _walk_on(walk))
    gone, returned = steps[N_FRAMES : N_FRAMES + 3], steps[N_FRAMES + 3 :]
    assert not any(s.has_pose for s in gone), [s.reason for s in gone]
    assert returned[0].status == "init" and returned[0].reason == "re-acquired near the last pose", returned[0].reason
    assert [s.status for s in returned[1:]] == ["tracking"] * 3, [(s.status, s.reason) for s in returned]
    d = walk.model.mesh.extent
    for s, truth in zip(returned, back):
        dp, da = pose_errors(s.t, s.q_wxyz, truth, walk.model.mesh)
        assert dp < 0.02 * d and da < 2.0, (s.frame, dp / d, da)


def test_a_re_found_track_is_picked_up_again_near_its_last_pose_and_stays_second_hand(walk):
    """A track re-found on keyframes (second-hand) that held, lost when the object leaves the
    view and coming back near where it went, is picked up again near its last pose as a
    first-hand track is — not left to recognition, which on the zoo walks' sides no photo
    shows found nothing for ~100 frames (bench/RESULTS.md, session 44). It stays second-hand:
    judged as one, and reported with its birth's covariance (the same birth as before)."""
    far = [Z.orbit_pose(walk.obj, walk.cam, 200.0 + 2.0 * i, 30.0) for i in range(14)]
    cv2.setRNGSeed(7)
    tracker = Tracker(walk.model, walk.cam, TrackerParams(), index=index_for(walk.model))
    tracker.init_pose(walk.poses[0].t, walk.poses[0].q_wxyz)
    steps = [tracker.step(f, k / FPS) for k, f in enumerate(walk.frames)]
    k = len(steps)

    def show(pose, i):
        img = Z.degrade(Z.compose(*walk.obj.render(walk.cam, pose), walk.bg), np.random.default_rng(60 + i))
        return tracker.step(img, (k + i) / FPS)

    gone = [tracker.step(walk.bg, (k + i) / FPS) for i in range(3)]  # lost: the walk's own track ends
    tracker.reset()  # (its last pose forgotten: recognition must find the object again)
    held = [show(far[i], 3 + i) for i in range(8)]  # re-found on keyframes (the far side), then held
    assert not any(s.has_pose for s in gone)
    assert "keyframe" in held[0].reason and all(s.status == "tracking" for s in held[1:]), [(s.status, s.reason) for s in held]
    assert tracker._second_hand
    birth = tracker._birth
    gap = [tracker.step(walk.bg, (k + 11 + i) / FPS) for i in range(2)]
    back = [show(far[10 + i], 13 + i) for i in range(4)]
    assert not any(s.has_pose for s in gap)
    assert back[0].status == "init" and back[0].reason == "re-acquired near the last pose", back[0].reason
    assert [s.status for s in back[1:]] == ["tracking"] * 3, [(s.status, s.reason) for s in back]
    assert tracker._second_hand and tracker._birth is birth
    d = walk.model.mesh.extent
    for s, truth in zip(back, far[10:]):
        dp, da = pose_errors(s.t, s.q_wxyz, truth, walk.model.mesh)
        assert dp < 0.05 * d and da < 5.0, (s.frame, dp / d, da)


@pytest.mark.parametrize("doubted", [False, True])
def test_near_a_pose_withheld_in_doubt_the_track_is_picked_up_only_at_the_doubted_bar(walk, monkeypatch, doubted):
    """A last pose the edges doubted (withheld, not reported) is picked up again only if the
    re-acquired pose passes the bar a doubted pose must pass to be reported again
    (``doubted_shift``, a quarter of the 5 %/5° criterion), not the usual half: with the edge
    refit moving it by 0.4 of the criterion the track is re-acquired near a reported last pose
    and not near a doubted one (bench/RESULTS.md, session 44: second-hand tracks picked up at the
    usual bar near doubted poses came back 7 % off)."""
    from dataclasses import replace

    p = TrackerParams()
    assert p.doubted_shift < 0.4 <= p.max_edge_shift
    cv2.setRNGSeed(7)
    tracker = Tracker(walk.model, walk.cam, p, index=index_for(walk.model))
    tracker.init_pose(walk.poses[0].t, walk.poses[0].q_wxyz)
    for k, f in enumerate(walk.frames):
        tracker.step(f, k / FPS)
    k = len(walk.frames)
    gone = [tracker.step(walk.bg, (k + i) / FPS) for i in range(3)]
    assert not any(s.has_pose for s in gone) and tracker._seen is not None
    tracker._seen = replace(tracker._seen, doubted=doubted)
    monkeypatch.setattr(tracker, "_edge_shift", lambda *a, **kw: 0.4)
    img = Z.degrade(Z.compose(*walk.obj.render(walk.cam, _walk_on(walk)[0]), walk.bg), np.random.default_rng(40))
    step = tracker.step(img, (k + 3) / FPS)
    assert (step.reason == "re-acquired near the last pose") is not doubted, step.reason


def _beyond(walk, beyond_deg: float):
    """The object seen from ``beyond_deg`` further round than where the walk ended (elevation
    30°), after the gap: a side the last keyframes saw only at a grazing angle."""
    end = 35.0 + SPAN_DEG
    return [Z.orbit_pose(walk.obj, walk.cam, end + beyond_deg + 1.0 * i, 30.0) for i in range(4)]


@pytest.mark.parametrize("beyond_deg", [20.0, 30.0])
def test_keyframes_synthetic_views_find_the_object_turned_beyond_every_keyframe(walk, beyond_deg):
    """The object comes back 20–30° further round than the walk went: no keyframe sees that
    side from near enough for SIFT, and without synthetic views nothing finds it; with them
    (each keyframe's crop re-rendered turned by ±20° and ±40°, made after the loss) it is
    found again within 5 % / 5° of the truth, and tracked on."""
    back = _beyond(walk, beyond_deg)
    _, plain, _ = _track(walk, TrackerParams(reacquire_s=0.0, keyframe_synthetic_deg=()), back)
    assert not any(s.has_pose for s in plain[N_FRAMES:]), [(s.status, s.reason) for s in plain[N_FRAMES:]]
    tracker, steps, _ = _track(walk, TrackerParams(reacquire_s=0.0), back)
    gone, returned = steps[N_FRAMES : N_FRAMES + 3], steps[N_FRAMES + 3 :]
    assert not any(s.has_pose for s in gone), [s.reason for s in gone]
    assert all(k.synthetic for k in tracker.keyframes.items)  # made while the object was gone
    found = [i for i, s in enumerate(returned) if s.has_pose]
    assert found and found[0] <= 1, [(s.status, s.reason) for s in returned]
    assert "keyframe" in returned[found[0]].reason and "-cam" in returned[found[0]].reason, returned[found[0]].reason
    assert all(s.has_pose for s in returned[found[0]:]), [(s.status, s.reason) for s in returned]
    d = walk.model.mesh.extent
    for s, truth in zip(returned[found[0]:], back[found[0]:]):
        dp, da = pose_errors(s.t, s.q_wxyz, truth, walk.model.mesh)
        assert dp < 0.05 * d and da < 5.0, (s.frame, dp / d, da)


def test_with_an_executor_synthetic_views_are_made_there(walk, monkeypatch):
    """Live streams: the synthetic views (≈ 0.25 s per lost frame's batch) are made on the
    caller's executor, never in the step, one batch at a time, and attached by a later step.
    (An executor that runs each job at once, so which step sees it done is known.)"""
    from concurrent.futures import Executor, Future

    from quatrack.recognition.tracker import keyframes as K

    calls = []
    real = K.synthetic_views
    monkeypatch.setattr(K, "synthetic_views", lambda *a, **k: calls.append(len(a[0])) or real(*a, **k))

    class AtOnce(Executor):
        def __init__(self):
            self.jobs = 0

        def submit(self, fn, *args, **kwargs):
            self.jobs += fn is K.synthetic_views
            f = Future()
            f.set_result(fn(*args, **kwargs))
            return f

    pool = AtOnce()
    cv2.setRNGSeed(7)
    tracker = Tracker(walk.model, walk.cam, TrackerParams(pipelined_refresh=True, reacquire_s=0.0),
                      index=index_for(walk.model), executor=pool)
    tracker.init_pose(walk.poses[0].t, walk.poses[0].q_wxyz)
    for k, f in enumerate(walk.frames):
        tracker.step(f, k / FPS)
    kf = tracker.keyframes
    missing = []
    for i in range(len(kf) + 2):  # frames without the object: lost
        missing.append(sum(k.synthetic is None for k in kf.items))
        tracker.step(walk.bg, (len(walk.frames) + i) / FPS)
    assert len(kf) >= 3 and missing[0] > 0 and sum(k.synthetic is None for k in kf.items) == 0, missing
    assert calls and len(calls) == pool.jobs  # every batch made on the executor
    assert all(c <= 2 for c in calls)  # (keyframe_synthetic_per_frame)
    assert all(len(k.synthetic) >= 4 for k in kf.items)


def test_without_keyframes_and_re_acquisition_the_far_side_is_not_found(walk):
    _, steps, _ = _track(walk, TrackerParams(keyframes_max=0, reacquire_s=0.0), _far_side(walk))
    assert not any(s.has_pose for s in steps[N_FRAMES:]), [(s.status, s.reason) for s in steps[N_FRAMES:]]


def test_without_keyframes_and_re_acquisition_the_walk_on_is_found_later_if_at_all(walk):
    """Where the walk goes on, recognition on the one photo alone may find the cube's print on
    the face now in view (since session 55's transition-tilt rule it does, in the third frame
    back, withheld in the second until confirmed): later than the keyframes' re-acquisition,
    which picks the track up in the first frame back (the re-acquisition tests below), and never
    wrong."""
    _, steps, back = _track(walk, TrackerParams(keyframes_max=0, reacquire_s=0.0), _walk_on(walk))
    after = steps[N_FRAMES + 3:]
    assert not after[0].has_pose, [(s.status, s.reason) for s in after]
    for s, truth in zip(after, back):
        if s.has_pose:
            dt, dr = pose_errors(s.t, s.q_wxyz, truth, walk.model.mesh)
            assert dt < 0.05 * walk.model.mesh.extent and dr < 5.0, (s.reason, dt, dr)


def test_a_shifted_pose_moves_the_image_by_the_shift(walk):
    pose = walk.poses[5]
    c = walk.model.mesh.centre
    moved = shifted_pose(pose, c, walk.cam, np.array([-87.0, 31.0]))
    uv0, uv1 = (walk.cam.project(p.apply(c[None]))[0] for p in (pose, moved))
    assert np.allclose(uv1 - uv0, [-87.0, 31.0], atol=1e-6)
    assert np.allclose(moved.q_wxyz, pose.q_wxyz)


def test_a_track_lost_sliding_out_of_the_frame_is_not_re_acquired_near_its_last_pose(walk):
    """An object sliding out of the frame leaves the track's points on one strip of it, and the
    pose drifts while they still agree among themselves (the zoo cube: 0.5 → 3.6°, on another
    rendering 5.9°, in its last six frames at 55 → 19 % inside). Re-acquired near such a last
    pose, it came back 1.7 % / 6.9° off with edges that agreed and was reported. So a last pose
    with less than ``reacquire_min_inside`` of the object in the image is not kept for
    re-acquisition (recognition restarts the track); one well inside still is (the tests above)."""
    from quatrack.recognition.evidence import silhouette_inside

    cv2.setRNGSeed(7)
    tracker = Tracker(walk.model, walk.cam, TrackerParams(), index=index_for(walk.model))
    tracker.init_pose(walk.poses[0].t, walk.poses[0].q_wxyz)
    for k, f in enumerate(walk.frames[:12]):
        assert tracker.step(f, k / FPS).has_pose
    c, last = walk.model.mesh.centre, walk.poses[11]
    steps, shares = [], []
    for i in range(1, 40):  # the object slides right, 12 px a frame, until the track is lost
        pose = shifted_pose(last, c, walk.cam, np.array([12.0 * i, 0.0]))
        img = Z.degrade(Z.compose(*walk.obj.render(walk.cam, pose), walk.bg), np.random.default_rng(i))
        steps.append(tracker.step(img, (11 + i) / FPS))
        shares.append(silhouette_inside(walk.model.mesh, walk.cam, pose)[0])
        if not tracker.tracking:  # (a pose the edges doubt is withheld while the track goes on)
            break
    assert not steps[-1].has_pose and shares[-2] < TrackerParams().reacquire_min_inside, ([s.reason for s in steps], shares[-3:])
    assert tracker._seen is None


@pytest.mark.parametrize("follow", [True, False])
def test_the_track_is_picked_up_where_the_object_went(walk, follow):
    """The object comes back 110 px left of where it was last seen (it slid while unseen):
    beyond KLT's reach from the last good frame, so re-acquisition first finds where its image
    went (object_shift); without that step (``reacquire_min_ncc`` > 1) it is not picked up."""
    c = walk.model.mesh.centre
    back = [shifted_pose(p, c, walk.cam, np.array([-110.0 - 4.0 * i, 0.0])) for i, p in enumerate(_walk_on(walk))]
    params = TrackerParams(keyframes_max=0, reacquire_min_ncc=0.5 if follow else 1.5)
    _, steps, _ = _track(walk, params, back)
    returned = steps[N_FRAMES + 3 :]
    if not follow:
        assert not any(s.has_pose for s in returned), [(s.status, s.reason) for s in returned]
        return
    assert returned[0].status == "init" and returned[0].reason == "re-acquired near the last pose", returned[0].reason
    assert [s.status for s in returned[1:]] == ["tracking"] * 3, [(s.status, s.reason) for s in returned]
    d = walk.model.mesh.extent
    err = [pose_errors(s.t, s.q_wxyz, truth, walk.model.mesh) for s, truth in zip(returned, back)]
    for s, (dp, da) in zip(returned, err):
        assert dp < 0.02 * d and da < 2.0, (s.frame, dp / d, da)


def test_re_anchoring_falls_back_on_the_keyframes_seen_from_near_the_current_direction(walk):
    """Where the model's views match nothing (a side the one photo never shows), re-anchoring
    matches the frame's SIFT to this run's keyframes — only those seen from within
    ``anchor_keyframe_max_deg`` of the current direction (SIFT matches a view only so far round)
    — and their matches land on the object where the truth puts them."""
    from quatrack.recognition.tracker.anchor import object_window

    tracker, steps, _ = _track(walk, TrackerParams())
    items = tracker.keyframes.items
    assert len(items) >= 3
    n_model = len(walk.model.viewsets)
    k = int(round(items[-1].time_s * FPS))  # the frame the last keyframe was taken in
    truth = walk.poses[k]
    feats = tracker._anchors().index.describe(walk.frames[k], object_window(walk.model.mesh, walk.cam, truth, 0.15))
    m = tracker._keyframe_matches(feats, truth)
    assert m is not None and len(m) >= 20
    used = np.unique(m.viewset[m.viewset >= n_model]) - n_model
    d = truth.viewing_direction(walk.model.mesh.centre)
    ang = np.degrees(np.arccos(np.clip([items[i].direction @ d for i in used], -1, 1)))
    assert len(used) and np.all(ang <= TrackerParams().anchor_keyframe_max_deg), ang
    kf_rows = m.viewset >= n_model
    err = np.linalg.norm(walk.cam.project(truth.apply(m.points3d[kf_rows])) - feats.keypoints[m.query_idx[kf_rows]], axis=1)
    assert np.median(err) < 2.0  # right matches, lifted at right poses
    # seen from 90° away from every keyframe: none of them is used
    far = Z.orbit_pose(walk.obj, walk.cam, 35.0 - 90.0, -40.0)
    dirs = np.array([it.direction for it in items])
    assert np.degrees(np.arccos(np.clip(dirs @ far.viewing_direction(walk.model.mesh.centre), -1, 1))).min() > 25
    assert tracker._keyframe_matches(feats, far) is None
    # off: no fallback at all
    off = Tracker(walk.model, walk.cam, TrackerParams(anchor_keyframes=False))
    off.keyframes = tracker.keyframes
    assert off._keyframe_matches(feats, truth) is None


def test_views_learned_where_the_photo_no_longer_anchors_are_relayed(walk, tmp_path):
    """``TrackerParams.relayed_views_anchor`` (False): a view learned at a frame that fewer than
    ``min_inliers`` points of the model's own views anchored inherits the track's drift. Its
    points are measured but anchor no frame, and a re-finding on it is second-hand ("re-found on
    the relayed view learnedN", judged as one on a keyframe). The views learned while the photo's points still
    anchored stay anchors. Stored, the model keeps which views are relayed, and a later run
    treats them so. With the option on, every learned view anchors and a re-finding on any of
    them is "recognition". Keyframes are off: only learned views are in play."""
    from dataclasses import replace

    from quatrack.recognition.tracker.points import PointBlock, Tracks

    def block(vs):
        return PointBlock.isotropic("trained", Tracks(vs.points3d, np.zeros((len(vs), 2))), 1.0)

    def refound(tracker, vs):  # (a frame at the view's own pose, searched afresh)
        tracker.reset()
        img = Z.degrade(Z.compose(*walk.obj.render(walk.cam, vs.pose), walk.bg), np.random.default_rng(3))
        step = tracker.step(img, 100.0)
        return step.reason if step.status == "init" else None

    params = TrackerParams(learn=True, keyframes_max=0)
    tracker, _, _ = _track(walk, params)
    relayed = [vs for vs in tracker.learned if vs.label in tracker._relayed_views]
    first_hand = [vs for vs in tracker.learned if vs.label not in tracker._relayed_views]
    assert relayed and first_hand, [vs.label for vs in tracker.learned]  # (the walk turns past the photo)
    assert all(tracker._anchoring(block(vs)) == 0 for vs in relayed)
    assert all(tracker._anchoring(block(vs)) == len(vs) for vs in first_hand)
    assert all(tracker._anchoring(block(vs), own=True) == 0 for vs in tracker.learned)  # (not the model's own)
    last = relayed[-1]
    assert refound(tracker, last) == f"re-found on the relayed view {last.label}" and tracker._second_hand

    # stored with the model (manifest "relayed": true), they stay relayed in the next run; the
    # first-hand ones become the model's own
    from quatrack.viewsets.learn import with_learned
    from quatrack.viewsets.store import load_manifest, load_model, save_model

    save_model(tmp_path, with_learned(walk.model, tracker.learned))
    entries = {e["label"]: e for e in load_manifest(tmp_path, walk.model.name)["viewsets"]}
    assert all(entries[vs.label].get("relayed") is True for vs in relayed)
    assert all("relayed" not in entries[vs.label] for vs in first_hand)
    later = Tracker(load_model(tmp_path, walk.model.name), walk.cam, params)
    assert later._relayed_views == {vs.label for vs in relayed}
    assert all(later._anchoring(block(vs)) == 0 for vs in relayed)
    assert all(later._anchoring(block(vs), own=True) == len(vs) for vs in first_hand)
    assert refound(later, last) == f"re-found on the relayed view {last.label}" and later._second_hand

    tracker, _, _ = _track(walk, replace(params, relayed_views_anchor=True))
    assert not tracker._relayed_views and len(tracker.learned) >= len(relayed) + len(first_hand)
    assert all(tracker._anchoring(block(vs)) == len(vs) for vs in tracker.learned)
    assert refound(tracker, tracker.learned[-1]) == "recognition" and not tracker._second_hand

"""The tracker's measurement sources alone on rendered frames with known motion (issue 12).

- points born on the mesh at the current pose (recognition/tracker/mesh_points.py): where they
  may be born, what covariance they carry, and that they alone follow a known motion;
- model edges (recognition/tracker/edges.py): a sub-pixel step edge found by the 1-D search,
  and edges alone following a known motion;
- a camera orbiting a cube trained from ONE photo, round to faces the photo never shows: the
  trained points alone lose it, the mesh-born points follow it to the end;
- the outline (recognition/tracker/contour.py) found by colour, and followed;
- a dead stop after a fast slide: the outline's sources search round the points' pose.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import one_photo_orbit
from quatrack.testing.scenes import EXAMPLE, Renderer, pose_errors
from quatrack.testing.sequences import box_sequence, clutter_background, compose
from quatrack.recognition.klt import make_frame
from quatrack.recognition.match import index_for
from quatrack.recognition.tracker.mesh_points import MeshPoints, birth_mask
from quatrack.recognition.tracker.points import pose_spread
from quatrack.recognition.tracker.sources import FrameContext
from quatrack.recognition.visibility import visible_points
from quatrack.recognition.video import Tracker, TrackerParams
from quatrack.tracking.pose import Pose
from quatrack.tracking.state import initial_state
from quatrack.viewsets.render import render

FPS = 30.0


@pytest.fixture(scope="module")
def box():
    seq = box_sequence(24, trajectory_seed=7, noise_seed=1, background=clutter_background(2), fps=FPS)
    return seq.model, seq.camera, seq.poses, seq.frames


def test_corners_are_born_on_visible_faces_away_from_the_silhouette(box):
    model, camera, poses, _ = box
    params = TrackerParams()
    mask = birth_mask(model.mesh, camera, poses[0], params) > 0
    sil = (render(model.mesh, camera, poses[0]).face >= 0).astype(np.uint8)
    assert mask.sum() > 0.3 * sil.sum()
    # distance of every allowed pixel to the background: at least the margin (less the half-
    # resolution rendering's rounding)
    dist = cv2.distanceTransform(sil, cv2.DIST_L2, 5)
    assert np.all(sil[mask] > 0) and dist[mask].min() >= params.mesh_edge_margin_px - 3


def test_a_born_point_carries_its_birth_pose_uncertainty(box):
    model, camera, poses, frames = box
    params = TrackerParams()
    src = MeshPoints(model.mesh, params)
    P = np.diag([0.2**2] * 3 + [np.radians(1.0) ** 2] * 3)
    state = initial_state(0.0, poses[0].t, poses[0].q_wxyz, P)
    frame = make_frame(cv2.cvtColor(frames[0], cv2.COLOR_BGR2GRAY))
    ctx = FrameContext(frames[0], frame, frame, camera, state)
    n = src.spawn(ctx, state)
    assert n > 30
    # the lifted points lie on the mesh where the rays met it: they project back onto their corners
    uv = camera.project(poses[0].apply(src.tracks.X))
    assert np.abs(uv - src.tracks.uv).max() < 1e-6
    block = src.measure(ctx, {})  # the same frame: KLT stays put
    assert len(block) > 0.9 * n
    # born together, they share one error: each carries it × their number (mesh_points.py)
    expected = params.sigma_px**2 * np.eye(2) + len(block) * pose_spread(camera, block.X, state)
    assert np.allclose(block.C, expected, rtol=1e-9)
    # 0.2 cm and 1° at ~60 cm spread a projection by a few pixels: far above σ² = 0.49 px²
    assert np.median(np.trace(block.C, axis1=1, axis2=2)) > 5 * 2 * params.sigma_px**2


def test_mesh_points_relifted_at_a_corrected_pose_lie_where_their_corners_are_seen_from_it(box):
    """MeshPoints.relift (Tracker._texture_audit moves a drifted track to where the keyframes'
    texture puts it): points lifted at a pose 2 % of the box deeper than the truth are lifted
    again at the true pose from the same pixels; they then project onto those pixels at the true
    pose, match the points lifted there afresh, and form one new cohort, not vouched for."""
    model, camera, poses, frames = box
    params = TrackerParams()
    truth = poses[0]
    c = truth.apply(model.mesh.centre[None])[0]
    off = Pose(truth.q_wxyz, truth.t + 0.02 * model.mesh.extent * c / np.linalg.norm(c))
    frame = make_frame(cv2.cvtColor(frames[0], cv2.COLOR_BGR2GRAY))
    P = np.diag([0.05**2] * 3 + [np.radians(0.5) ** 2] * 3)
    drifted, fresh = MeshPoints(model.mesh, params), MeshPoints(model.mesh, params)
    at_off, at_truth = initial_state(0.0, off.t, off.q_wxyz, P), initial_state(0.0, truth.t, truth.q_wxyz, P)
    n = drifted.spawn(FrameContext(frames[0], frame, frame, camera, at_off), at_off)
    fresh.spawn(FrameContext(frames[0], frame, frame, camera, at_truth), at_truth)
    assert n > 30 and len(fresh) > 30
    assert np.abs(camera.project(truth.apply(drifted.tracks.X)) - drifted.tracks.uv).max() > 0.5  # (off: they disagree)
    before = drifted._births
    m = drifted.relift(camera, at_truth)
    assert 0.9 * n <= m == len(drifted) == len(drifted.cov_X) == len(drifted.ema)
    assert np.abs(camera.project(truth.apply(drifted.tracks.X)) - drifted.tracks.uv).max() < 1e-6
    common = {tuple(np.round(u, 3)): X for u, X in zip(fresh.tracks.uv, fresh.tracks.X)}
    same = [np.linalg.norm(X - common[tuple(np.round(u, 3))]) for u, X in zip(drifted.tracks.uv, drifted.tracks.X)
            if tuple(np.round(u, 3)) in common]
    assert len(same) > 0.5 * m and max(same) < 1e-6 * model.mesh.extent
    assert np.all(drifted.cohort == before) and drifted._births == before + 1 and not drifted.vouched.any()


def test_mesh_points_alone_follow_a_known_motion(box):
    model, camera, poses, frames = box
    tracker = Tracker(model, camera, TrackerParams(sources=("mesh",)), index=index_for(model))
    tracker.init_pose(poses[0].t, poses[0].q_wxyz)
    steps = [tracker.step(f, k / FPS) for k, f in enumerate(frames)]
    assert [s.status for s in steps] == ["init"] + ["tracking"] * (len(frames) - 1)
    err = np.array([pose_errors(s.t, s.q_wxyz, p, model.mesh) for s, p in zip(steps, poses)])
    d = model.mesh.extent
    assert err[:, 0].mean() < 0.01 * d and err[:, 0].max() < 0.02 * d
    assert err[:, 1].mean() < 1.0 and err[:, 1].max() < 2.0
    assert len(tracker.mesh_points) >= 30 and steps[-1].inliers >= 30
    # they are measured right: at the true pose the tracked points project within ~1 px (0.99 px
    # when born points counted as independent; 1.06 px since a cohort counts as its birth pose)
    uv = camera.project(poses[-1].apply(tracker.mesh_points.tracks.X))
    assert np.median(np.linalg.norm(uv - tracker.mesh_points.tracks.uv, axis=1)) < 1.2


def test_mesh_points_are_kept_when_a_jolt_puts_the_prediction_off(box):
    """A camera jolt moves the whole image 12 px between two frames on a side no trained point
    shows; the prediction knows nothing
    of it. KLT follows the born points to where they went, and nearly all fail the innovation
    gate at the prediction: kept anyway (as the trained points are), the adjustment judges them
    — gated to a handful, the zoo cubes and prisms were lost at the peak of their walks' shake
    ("only 4 textured points agree") with every point tracked (session 42)."""
    model, camera, poses, frames = box
    params = TrackerParams()
    src = MeshPoints(model.mesh, params)
    P = np.diag([0.05**2] * 3 + [np.radians(0.3) ** 2] * 3)  # a confident track
    state = initial_state(0.0, poses[0].t, poses[0].q_wxyz, P)
    grey = cv2.cvtColor(frames[0], cv2.COLOR_BGR2GRAY)
    ctx0 = FrameContext(frames[0], make_frame(grey), make_frame(grey), camera, state)
    n = src.spawn(ctx0, state)
    assert n > 30
    jolted = np.roll(frames[0], (5, 11), axis=(0, 1))  # 11 px right, 5 px down
    ctx = FrameContext(jolted, make_frame(cv2.cvtColor(jolted, cv2.COLOR_BGR2GRAY)), ctx0.frame, camera, state)
    ctx.anchored = False  # a side no trained point shows: the born points are all the texture
    block = src.measure(ctx, {})
    assert len(block) > 0.8 * n
    moved = block.uv - camera.project(poses[0].apply(block.X))
    assert np.allclose(np.median(moved, axis=0), [11.0, 5.0], atol=0.5)  # where they went, not where predicted


@pytest.mark.parametrize("source", ["mesh", "trained"])
@pytest.mark.parametrize("share, kept_all", [(0.3, True), (0.7, False)])
def test_points_are_gated_only_when_most_of_them_pass(box, monkeypatch, source, share, kept_all):
    """Gated to the third the prediction still expected, the cubes' born points dwindled over a
    shake's frames until the track was lost again: the gate applies only when at least half pass
    — for the trained points as for the born ones (one rule, points.unless_off)."""
    import quatrack.recognition.tracker.mesh_points as mp
    import quatrack.recognition.tracker.sources as sources

    model, camera, poses, frames = box
    born = MeshPoints(model.mesh, TrackerParams())
    state = initial_state(0.0, poses[0].t, poses[0].q_wxyz, np.diag([0.05**2] * 3 + [np.radians(0.3) ** 2] * 3))
    frame = make_frame(cv2.cvtColor(frames[0], cv2.COLOR_BGR2GRAY))
    ctx = FrameContext(frames[0], frame, frame, camera, state)
    n = born.spawn(ctx, state)
    ctx.anchored = False
    src = born
    if source == "trained":  # the same corners, as trained model points
        src = sources.TrainedPoints(model.mesh, TrackerParams())
        src.tracks = born.tracks
    fake_gate = lambda camera, block, prior, chi2: np.arange(len(block)) < share * len(block)  # noqa: E731
    monkeypatch.setattr(mp, "gate", fake_gate)
    monkeypatch.setattr(sources, "gate", fake_gate)
    block = src.measure(ctx, {})
    assert n > 30
    assert (len(block) > 0.9 * n) if kept_all else (len(block) < 0.75 * n)


@pytest.fixture(scope="module")
def cube(tmp_path_factory):
    """A 6 cm cube trained from one rendered photo (no synthetic views), and a camera orbiting
    it by 120° in 1.5 s: the photo shows three faces; the last frames show two it never did."""
    w = one_photo_orbit(tmp_path_factory.mktemp("cube"), 120.0, 45)
    return w.model, w.cam, w.poses, w.frames


def _orbit(cube, sources):
    model, cam, poses, frames = cube
    tracker = Tracker(model, cam, TrackerParams(sources=sources), index=index_for(model))
    tracker.init_pose(poses[0].t, poses[0].q_wxyz)
    return [tracker.step(f, k / FPS) for k, f in enumerate(frames)]


def test_a_turn_to_faces_no_photo_shows_is_followed_to_the_end(cube):
    model, _, poses, _ = cube
    d = model.mesh.extent
    steps = _orbit(cube, ("trained", "mesh", "edges"))
    assert all(s.has_pose for s in steps), [s.reason for s in steps if not s.has_pose][:3]
    err = np.array([pose_errors(s.t, s.q_wxyz, p, model.mesh) for s, p in zip(steps, poses)])
    assert err[:, 0].mean() < 0.01 * d and err[:, 1].mean() < 1.0
    assert err[:, 0].max() < 0.025 * d and err[:, 1].max() < 2.0
    # the trained points alone cannot: their faces turn away and the track is lost (re-acquisition
    # near the last pose may pick it up again afterwards)
    alone = _orbit(cube, ("trained",))
    assert any(s.status == "lost" for s in alone[1:])


def test_an_edge_is_found_at_its_subpixel_position():
    from quatrack.recognition.tracker.edges import search_edges

    # a vertical step edge at x = 100.3 (anti-aliased), searched from x = 96 along +x
    x = np.arange(200, dtype=float)
    row = np.clip(x - 100.3 + 0.5, 0.0, 1.0) * 120 + 60
    img = np.tile(row, (80, 1)).astype(np.float32)
    g = cv2.GaussianBlur(img, (0, 0), 1.0)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    uv = np.array([[96.0, 40.0], [104.0, 30.0], [150.0, 20.0]])
    normal = np.array([[1.0, 0.0], [-1.0, 0.0], [1.0, 0.0]])
    meas, found = search_edges(gx, gy, uv, normal, np.array([8.0, 8.0, 8.0]), 6.0)
    assert found.tolist() == [True, True, False]  # the third has no edge within reach
    # the edge between pixels 100 and 101 (grey 60 → 120): gradient centred at 100.3 − 0.5 + 0.5
    assert np.abs(meas[:2, 0] - 100.3).max() < 0.25 and np.allclose(meas[:2, 1], [40.0, 30.0])


def test_an_edge_with_a_rival_in_reach_reports_the_rival():
    """A crease beside a parallel line of the print: two aligned gradient maxima 8 px apart
    within the search's reach. The stronger is measured; its rival's distance is reported when
    the rival reaches ``ambiguity ×`` the winner's strength, 0 when it does not or when the
    edge is alone in reach (then the search is exactly :func:`search_edges`)."""
    from quatrack.recognition.tracker.edges import edge_candidates, search_edges

    x = np.arange(200, dtype=float)

    def gradients(steps):  # (position, height) of vertical step edges, each anti-aliased
        row = 60 + sum(h * np.clip(x - p + 0.5, 0.0, 1.0) for p, h in steps)
        g = cv2.GaussianBlur(np.tile(row, (40, 1)).astype(np.float32), (0, 0), 1.0)
        return (cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125),
                cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125))

    uv, normal, radius = np.array([[100.0, 20.0]]), np.array([[1.0, 0.0]]), np.array([10.0])
    gx, gy = gradients([(96.0, 100.0), (104.0, 60.0)])  # the rival at 60 % of the winner
    meas, found, gap = edge_candidates(gx, gy, uv, normal, radius, 6.0, ambiguity=0.5)
    assert found[0] and abs(meas[0, 0] - 96.0) < 0.3 and gap[0] == pytest.approx(8.0)
    np.testing.assert_array_equal(meas, search_edges(gx, gy, uv, normal, radius, 6.0)[0])
    assert edge_candidates(gx, gy, uv, normal, radius, 6.0, ambiguity=0.7)[2][0] == 0.0
    gx, gy = gradients([(96.0, 100.0)])  # alone in reach
    assert edge_candidates(gx, gy, uv, normal, radius, 6.0, ambiguity=0.5)[2][0] == 0.0


@pytest.mark.parametrize("turn_deg", [90.0, 12.0])
def test_re_anchoring_refuses_matches_that_agree_with_another_pose(box, turn_deg):
    """Texture repeated on another face (a cube's sides cut from one photo) gives SIFT matches
    consistent among themselves with the object turned by 90°, and a cube's edges agree with
    that pose too: merged as a fresh anchor, they turned a right track (and a user's right
    starting pose) by 90°. Matches whose own pose lies beyond the 5 %/5° criterion from the
    track's are refused (0 merged, tracks unchanged); the same points matched where the pose
    puts them are merged."""
    from types import SimpleNamespace

    from quatrack.recognition.match import Matches
    from quatrack.recognition.tracker.anchor import Anchor
    from quatrack.recognition.tracker.points import Tracks
    from quatrack.viewsets.novel import rotate_about_centre

    model, camera, poses, _ = box
    pose, mesh = poses[3], model.mesh
    other = rotate_about_centre(pose, mesh.centre, np.radians([0.0, turn_deg, 0.0]))
    X = np.concatenate([vs.points3d for vs in model.viewsets])
    X = X[visible_points(mesh, camera, other, X)[0] & visible_points(mesh, camera, pose, X)[0]][:60]
    assert len(X) >= 30

    def merge(at):
        n = len(X)
        m = Matches(np.arange(n), np.arange(n), np.zeros(n, int), X, np.zeros((n, 3)), np.zeros(n))
        feats = SimpleNamespace(keypoints=camera.project(at.apply(X)))
        kept = Tracks(X[:5], camera.project(pose.apply(X[:5])))
        return Anchor(mesh, None, TrackerParams()).merge(feats, m, camera, pose, kept, wide=False), kept

    (tracks, n, replaced), kept = merge(other)
    assert n == 0 and not replaced and tracks is kept
    (tracks, n, replaced), _ = merge(pose)
    assert n >= 30 and len(tracks) >= n


def test_a_start_whose_anchors_disagree_goes_on_the_mesh(box, monkeypatch):
    """A given pose whose SIFT anchors near it disagree among themselves (matched on repeated
    texture: no pose fits them) is not refused for that: like a pose with too few anchors, the
    track starts on corners born on the mesh once the model's edges confirm the pose, and
    follows the frames; a pose the edges refute is still refused."""
    from quatrack.recognition.tracker.anchor import Anchor
    from quatrack.recognition.tracker.points import Tracks
    from quatrack.tracking import quaternion as quat

    model, camera, poses, frames = box
    rng = np.random.default_rng(3)
    X = np.concatenate([vs.points3d for vs in model.viewsets])[:40]

    def scattered(self, img, cam, pose, tracks, wide, alternative=None):  # 40 matches, no consensus
        return Tracks(X, cam.project(pose.apply(X)) + rng.uniform(-40, 40, (len(X), 2))), len(X), False

    monkeypatch.setattr(Anchor, "now", scattered)
    tracker = Tracker(model, camera, TrackerParams(), index=index_for(model))
    tracker.init_pose(poses[0].t, poses[0].q_wxyz)
    first = tracker.step(frames[0], 0.0)
    assert first.status == "init" and "born on the mesh" in first.reason
    monkeypatch.undo()
    steps = [tracker.step(frames[k], k / FPS) for k in range(1, 6)]
    assert all(s.status == "tracking" for s in steps)
    assert max(pose_errors(s.t, s.q_wxyz, poses[k], model.mesh)[0] for k, s in enumerate(steps, 1)) < 0.02 * model.mesh.extent
    monkeypatch.setattr(Anchor, "now", scattered)
    wrong = Tracker(model, camera, TrackerParams(), index=index_for(model))
    wrong.init_pose(poses[0].t + [3.0, 0.0, 0.0], quat.multiply(quat.from_rotvec(np.radians([0, 15, 0])), poses[0].q_wxyz))
    assert wrong.step(frames[0], 0.0).status == "lost"


def test_model_edges_are_measured_where_the_true_pose_puts_them(box):
    """The edge source alone on a rendered frame, predicted 0.4 cm and 0.5° off: its samples
    move to the true edges (across-edge residual at the true pose), away from the prediction."""
    from quatrack.recognition.tracker.edges import ModelEdges
    from quatrack.tracking import quaternion as quat
    from quatrack.tracking.pose import Pose

    model, camera, poses, frames = box
    truth = poses[3]
    off = Pose(quat.multiply(quat.from_rotvec(np.radians([0.3, -0.4, 0.0])), truth.q_wxyz), truth.t + [0.4, -0.2, 0.0])
    prior = initial_state(0.0, off.t, off.q_wxyz, np.diag([0.3**2] * 3 + [np.radians(0.7) ** 2] * 3))
    frame = make_frame(cv2.cvtColor(frames[3], cv2.COLOR_BGR2GRAY))
    block = ModelEdges(model.mesh, TrackerParams()).measure(FrameContext(frames[3], frame, None, camera, prior), {})
    assert len(block) > 60
    n = np.linalg.eigh(block.C)[1][:, :, 0]  # the across-edge direction (smallest variance)

    def across(pose):
        return np.abs(np.einsum("ij,ij->i", block.uv - camera.project(pose.apply(block.X)), n))

    # ~half the samples land within 1 px of the true edges (the rest on the print's own edges
    # next to them: outliers for the robust adjustment); almost none stay at the prediction
    assert np.mean(across(truth) < 1.0) > 0.4 and np.mean(across(off) < 1.0) < 0.1
    # taking the strongest whatever else is in reach (edge_ambiguity None) keeps more samples,
    # a smaller share of them on the true edges: the dropped ones had a rival in reach
    every = ModelEdges(model.mesh, TrackerParams(edge_ambiguity=None)).measure(
        FrameContext(frames[3], frame, None, camera, prior), {})
    n_every = np.linalg.eigh(every.C)[1][:, :, 0]
    on_truth = np.abs(np.einsum("ij,ij->i", every.uv - camera.project(truth.apply(every.X)), n_every)) < 1.0
    assert len(every) > len(block) and np.mean(across(truth) < 1.0) > on_truth.mean() + 0.05


def test_one_klt_call_for_every_point_source_measures_what_one_call_each_does(box):
    """follow_together follows the trained and the mesh-born tracks in one pyramidal-LK call:
    each source's block is exactly the block of its own call."""
    from quatrack.recognition.tracker.sources import TrainedPoints, follow_together

    model, camera, poses, frames = box
    params = TrackerParams()
    P = np.diag([0.05**2] * 3 + [np.radians(0.3) ** 2] * 3)
    born = MeshPoints(model.mesh, params)
    f0, f1 = (make_frame(cv2.cvtColor(frames[k], cv2.COLOR_BGR2GRAY)) for k in (0, 1))
    assert born.spawn(FrameContext(frames[0], f0, None, camera, initial_state(0.0, poses[0].t, poses[0].q_wxyz, P)),
                      initial_state(0.0, poses[0].t, poses[0].q_wxyz, P)) > 40
    trained = TrainedPoints(model.mesh, params)
    half = np.arange(len(born)) % 2 == 0
    trained.tracks, born.tracks = born.tracks.keep(half), born.tracks.keep(~half)
    born.cov_X, born.cohort, born.ema = born.cov_X[~half], born.cohort[~half], born.ema[~half]
    prior = initial_state(1 / FPS, poses[1].t, poses[1].q_wxyz, P)
    alone = [s.measure(FrameContext(frames[1], f1, f0, camera, prior), {}) for s in (trained, born)]
    ctx = FrameContext(frames[1], f1, f0, camera, prior)
    follow_together(ctx, [trained, born], {})
    assert set(ctx.followed) == {"trained", "mesh"}
    together = [s.measure(ctx, {}) for s in (trained, born)]
    for a, b in zip(alone, together):
        assert len(a) > 15
        np.testing.assert_array_equal(a.X, b.X)
        np.testing.assert_array_equal(a.uv, b.uv)
        np.testing.assert_array_equal(a.C, b.C)


def _points_and_edges_disagree(box, points: str, second_hand: bool = False, params=None):
    """A tracker one frame after the truth (``params``: TrackerParams()'s by default); 60 points
    (source ``points``) where the object is, and three times as many edge samples that all say it
    is 3 px to the right (a search locked onto the print beside each outline), adjusted jointly.
    Returns the tracker, the blocks, the stacked block, the joint inlier mask and ``px``: a
    state's centre's x offset from the truth."""
    from quatrack.recognition.tracker.points import PointBlock
    from quatrack.tracking.pose import Pose

    model, camera, poses, frames = box
    tracker = Tracker(model, camera, params or TrackerParams(), index=index_for(model))
    tracker.init_pose(poses[0].t, poses[0].q_wxyz)
    tracker.step(frames[0], 0.0)
    tracker._second_hand = second_hand
    truth = tracker.filter.state.pose
    tracker.filter.predict(1.0 / FPS)
    rng = np.random.default_rng(3)
    V = model.mesh.vertices
    X = V[rng.integers(len(V), size=(300, 3))].mean(axis=1)  # points on and in the box
    z = truth.apply(model.mesh.centre[None])[0, 2]
    off = Pose(truth.q_wxyz, truth.t + np.array([3.0 * z / camera.fx, 0.0, 0.0]))  # 3 px right
    uv_t = camera.project(truth.apply(X[:60])) + rng.normal(0.0, 0.3, (60, 2))
    uv_e = camera.project(off.apply(X[60:])) + rng.normal(0.0, 0.3, (240, 2))
    C_t = np.broadcast_to(np.eye(2), (60, 2, 2)).copy()
    C_e = np.broadcast_to(np.diag([1.0, 2500.0]), (240, 2, 2)).copy()  # across the edge: x
    empty = PointBlock("", np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2, 2)))
    pts = PointBlock(points, X[:60], uv_t, C_t)
    blocks = [pts, empty, PointBlock("edges", X[60:], uv_e, C_e)] if points == "trained" else \
        [empty, pts, PointBlock("edges", X[60:], uv_e, C_e)]
    block = PointBlock.stack(blocks)
    ok, _, inl = tracker._adjust(block)
    centre = model.mesh.centre[None]
    px = lambda s: (camera.project(s.pose.apply(centre)) - camera.project(truth.apply(centre)))[0, 0]
    assert ok and inl[:60].sum() >= 50  # the points still count as inliers…
    assert px(tracker.filter.state) > 1.5  # …of a pose the edges dragged more than half-way
    return tracker, blocks, block, inl, px


def test_edges_cannot_outvote_the_trained_points(box):
    """The score test (Tracker._unless_outvoted) sees the trained points disagree with the joint
    pose the edges dragged and adjusts again without the edges."""
    from quatrack.recognition.tracker.points import score_statistic

    tracker, blocks, block, inl, px = _points_and_edges_disagree(box, "trained")
    camera = box[1]
    assert score_statistic(camera, blocks[0].keep(inl[:60]), tracker.filter.state) > TrackerParams().texture_chi2
    kept, _ = tracker._unless_outvoted(blocks, block, inl)
    assert abs(px(tracker.filter.state)) < 0.3 and not kept[60:].any() and kept[:60].sum() >= 55


def test_points_that_outvote_the_edges_far_withhold_the_pose(box):
    """Where the textured points outvote the edges (Tracker._unless_outvoted) and their own pose lies
    more than ``outvote_max_shift`` of the 5 %/5° criterion from the joint one, the conflict is
    reported — its size, the two poses' pose_shift — and the frame's pose is withheld in doubt."""
    from quatrack.recognition.evidence import pose_shift

    for limit, conflict in ((TrackerParams().outvote_max_shift, False), (0.05, True)):
        tracker, blocks, block, inl, px = _points_and_edges_disagree(box, "trained",
                                                                     params=TrackerParams(outvote_max_shift=limit))
        joint = tracker.filter.state
        kept, shift = tracker._unless_outvoted(blocks, block, inl)
        assert abs(px(tracker.filter.state)) < 0.3 and not kept[60:].any()  # (outvoted, as ever)
        moved = pose_shift(tracker.filter.state.pose, joint.pose, box[0].mesh)
        assert 0.05 < moved < TrackerParams().outvote_max_shift  # (3 px on the cookie box: ~0.12)
        assert shift == (moved if conflict else None)

    # in a step: withheld, the track goes on (in doubt) and says why
    model, camera, poses, frames = box
    tracker = Tracker(model, camera, TrackerParams(outvote_max_shift=0.05), index=index_for(model))
    tracker.init_pose(poses[0].t, poses[0].q_wxyz)
    tracker.step(frames[0], 0.0)
    tracker._unless_outvoted = lambda blocks, block, inl: (inl, 0.8)
    step = tracker.step(frames[1], 1.0 / FPS)
    assert step.status == "lost" and tracker.tracking and tracker._doubted == 1, step
    assert step.reason.startswith("the textured points and the model's edges put the object 0.80 of the 5 %/5° "
                                  "criterion apart: the pose is withheld while the track goes on"), step.reason


def test_mesh_points_judge_the_edges_only_in_a_second_hand_track(box):
    """Without trained points in view, the points born on the mesh judge the edges in a track
    re-found on keyframes (their texture is all there is); in a first-hand track they do not
    (lifted at the tracker's own poses, they may be the ones that are off) and the joint pose stays."""
    tracker, blocks, block, inl, px = _points_and_edges_disagree(box, "mesh", second_hand=True)
    kept, _ = tracker._unless_outvoted(blocks, block, inl)
    assert abs(px(tracker.filter.state)) < 0.3 and not kept[60:].any() and kept[:60].sum() >= 55

    tracker, blocks, block, inl, px = _points_and_edges_disagree(box, "mesh", second_hand=False)
    joint = px(tracker.filter.state)
    kept, _ = tracker._unless_outvoted(blocks, block, inl)
    assert px(tracker.filter.state) == joint and np.array_equal(kept, inl)

def _contour_at(box, frame_k: int, grey: bool = False):
    """The outline source on a rendered frame: colours learned at the true pose, then measured
    from a prediction 0.4 cm and 0.5° off (or 4 px sideways). Returns the block, the truth and the
    prediction."""
    from quatrack.recognition.tracker.contour import Contour
    from quatrack.tracking import quaternion as quat
    from quatrack.tracking.pose import Pose

    model, camera, poses, frames = box
    img = frames[frame_k]
    if grey:
        img = cv2.cvtColor(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    truth = poses[frame_k]
    frame = make_frame(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    src = Contour(model.mesh, TrackerParams())
    P = np.diag([0.3**2] * 3 + [np.radians(0.7) ** 2] * 3)
    src.measure(FrameContext(img, frame, None, camera, initial_state(0.0, truth.t, truth.q_wxyz, P)), {})
    assert src.colours.ready
    off = Pose(quat.multiply(quat.from_rotvec(np.radians([0.3, -0.4, 0.0])), truth.q_wxyz), truth.t + [0.4, -0.2, 0.0])
    block = src.measure(FrameContext(img, frame, None, camera, initial_state(0.0, off.t, off.q_wxyz, P)), {})
    return block, truth, off


@pytest.mark.parametrize("grey", [False, True])
def test_the_outline_is_found_where_the_true_pose_puts_it(box, grey):
    """The outline source (recognition/tracker/contour.py) on a rendered frame over clutter,
    predicted 0.4 cm and 0.5° off: its lines find the outline where the true pose projects it,
    away from the prediction — in colour and on a grey image alike."""
    model, camera, _, _ = box
    block, truth, off = _contour_at(box, 3, grey)
    assert len(block) > 40
    n = np.linalg.eigh(block.C)[1][:, :, 0]  # across the outline (the smallest variance)

    def across(pose):
        return np.abs(np.einsum("ij,ij->i", block.uv - camera.project(pose.apply(block.X)), n))

    # each line's σ across (≥ contour_sigma_min_px) says how sure it is: in units of it the
    # outline lies at the truth, several σ from the prediction
    sd = np.sqrt(np.linalg.eigvalsh(block.C)[:, 0])
    assert sd.min() >= TrackerParams().contour_sigma_min_px - 1e-9 and sd.max() > sd.min()
    at_truth, at_off = np.median(across(truth) / sd), np.median(across(off) / sd)
    assert at_truth < 0.8 and at_off > 1.5 and at_off > 2.5 * at_truth
    # colour tells the box from the clutter better than brightness alone: sharper lines
    assert np.median(across(truth)) < (2.0 if grey else 0.6) < np.median(across(off)) / 2.5
    assert np.median(sd) < (3.5 if grey else 1.6)


@pytest.mark.parametrize("gain, cast", [(0.6, (0.85, 1.0, 1.15)), (1.5, (1.0, 1.0, 1.0))])
def test_the_outline_is_found_after_the_light_changes(box, gain, cast):
    """Colours learned under one light, the outline searched under another (the image's gain
    times a colour cast, as the zoo's lighting change and a camera's auto-exposure do): the
    pixels are read relative to the frame's mean colour (``contour_normalise``, off by default),
    so the lines
    still find the outline where the true pose puts it. Read raw, the learned colours no longer
    match and the lines land several pixels off."""
    from dataclasses import replace

    from quatrack.recognition.tracker.contour import Contour
    from quatrack.tracking import quaternion as quat

    model, camera, poses, frames = box
    truth = poses[3]
    before = frames[3]
    after = np.clip(before.astype(np.float32) * gain * np.array(cast, np.float32), 0, 255).astype(np.uint8)
    P = np.diag([0.3**2] * 3 + [np.radians(0.7) ** 2] * 3)
    off = Pose(quat.multiply(quat.from_rotvec(np.radians([0.3, -0.4, 0.0])), truth.q_wxyz), truth.t + [0.4, -0.2, 0.0])

    def found(normalise: bool):
        src = Contour(model.mesh, replace(TrackerParams(), contour_normalise=normalise))
        for img, pose in ((before, truth), (after, off)):
            frame = make_frame(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
            block = src.measure(FrameContext(img, frame, None, camera, initial_state(0.0, pose.t, pose.q_wxyz, P)), {})
        n = np.linalg.eigh(block.C)[1][:, :, 0]
        return [float(np.median(np.abs(np.einsum("ij,ij->i", block.uv - camera.project(p.apply(block.X)), n))))
                for p in (truth, off)]

    at_truth, at_off = found(True)
    assert at_truth < 1.0 and at_off > 2.5 * at_truth
    raw_truth, _ = found(False)
    assert raw_truth > 3.0 * at_truth


def test_outline_lines_stop_at_the_objects_far_side():
    """A line across a thin object reads its inside only up to the far side: beyond it lies
    background again, which would otherwise pull the outline inwards."""
    from quatrack.recognition.tracker.contour import outline_posterior, side_runs

    x = np.arange(-12.0, 13.0)
    on = (x <= 0) & (x >= -4)  # object 5 px thick, background beyond its far side
    p = np.where(on, 0.9, 0.1)[None]
    ok = side_runs(on[None], x, np.array([1.0]))
    assert not ok[0, x < -6].any() and ok[0, x >= -4].all()
    mu_all, _, _ = outline_posterior(p, x, np.array([6.0]), 0.43, 1.3)
    mu_kept, _, _ = outline_posterior(np.where(ok, p, 0.5), x, np.array([6.0]), 0.43, 1.3)
    assert abs(mu_kept[0] - 0.5) < abs(mu_all[0] - 0.5)


def test_outline_and_mesh_points_follow_a_known_motion(box):
    """The outline with the points born on the mesh, no trained point and no edge: they follow
    the rendered box through its motion."""
    model, camera, poses, frames = box
    tracker = Tracker(model, camera, TrackerParams(sources=("mesh", "contour")), index=index_for(model))
    tracker.init_pose(poses[0].t, poses[0].q_wxyz)
    steps = [tracker.step(f, k / FPS) for k, f in enumerate(frames)]
    assert all(s.has_pose for s in steps)
    err = np.array([pose_errors(s.t, s.q_wxyz, p, model.mesh) for s, p in zip(steps, poses)])
    d = model.mesh.extent
    assert err[:, 0].mean() < 0.01 * d and err[:, 1].mean() < 1.0
    assert any(s.timings_ms.get("contour") is not None for s in steps[1:])
    # no trained point: on probation at first, the edges judge the poses (the "judge" stage)
    assert any(s.timings_ms.get("judge") is not None for s in steps[1:])


def test_the_outline_posterior_is_the_whole_product():
    """outline_posterior sums the flat far terms of log P(d) by running sums and evaluates only
    the terms near each candidate: the same mean and spread as the whole product, on noisy
    random lines (the outline anywhere in reach, pixels that say nothing among them)."""
    from quatrack.recognition.tracker.contour import outline_posterior

    alpha, slope = 0.43, 1.3
    rng = np.random.default_rng(0)
    for R in (3, 12, 20):
        x = np.arange(-(R + 8), R + 9, dtype=float)
        edge = rng.uniform(-R, R, 200)
        p = np.clip(np.where(x[None] < edge[:, None], 0.8, 0.2) + rng.normal(0, 0.25, (200, len(x))), 0.01, 0.99)
        p[rng.random(p.shape) < 0.1] = 0.5
        radius = rng.uniform(3, R, 200) if R > 3 else np.full(200, 3.0)
        d = np.arange(-R, R + 1, dtype=float)
        hF = 0.5 - alpha * np.tanh((x[None, :] - d[:, None]) / (2.0 * slope))
        ll = np.log((1 - p)[:, None, :] + hF[None] * (2 * p - 1)[:, None, :]).sum(axis=2)
        ll = np.where(np.abs(d)[None] <= radius[:, None], ll, -np.inf)
        P = np.exp(ll - ll.max(axis=1, keepdims=True))
        P /= P.sum(axis=1, keepdims=True)
        mu = P @ d
        sd = np.sqrt(np.einsum("nd,nd->n", P, (d[None] - mu[:, None]) ** 2))
        mu_f, var_f, _ = outline_posterior(p, x, radius, alpha, slope)
        assert np.abs(mu_f - mu).max() < 0.02 and np.abs(np.sqrt(var_f) - sd).max() < 0.02
        within = np.abs(edge) < radius - 1.0  # (and the lines find the outlines within their reach)
        assert np.abs(mu - edge)[within].mean() < 1.0


def _jolted(box, stop: int, px_per_frame: float):
    """The box's frames with a slide right at ``px_per_frame`` that stops dead at frame ``stop``."""
    model, camera, poses, _ = box
    renderer = Renderer.from_spec(EXAMPLE / "object.json")
    rng = np.random.default_rng(5)
    bg = clutter_background(4)
    out_poses, frames = [], []
    for k, p in enumerate(poses[: stop + 4]):
        z = p.apply(model.mesh.centre[None])[0, 2]
        shifted = Pose(p.q_wxyz, p.t + np.array([px_per_frame * min(k, stop) * z / camera.fx, 0.0, 0.0]))
        out_poses.append(shifted)
        frames.append(compose(renderer, camera, shifted, bg, rng))
    return out_poses, frames


def test_a_dead_stop_is_followed_by_the_outline_sources_too(box):
    """The box slides right at 45 px a frame and stops dead: the prediction overshoots by 45 px.
    The edges and the outline search a few px round the prediction; they must search round the
    points' own pose instead (Tracker._recentred), or they lock onto the print beside the
    prediction and outvote the points (with ``recentre_px=0`` the pose is lost at the stop)."""
    model, camera, _, _ = box
    poses, frames = _jolted(box, stop=8, px_per_frame=45.0)
    tracker = Tracker(model, camera, TrackerParams(), index=index_for(model))
    tracker.init_pose(poses[0].t, poses[0].q_wxyz)
    steps = [tracker.step(f, k / FPS) for k, f in enumerate(frames)]
    d = model.mesh.extent
    for k, (s, p) in enumerate(zip(steps, poses)):
        assert s.has_pose, (k, s.reason)
        dt, dr = pose_errors(s.t, s.q_wxyz, p, model.mesh)
        assert dt < 0.03 * d and dr < 3.0, (k, dt / d, dr)


def test_a_pose_confirmed_after_a_doubt_is_tested_strictly_for_doubt_frames_more(box, monkeypatch):
    """The audit doubts one pose (scripted: the edge refit's first verdict is 0.9 of the
    criterion, every later one 0.1): that pose is withheld, the next is confirmed and reported,
    and each of the ``doubt_frames`` frames after it is judged by the edges too — not only every
    ``audit_every``-th frame (in the zoo's blur one confirmation let three frames 5–8° off
    through unjudged)."""
    model, camera, poses, frames = box
    # (the audit every audit_every-th frame, anchored or not: the first edge verdict must be the
    # audit's, before any view is captured, whose strict test would take the scripted 0.9)
    params = TrackerParams(audit_every_anchored=None)
    tracker = Tracker(model, camera, params, index=index_for(model))
    judged: list[int] = []

    def scripted(self, gray, pose, agreement=True, points=True):
        judged.append(self._frame)
        return 0.9 if len(judged) == 1 else 0.1

    monkeypatch.setattr(Tracker, "_edge_shift", scripted)
    tracker.init_pose(poses[0].t, poses[0].q_wxyz)
    steps = [tracker.step(f, k / FPS) for k, f in enumerate(frames)]
    doubted = judged[0]  # (frames count from 0, as the steps do)
    withheld = steps[doubted]
    assert withheld.status == "lost" and withheld.reason.endswith("the pose is withheld while the track goes on")
    confirmed = doubted + 1
    assert steps[confirmed].status == "tracking"
    after = set(range(confirmed + 1, confirmed + 1 + params.doubt_frames))
    assert confirmed + params.doubt_frames < len(frames) and after <= set(judged), sorted(judged)


@pytest.mark.parametrize("confirm", [0.25, None])
def test_a_doubted_pose_is_reported_again_only_on_stronger_evidence(box, monkeypatch, confirm):
    """The audit doubts one pose (scripted refit verdicts: 0.9 of the criterion, then 0.4 twice,
    then 0.1): with ``doubt_confirm_shift`` 0.25 the two frames at 0.4 — a verdict that passes a
    pose never doubted (``max_edge_shift`` 0.5) — stay withheld, and the track is reported again
    at 0.1; without it (None) the first 0.4 reports it. (A wrong track 17 % off, doubted for
    five frames, was reported again on a verdict of 0.42: bench/RESULTS.md, session 39.)"""
    model, camera, poses, frames = box
    params = TrackerParams(audit_every_anchored=None, doubt_confirm_shift=confirm)
    tracker = Tracker(model, camera, params, index=index_for(model))
    verdicts = iter([0.9, 0.4, 0.4])
    judged: list[int] = []

    def scripted(self, gray, pose, agreement=True, points=True):
        judged.append(self._frame)
        return next(verdicts, 0.1)

    monkeypatch.setattr(Tracker, "_edge_shift", scripted)
    tracker.init_pose(poses[0].t, poses[0].q_wxyz)
    steps = [tracker.step(f, k / FPS) for k, f in enumerate(frames)]
    doubted = judged[0]
    withheld = [k for k, st in enumerate(steps) if st.status == "lost"]
    assert all(steps[k].reason.endswith("the pose is withheld while the track goes on") for k in withheld)
    if confirm is None:
        assert withheld == [doubted]
    else:
        assert withheld == [doubted, doubted + 1, doubted + 2]
    assert steps[withheld[-1] + 1].status == "tracking"


@pytest.mark.parametrize("confirm", [0.25, None])
def test_a_pose_settled_on_the_edges_must_be_where_they_converge(box, monkeypatch, confirm):
    """Tracker._edge_settled (:func:`recognition.tracker.edge_tests.settle_on_edges`) on scripted
    edge refits (shift of the first refit, then of the second from the refitted pose): a first
    refit within ``max_edge_shift`` (0.5) keeps the pose; one beyond recognition's tolerance (1.0)
    refuses it; otherwise the refitted pose is taken only if a second refit from it moves it by at
    most ``doubt_confirm_shift`` (0.25; None: 0.5) and by at most half the first. Why 0.25: the
    zoo's wide box re-found 10.4 % off was refitted to 6.9 %, and a second refit moving it by 0.34
    (half the first, 0.72, is 0.36) passed it: the edges were still converging, and the track
    reported two poses 7 % off (bench/RESULTS.md, session 40)."""
    from quatrack.recognition.evidence import EdgeFit

    model, camera, poses, _ = box
    tracker = Tracker(model, camera, TrackerParams(doubt_confirm_shift=confirm), index=index_for(model))
    start, refitted = poses[0], poses[1]

    def settle(*shifts):
        fits = iter([EdgeFit(200, shift=shifts[0], pose=refitted)] + [EdgeFit(200, shift=s, pose=poses[2]) for s in shifts[1:]])
        asked = []

        def scripted(self, gray, pose, agreement=True, points=True):
            asked.append((pose, points))
            return next(fits)

        monkeypatch.setattr(Tracker, "_edge_refit", scripted)
        settled = tracker._edge_settled(None, start)
        assert [p for p, _ in asked] == [start, refitted][:len(asked)] and not any(pts for _, pts in asked)  # (edges alone)
        return settled

    assert settle(0.4) is start
    assert settle(1.2) is None
    assert settle(0.72, 0.1) is refitted
    assert settle(0.72, 0.4) is None  # (more than half the first: not converging)
    assert (settle(0.72, 0.34) is None) == (confirm is not None)


def _edge_candidates_numpy(gx, gy, uv, normal, radius, min_grad, ambiguity=1.0):
    """``edge_candidates`` as it was written in numpy (a samples × offsets array per step),
    before it was compiled: the reference the compiled search must equal bit for bit."""
    h, w = gx.shape
    rmax = int(np.ceil(radius.max())) if len(radius) else 0
    offs = np.arange(-rmax, rmax + 1, dtype=float)
    P = uv[:, None, :] + offs[None, :, None] * normal[:, None, :]
    ui = np.clip(np.rint(P[..., 0]).astype(int), 0, w - 1)
    vi = np.clip(np.rint(P[..., 1]).astype(int), 0, h - 1)
    ex, ey = gx[vi, ui], gy[vi, ui]
    gn = np.abs(ex * normal[:, None, 0] + ey * normal[:, None, 1])
    mag = np.hypot(ex, ey)
    valid = (np.abs(offs)[None, :] <= radius[:, None]) & (gn >= 0.9 * mag) & (mag >= min_grad)
    inside = (P[..., 0] >= 0) & (P[..., 1] >= 0) & (P[..., 0] <= w - 1) & (P[..., 1] <= h - 1)
    score = np.where(valid & inside, gn, -1.0)
    rows = np.arange(len(uv))
    j = np.argmax(score, axis=1)
    best = score[rows, j]
    found = best > 0
    gap = np.zeros(len(uv))
    if ambiguity < 1.0 and len(uv):
        left, right = np.roll(score, 1, axis=1), np.roll(score, -1, axis=1)
        left[:, 0], right[:, -1] = -1.0, -1.0
        peak = (score > 0) & (score >= left) & (score >= right)
        rivals = np.where(peak & (np.abs(np.arange(len(offs))[None, :] - j[:, None]) > 2), score, 0.0)
        k = np.argmax(rivals, axis=1)
        gap = np.where(found & (rivals[rows, k] >= ambiguity * best), np.abs(offs[k] - offs[j]), 0.0)
    jl, jr = np.clip(j - 1, 0, len(offs) - 1), np.clip(j + 1, 0, len(offs) - 1)
    a, b, c = (np.maximum(score[rows, k], 0.0) for k in (jl, j, jr))
    den = a - 2 * b + c
    frac = np.where((jl != j) & (jr != j) & (den < 0), 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    off = offs[j] + np.clip(frac, -0.5, 0.5)
    return uv + off[:, None] * normal, found, gap


@pytest.mark.parametrize("seed", range(40))
def test_the_compiled_edge_search_equals_the_numpy_one(seed):
    """The 1-D edge search runs compiled (numba): measured points, found flags and rival gaps
    equal the numpy version's bit for bit, over textured gradients with lines reaching out of
    the image, radii of 2–15 px, strength thresholds that float32 cannot hold exactly (0.1), and
    with and without the rival test."""
    from quatrack.recognition.tracker.edges import edge_candidates

    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(20, 120, 2))
    img = cv2.GaussianBlur(rng.normal(0, 30, (h, w)).astype(np.float32), (0, 0), rng.uniform(0.5, 3.0))
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    n = int(rng.integers(1, 80))
    uv = rng.uniform([-5.0, -5.0], [w + 5.0, h + 5.0], (n, 2))
    a = rng.uniform(0.0, 2 * np.pi, n)
    normal = np.column_stack([np.cos(a), np.sin(a)])
    radius = np.clip(rng.uniform(0.0, 16.0, n), 2.0, 15.0)
    for min_grad in (0.1, 2.0, 6.0):
        for ambiguity in (1.0, 0.5):
            got = edge_candidates(gx, gy, uv, normal, radius, min_grad, ambiguity)
            want = _edge_candidates_numpy(gx, gy, uv, normal, radius, min_grad, ambiguity)
            for g, e in zip(got, want):
                np.testing.assert_array_equal(g, e)
    assert edge_candidates(gx, gy, uv[:0], normal[:0], radius[:0], 6.0, 0.5)[0].shape == (0, 2)

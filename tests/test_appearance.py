"""The appearance evidence (recognition/appearance.py) on rendered frames with known poses.

The zoo cube's faces carry overlapping crops of one photograph, and turned by 90° about its
vertical axis the cube has the same outline (the hexagonal prism by 60°): the case that SIFT consensus and the edges let
through (a tracker re-found it so, session 36). Its texture must tell it apart."""

import cv2
import numpy as np
import pytest

from quatrack.recognition.appearance import _tile_correlations_numpy, texture_agreement, texture_refit, tile_correlations
from quatrack.recognition.evidence import pose_shift, silhouette_inside
from quatrack.recognition.tracker.keyframes import Keyframe, Keyframes
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import planar_groups
from quatrack.viewsets.novel import rotate_about_centre
from quatrack.viewsets.render import render
from quatrack.viewsets.texture import TextureReference
from quatrack.viewsets.viewset import Viewset
from quatrack.testing import zoo as Z

CAM = Z.zoo_camera()


@pytest.fixture(scope="module", params=["cube-m", "hex-prism-m"])
def scene(request):
    """The object's reference view (azimuth 35°, colour) and a frame 15° further round, each
    over a different real background."""
    obj = Z.textured(request.param)
    bgs = Z.real_backgrounds()
    ref_pose = Z.orbit_pose(obj, CAM, 35.0)
    ref = Z.compose(*obj.render(CAM, ref_pose), bgs[0])
    pose = Z.orbit_pose(obj, CAM, 50.0)
    frame = Z.compose(*obj.render(CAM, pose), bgs[1])
    return obj, TextureReference(ref, CAM, ref_pose), frame, pose


def _agreement(obj, frame, pose, refs, **kw):
    return texture_agreement(frame, CAM, pose, obj.mesh, planar_groups(obj.mesh), refs, **kw)


def _turned(obj, pose):
    """The pose turned about the object's vertical (z) axis through its centre by its symmetry
    angle (the cube's 90°, the hexagonal prism's 60°): the same outline, other faces in view."""
    angle = np.pi / 2 if obj.obj.shape == "box" else 2 * np.pi / obj.obj.sides
    return rotate_about_centre(pose, obj.mesh.centre, np.array([0.0, 0.0, angle]))


def test_the_true_pose_agrees_and_the_same_outline_turned_by_a_symmetry_does_not(scene):
    obj, ref, frame, pose = scene
    right = _agreement(obj, frame, pose, [ref])
    assert right.pixels > 5000 and right.ncc > 0.8
    wrong_pose = _turned(obj, pose)
    a = render(obj.mesh, CAM, pose).face >= 0  # the trap: the wrong pose's silhouette is the true one's
    b = render(obj.mesh, CAM, wrong_pose).face >= 0
    assert (a ^ b).sum() < 0.01 * a.sum()
    wrong = _agreement(obj, frame, wrong_pose, [ref])
    assert wrong.pixels > 5000 and wrong.ncc < 0.35, wrong


def test_a_change_of_light_and_colour_cast_leaves_it_alone(scene):
    obj, ref, frame, pose = scene
    gain = np.array([0.85, 1.0, 1.15], np.float32) * 0.6  # B, G, R: the zoo walks' new light
    ramp = np.linspace(0.8, 1.2, frame.shape[1], dtype=np.float32)[None, :, None]
    dim = np.clip(frame.astype(np.float32) * gain * ramp, 0, 255).astype(np.uint8)
    assert _agreement(obj, dim, pose, [ref]).ncc > 0.8
    grey = cv2.cvtColor(dim, cv2.COLOR_BGR2GRAY)  # grey frames against a colour reference
    assert _agreement(obj, grey, pose, [ref]).ncc > 0.8


def test_an_object_half_out_of_the_frame_is_judged_on_what_is_inside(scene):
    obj, ref, _, pose = scene
    d = pose.apply(obj.mesh.centre[None])[0, 2]
    shifted = Pose(pose.q_wxyz, pose.t + np.array([0.5 * CAM.width * d / CAM.fx, 0.0, 0.0]))
    inside = silhouette_inside(obj.mesh, CAM, shifted)[0]
    assert 0.3 < inside < 0.7
    frame = Z.compose(*obj.render(CAM, shifted), Z.real_backgrounds()[2])
    full = _agreement(obj, Z.compose(*obj.render(CAM, pose), Z.real_backgrounds()[2]), pose, [ref])
    half = _agreement(obj, frame, shifted, [ref])
    assert 0 < half.pixels < full.pixels and half.ncc > 0.8


def test_the_compiled_block_sums_give_the_numpy_answer():
    """tile_correlations (one compiled pass) against its numpy original: the same blocks kept,
    the same ρ to 1e-9 (the sums run in another order), on crops that are not a whole number of
    blocks, with masks, flat blocks and correlated, anti-correlated and unrelated textures."""
    rng = np.random.default_rng(7)
    for h, w, tile in ((37, 53, 8), (120, 90, 16), (64, 64, 20), (9, 300, 8)):
        a = rng.normal(100, 30, (h, w)).astype(np.float32)
        b = (0.5 * a + rng.normal(0, 20, (h, w))).astype(np.float32) * rng.choice([-1, 1])
        b[: h // 3, : w // 3] = 42.0  # a flat corner: no evidence there
        mask = rng.random((h, w)) > 0.3
        mask[h // 2 :, w // 2 :] = False
        rho, n = tile_correlations(a, b, mask, tile)
        rho0, n0 = _tile_correlations_numpy(a, b, mask, tile)
        assert len(rho0) > 0 and np.array_equal(n, n0)
        np.testing.assert_allclose(rho, rho0, rtol=0, atol=1e-9)


def test_no_shared_face_gives_no_evidence():
    """A reference that saw none of the faces in view compares nothing: nan, 0 pixels (no
    evidence either way), never a refusal."""
    obj = Z.textured("cube-m")
    ref_pose = Z.orbit_pose(obj, CAM, 35.0, 25.0)
    ref = TextureReference(Z.compose(*obj.render(CAM, ref_pose), Z.real_backgrounds()[0]), CAM, ref_pose)
    pose = Z.orbit_pose(obj, CAM, 215.0, -25.0)  # the other side, from below
    frame = Z.compose(*obj.render(CAM, pose), Z.real_backgrounds()[1])
    a = _agreement(obj, frame, pose, [ref])
    assert a.pixels == 0 and np.isnan(a.ncc)


def test_every_reference_s_blocks_count(scene):
    obj, ref, frame, pose = scene
    other = TextureReference(ref.image, CAM, _turned(obj, ref.pose))  # a reference that lies
    a = _agreement(obj, frame, pose, [ref, other])
    (r1, n1), (r2, n2) = a.per_reference
    assert r1 > 0.8 and r2 < 0.35 and a.pixels == n1 + n2
    assert min(r1, r2) <= a.ncc <= max(r1, r2)  # the median of both references' blocks


def test_keyframes_answer_with_their_crops(scene):
    """What the tracker asks after a loss (Tracker._unlike_keyframes): the keyframes' crops, each
    with the camera of its crop, rendered at the pose."""
    obj, ref, frame, pose = scene
    x0, y0, x1, y1 = 150, 100, 500, 400
    crop_cam = CAM.cropped(x0, y0, x1, y1)
    vs = Viewset("k", -1, False, CAM, ref.pose, np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32),
                 np.zeros((0, 3)), (0, 0, 1, 1))
    kf = Keyframes(obj.mesh.centre, 4, 15.0, 3.0)
    kf.items.append(Keyframe(0.0, np.array([1.0, 0.0, 0.0]), vs, ref.image[y0:y1, x0:x1].copy(), crop_cam))
    right = kf.texture_agreement(frame, CAM, pose, obj.mesh)
    wrong = kf.texture_agreement(frame, CAM, _turned(obj, pose), obj.mesh)
    assert right.ncc > 0.8 and wrong.ncc < 0.35
    assert right.ncc == pytest.approx(_agreement(obj, frame, pose, [TextureReference(kf.items[0].crop, crop_cam, ref.pose)]).ncc)


def _cube_tracker(tmp_path, params):
    """A tracker of the zoo cube (trained from one photo) with one keyframe (azimuth 35°), and a
    grey frame 15° further round with its true pose."""
    from quatrack.recognition.video import Tracker
    from quatrack.viewsets.spec import load_spec
    from quatrack.viewsets.train import TrainParams, train_object

    obj = Z.textured("cube-m")
    model = train_object(load_spec(Z.write_spec("cube-m", tmp_path, 1, backgrounds=Z.real_backgrounds())),
                         TrainParams(novel=None))
    tracker = Tracker(model, CAM, params)
    ref_pose = Z.orbit_pose(obj, CAM, 35.0)
    ref = Z.compose(*obj.render(CAM, ref_pose), Z.real_backgrounds()[0])
    vs = Viewset("k", -1, False, CAM, ref_pose, np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32),
                 np.zeros((0, 3)), (0, 0, 1, 1))
    tracker.keyframes.items.append(Keyframe(0.0, np.array([1.0, 0.0, 0.0]), vs, ref, CAM))
    pose = Z.orbit_pose(obj, CAM, 50.0)
    grey = cv2.cvtColor(Z.compose(*obj.render(CAM, pose), Z.real_backgrounds()[1]), cv2.COLOR_BGR2GRAY)
    return obj, tracker, pose, grey


def test_the_tracker_refuses_a_pose_found_after_a_loss_that_its_keyframes_contradict(tmp_path):
    """Tracker._unlike_keyframes, the test a pose found after a loss must pass: the cube's true
    pose passes, the same outline turned by 90° is refused with the figures, and the setting at
    0 turns it off."""
    from dataclasses import replace

    from quatrack.recognition.video import TrackerParams

    obj, tracker, pose, grey = _cube_tracker(tmp_path, TrackerParams())
    timings = {}
    assert tracker._unlike_keyframes(grey, pose, timings) is None and "texture" in timings
    why = tracker._unlike_keyframes(grey, _turned(obj, pose), {})
    assert why is not None and "correlates" in why and "at least 0.5" in why
    tracker.params = replace(tracker.params, refind_min_texture_ncc=0.0)
    assert tracker._unlike_keyframes(grey, _turned(obj, pose), {}) is None


def test_live_streams_withhold_an_unanchored_pose_its_keyframes_contradict(tmp_path):
    """Tracker._texture_audit (live streams: ``for_live_streams`` turns ``audit_texture`` on):
    in a frame no trained point anchors, the pose must look as the keyframes show the object.
    The true pose passes; the same pose put too near the camera (the live wide box's drift, here
    15 % of the diameter) is withheld with the figures; a frame the trained points anchor, and
    the offline settings, are not judged so."""
    from dataclasses import replace
    from types import SimpleNamespace

    from quatrack.recognition.video import TrackerParams
    from quatrack.tracking.state import initial_state

    assert not TrackerParams().audit_texture and TrackerParams().for_live_streams().audit_texture
    obj, tracker, pose, grey = _cube_tracker(tmp_path, TrackerParams().for_live_streams())
    c = pose.apply(obj.mesh.centre[None])[0]
    near = Pose(pose.q_wxyz, pose.t - 0.15 * obj.mesh.extent * c / np.linalg.norm(c))

    def audit(at, anchored=False):
        tracker.filter.state = initial_state(0.0, at.t, at.q_wxyz, np.eye(6) * 1e-6)
        return tracker._texture_audit(SimpleNamespace(anchored=anchored, frame=SimpleNamespace(gray=grey)), {})

    assert audit(pose) is None
    why = audit(near)
    assert why is not None and "correlates" in why
    assert audit(near, anchored=True) is None
    tracker.params = replace(tracker.params, audit_texture=False)
    assert audit(near) is None


def _drifted(obj, pose, depth_pct, turn_deg, axis=(0.3, 1.0, 0.2)):
    """``pose`` moved ``depth_pct`` % of the diameter away along the line of sight to the centre
    and turned by ``turn_deg`` about ``axis`` through the centre: how a track born on its own
    poses drifts (bench/RESULTS.md, session 49)."""
    c = pose.apply(obj.mesh.centre[None])[0]
    moved = Pose(pose.q_wxyz, pose.t + c / np.linalg.norm(c) * depth_pct / 100 * obj.mesh.extent)
    a = np.asarray(axis, float)
    return rotate_about_centre(moved, obj.mesh.centre, a / np.linalg.norm(a) * np.radians(turn_deg))


@pytest.mark.parametrize("depth_pct, turn_deg", [(5.0, 2.0), (-4.0, 1.5), (0.0, 4.0)])
def test_the_texture_refit_brings_a_drifted_pose_back(scene, depth_pct, turn_deg):
    obj, ref, frame, pose = scene
    off = _drifted(obj, pose, depth_pct, turn_deg)
    assert pose_shift(off, pose, obj.mesh) > 0.75  # (the drift is most of the 5 %/5° criterion)
    fit = texture_refit(frame, CAM, off, obj.mesh, planar_groups(obj.mesh), [ref])
    assert fit.inliers >= 40, fit
    assert pose_shift(fit.pose, pose, obj.mesh) < 0.25, fit  # within 1.25 % / 1.25° of the truth


def test_the_texture_refit_reuses_the_agreement_s_renders_with_the_same_answer(scene, monkeypatch):
    """texture_refit(rendered=the agreement's renders at that pose): the same pose, points and
    pixels, bit for bit (the zoo camera's principal point lies on half pixels, so the two
    windows' rays are the same), a reference the agreement did not render rendered over its box;
    renders made at another pose are not used."""
    from quatrack.recognition import appearance

    real = appearance.render_textured_view
    obj, ref, frame, pose = scene
    groups = planar_groups(obj.mesh)
    other = TextureReference(ref.image, CAM, _turned(obj, ref.pose))
    for off in (_drifted(obj, pose, 5.0, 2.0), pose):
        agreement = _agreement(obj, frame, off, [ref])
        assert agreement.rendered is not None and set(agreement.rendered.views) == {id(ref)}
        for refs in ([ref], [ref, other]):
            plain = texture_refit(frame, CAM, off, obj.mesh, groups, refs)
            calls = []
            monkeypatch.setattr(appearance, "render_textured_view", lambda *a: calls.append(a) or real(*a))
            reused = texture_refit(frame, CAM, off, obj.mesh, groups, refs, rendered=agreement.rendered)
            monkeypatch.setattr(appearance, "render_textured_view", real)
            assert len(calls) == len(refs) - 1  # (only the one the agreement did not render)
            assert plain.pose is not None and (plain.tracked, plain.inliers) == (reused.tracked, reused.inliers)
            np.testing.assert_array_equal(plain.pose.t, reused.pose.t)
            np.testing.assert_array_equal(plain.pose.q_wxyz, reused.pose.q_wxyz)
            np.testing.assert_array_equal(plain.X, reused.X)
            np.testing.assert_array_equal(plain.uv, reused.uv)
    elsewhere = _agreement(obj, frame, _drifted(obj, pose, 0.0, 4.0), [ref]).rendered
    fit = texture_refit(frame, CAM, pose, obj.mesh, groups, [ref], rendered=elsewhere)
    assert pose_shift(fit.pose, pose, obj.mesh) < 0.1  # (the other pose's renders ignored)


def test_the_texture_refit_leaves_a_right_pose_where_it_is_in_any_light(scene):
    obj, ref, frame, pose = scene
    gain = np.array([0.85, 1.0, 1.15], np.float32) * 0.6  # the zoo walks' new light, as above
    dim = np.clip(frame.astype(np.float32) * gain, 0, 255).astype(np.uint8)
    for img in (frame, cv2.cvtColor(dim, cv2.COLOR_BGR2GRAY)):
        fit = texture_refit(img, CAM, pose, obj.mesh, planar_groups(obj.mesh), [ref])
        assert fit.inliers >= 40 and pose_shift(fit.pose, pose, obj.mesh) < 0.1, fit


def test_the_texture_refit_finds_nothing_where_the_texture_is_not(scene):
    obj, ref, _, pose = scene
    empty = Z.compose(np.zeros((CAM.height, CAM.width, 3), np.uint8), np.zeros((CAM.height, CAM.width), bool),
                      Z.real_backgrounds()[1])
    fit = texture_refit(empty, CAM, pose, obj.mesh, planar_groups(obj.mesh), [ref])
    assert fit.pose is None or fit.inliers < 40 or pose_shift(fit.pose, pose, obj.mesh) > 0.5


def test_live_streams_withhold_a_pose_the_keyframes_texture_moves_away(tmp_path):
    """Tracker._texture_audit's refit (``texture_refit_shift``): a pose drifted by 5 % of the
    diameter in depth and 2° — whose texture still correlates well enough to pass the NCC bar —
    is withheld, because the keyframe's texture, followed into the frame, puts the object back
    where it is and correlates better there; the true pose passes; the setting at 0 turns the
    refit off (the drifted pose then passes, as it did before session 49). Withheld, the track
    goes on from the refit's pose, unless ``texture_refit_restart`` is off."""
    from dataclasses import replace
    from types import SimpleNamespace

    from quatrack.recognition.video import TrackerParams
    from quatrack.tracking.state import initial_state

    obj, tracker, pose, grey = _cube_tracker(tmp_path, TrackerParams().for_live_streams())
    off = _drifted(obj, pose, 5.0, 2.0)

    def audit(at):
        tracker.filter.state = initial_state(0.0, at.t, at.q_wxyz, np.eye(6) * 1e-6)
        timings = {}
        return tracker._texture_audit(SimpleNamespace(anchored=False, frame=SimpleNamespace(gray=grey)), timings), timings

    why, timings = audit(pose)
    assert why is None and timings["texture"] > 0
    assert tracker.keyframes.texture_agreement(grey, CAM, off, obj.mesh).ncc > 0.5  # (the NCC bar passes it)
    why, _ = audit(off)
    assert why is not None and "puts the object" in why and "criterion away" in why, why
    # the track goes on from where the texture put the object (texture_refit_restart) ...
    assert pose_shift(tracker.filter.state.pose, pose, obj.mesh) < 0.25
    tracker.params = replace(tracker.params, texture_refit_restart=False)
    assert audit(off)[0] is not None and tracker.filter.state.pose is not None
    assert pose_shift(tracker.filter.state.pose, off, obj.mesh) == 0.0  # ... or only withheld
    tracker.params = replace(tracker.params, texture_refit_shift=0.0)
    assert audit(off)[0] is None


def test_live_streams_take_anchors_from_the_keyframes_texture_that_do_not_anchor(tmp_path):
    """``TrackerParams.texture_anchors``: a pose drifted by less than the withholding bar (it is
    reported) but correlating below 0.97 is refitted; with fewer than ``min_inliers`` trained
    points, the refit's consensus becomes the trained source's tracks — object points where the
    keyframe saw the texture, at the pixels where this frame shows it (the truth projects them
    there) — and measured they do not count as anchoring the frame; off, nothing changes."""
    from dataclasses import replace
    from types import SimpleNamespace

    from quatrack.recognition.tracker.points import PointBlock, Tracks
    from quatrack.recognition.video import TrackerParams
    from quatrack.tracking.state import initial_state

    obj, tracker, pose, grey = _cube_tracker(tmp_path, TrackerParams().for_live_streams())
    off = _drifted(obj, pose, 2.5, 1.0)
    assert 0.2 < pose_shift(off, pose, obj.mesh) < tracker.params.texture_refit_shift
    assert tracker.keyframes.texture_agreement(grey, CAM, off, obj.mesh).ncc < 1 - tracker.params.texture_refit_gain

    def audit():
        tracker.trained.tracks = Tracks.empty()
        tracker.filter.state = initial_state(0.0, off.t, off.q_wxyz, np.eye(6) * 1e-6)
        return tracker._texture_audit(SimpleNamespace(anchored=False, frame=SimpleNamespace(gray=grey)), {})

    assert audit() is None  # (reported: not withheld)
    tracks = tracker.trained.tracks
    assert len(tracks) >= tracker.params.texture_refit_min_inliers
    err = np.linalg.norm(CAM.project(pose.apply(tracks.X)) - tracks.uv, axis=1)
    drifted = np.linalg.norm(CAM.project(off.apply(tracks.X)) - tracks.uv, axis=1)
    # keyframe-anchored: where the truth puts them (within the consensus' 2 px), not the drifted pose
    assert np.median(err) < 0.5 and np.percentile(err, 95) < 2.0 and np.median(drifted) > 4 * np.median(err)
    block = PointBlock.isotropic("trained", tracks, 1.0)
    assert tracker._anchoring(block) == 0
    other = PointBlock.isotropic("trained", Tracks(tracks.X + 1e-3, tracks.uv), 1.0)  # (points SIFT matched)
    assert tracker._anchoring(other) == len(tracks)
    tracker.params = replace(tracker.params, texture_anchors=False)
    assert audit() is None and len(tracker.trained.tracks) == 0

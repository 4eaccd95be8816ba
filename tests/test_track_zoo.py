"""The tracking zoo (issue 12): a camera walking round objects trained from ONE photo.

- the walk (testing/orbit.py) does what the benchmark says: every side, ×3 in size, a slide out
  of the frame below 30 % visible, a lighting change, an occluder, motion blur;
- a short orbit round a cube (mesh in metres) to faces its one photo never shows is followed to
  the end within tolerances, and the pose covariance is honest there: NEES (6 dof) near 6, not
  the hundreds of a filter that believes points born at one uncertain pose are independent;
- the benchmark's figures come from the truth: a tiny run computes them, and a pass that is off
  or lost is reported as such.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from quatrack.bench import track_zoo as B
from quatrack.testing import zoo as Z
from quatrack.testing.orbit import OrbitParams, calm_orbit, orbit_pose_at, render_orbit, short_orbit
from quatrack.recognition.klt import make_frame
from quatrack.recognition.match import index_for
from quatrack.recognition.tracker.mesh_points import MeshPoints, inherited_spread
from quatrack.recognition.tracker.sources import FrameContext
from quatrack.tracking.state import initial_state
from quatrack.recognition.video import TrackerParams
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.train import TrainParams, train_object


def _backgrounds():
    """Deterministic cluttered backgrounds (the real ones need the example trained: ~25 s)."""
    out = []
    for seed in (3, 4, 5):
        rng = np.random.default_rng(seed)
        img = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640, 3)).astype(np.float32), (0, 0), 3.0)
        img = cv2.normalize(img, None, 30, 220, cv2.NORM_MINMAX)
        for _ in range(25):
            c = tuple(int(v) for v in rng.uniform(0, 255, 3))
            cv2.circle(img, (int(rng.uniform(0, 640)), int(rng.uniform(0, 480))), int(rng.uniform(5, 40)), c, -1)
        out.append(img.astype(np.uint8))
    return tuple(out)


def test_the_walk_shows_every_side_at_three_sizes():
    obj = Z.textured("wide-box-cm")
    cam = Z.zoo_camera(640, 480)
    p = OrbitParams()
    ts = np.linspace(0, p.seconds, 301)
    poses = [orbit_pose_at(obj, cam, t, p) for t in ts]
    # the camera's viewing direction in the object frame: every side's normal is faced at some time
    view = np.array([-(pz.R.T @ (pz.R @ obj.mesh.centre + pz.t)) for pz in poses])
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    for axis in np.vstack([np.eye(3), -np.eye(3)]):
        assert (view @ axis).max() > 0.35, axis
    depth = np.array([(pz.R @ obj.mesh.centre + pz.t)[2] for pz in poses])
    assert 2.7 < depth.max() / depth.min() < 3.3


def test_the_walk_leaves_the_frame_dims_and_is_occluded():
    obj = Z.textured("small-cube-cm")
    cam = Z.zoo_camera(320, 240)
    p = replace(OrbitParams(), fps=4.0)  # 40 frames over the whole walk
    seq = render_orbit(obj, cam, tuple(cv2.resize(b, (320, 240)) for b in _backgrounds()), p, seed=1)
    assert len(seq) == 40
    x = np.arange(40) / 40.0
    out = (x > p.out_phase[0]) & (x < p.out_phase[1])
    assert seq.visible[out].min() < 0.3 and seq.visible[~out & (seq.occluded == 0)].min() > 0.95
    assert seq.occluded.max() > 0.2 and np.all(seq.occluded[x < p.occluder_phase[0]] == 0)
    # the light: the same background corner is darker after the change
    before, after = seq.image(2)[:30, :30].mean(), seq.image(39)[:30, :30].mean()
    assert after < 0.85 * before
    assert any("blur" in ph for ph in seq.phases) and any("dim" in ph for ph in seq.phases)


@pytest.fixture(scope="module")
def cube(tmp_path_factory):
    """The 10 cm cube in metres, trained from one photo, and 2.5 s of a camera turning 150°
    round it (two faces the photo never shows come into view)."""
    name = "cube-m"
    bgs = _backgrounds()
    cam = Z.zoo_camera(640, 480)
    spec = Z.write_spec(name, tmp_path_factory.mktemp("cube"), n_views=1, backgrounds=bgs[:1], camera=cam)
    model = train_object(load_spec(spec), TrainParams(novel=None))
    seq = render_orbit(Z.textured(name), cam, bgs[1:], short_orbit(2.5), seed=0)
    return model, seq


def test_points_born_at_one_pose_claim_no_more_than_they_know(cube):
    """Points born together share their birth pose's error δ (covariance P_b): the pose their
    block alone gives, x̂ = (Σ Jᵢᵀ Cᵢ⁻¹ Jᵢ)⁻¹ Σ Jᵢᵀ Cᵢ⁻¹ yᵢ, has the true covariance
    A (M P_b Mᵀ + σ² I) Aᵀ (M: how δ moves every pixel, shared). The covariance the block claims,
    (Σ Jᵢᵀ Cᵢ⁻¹ Jᵢ)⁻¹, must not be smaller in any direction — at birth and after the camera moved
    on. Treated as independent (each σ²I + J P_b Jᵀ) they claimed about n times too little."""
    from quatrack.recognition.tracker.mesh_points import lift_jacobian
    from quatrack.tracking.measurements import project_model_points
    from quatrack.viewsets.render import cast_rays, undistort_pixels

    model, seq = cube
    cam = seq.camera
    pose = seq.poses[0]
    P = np.diag([(0.004 * model.mesh.extent) ** 2] * 3 + [np.radians(0.4) ** 2] * 3)
    state = initial_state(0.0, pose.t, pose.q_wxyz, P)
    img = seq.image(0)
    frame = make_frame(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    src = MeshPoints(model.mesh, TrackerParams())
    assert src.spawn(FrameContext(img, frame, frame, cam, state), state) > 30
    X = src.tracks.X
    _, face, _ = cast_rays(model.mesh, pose, undistort_pixels(cam, src.tracks.uv))
    QG = lift_jacobian(pose, X, model.mesh.face_normals[face])
    sigma2 = TrackerParams().sigma_px ** 2

    def excess(later, C):
        """Largest eigenvalue of claimed⁻¹ᐟ² · true · claimed⁻¹ᐟ² (≤ 1: honest or cautious)."""
        st = initial_state(0.0, later.t, later.q_wxyz, P)
        _, J = project_model_points(cam, X, st.p, st.R, True)
        JX = J[:, :, :3] @ st.R
        W = np.linalg.inv(C)
        claimed = np.linalg.inv(np.einsum("nki,nkl,nlj->ij", J, W, J))
        A = claimed @ np.concatenate([J[i].T @ W[i] for i in range(len(X))], axis=1)  # (6, 2n)
        M = np.concatenate([JX[i] @ QG[i] for i in range(len(X))])  # (2n, 6)
        true = A @ (M @ P @ M.T + sigma2 * np.eye(2 * len(X))) @ A.T
        L = np.linalg.cholesky(claimed)
        Li = np.linalg.inv(L)
        return float(np.linalg.eigvalsh(Li @ true @ Li.T).max())

    for later in (seq.poses[0], seq.poses[30]):
        st = initial_state(0.0, later.t, later.q_wxyz, P)
        C = sigma2 * np.eye(2) + inherited_spread(cam, X, src.cov_X, src.cohort, st)
        assert excess(later, C) <= 1.05
        # the old covariance (independent points) claimed far too much
        naive = sigma2 * np.eye(2) + inherited_spread(cam, X, src.cov_X, np.arange(len(X)), st)
        assert excess(later, naive) > 5.0


def test_an_orbit_to_unseen_faces_is_followed_to_the_end_with_an_honest_covariance(cube):
    model, seq = cube
    run = B.run_pass(model, seq, TrackerParams(), True, index_for(model))
    f = B.figures(run, seq.visible, model.mesh.extent)
    assert f["lost"] == 0, [s for s in run.status if s == "lost"]
    assert f["t_mean_pct"] < 1.0 and f["r_mean_deg"] < 1.0
    assert f["t_max_pct"] < 2.5 and f["r_max_deg"] < 2.0 and f["bad"] == 0
    # NEES of [p, δθ] (6 dof) over the tracked frames: honest means a median of ~5.3 (χ²₆).
    # Measured here: mean 127 before the born points' shared error was accounted for, 50–70
    # after; the filter's own covariance still has a median of 46 (the errors its measurements
    # share are not modelled), the reported one (plus the systematic floor, chosen on the zoo
    # walks, not on this orbit) 4.7. The bounds catch an overconfident report and an absurdly
    # cautious one. Session 38 brightened run time's dim SIFT queries: this orbit's mean error
    # fell 0.37 → 0.28°, its max 1.6 → 0.9°, with the same floor, and the median 3.2 → 2.0.
    assert 1.5 < f["nees_median"] < 15.0, f["nees_median"]
    # and each half on its own (3 dof, median 2.37 when honest): measured 1.4 for the centre and
    # 3.0 for the rotation; the floor of sessions 22–30 gave 0.12 and 8.3 — a far too cautious
    # position hiding a far too confident rotation in a 6-dof median of 8.5
    assert 0.6 < f["nees_centre_median"] < 9.0, f["nees_centre_median"]
    assert 0.6 < f["nees_rotation_median"] < 9.0, f["nees_rotation_median"]


@pytest.mark.parametrize("start", [30, 60, 65])
def test_a_track_started_on_a_side_no_photo_shows_holds(cube, start):
    """Started at the true pose (the user's ``init_pose``) on a side the one photo never shows,
    the track is carried by corners born on the mesh and by the edges. Those points were lifted
    at the state's own pose, so their birth error is the state's (mesh_points.py): counted on top
    (σ ≈ 28 px for a cohort of ~90) they weighed nothing, the edges alone moved the pose, and
    ~10 % of them locked on print lines beside the creases: on the zoo cube's walk such a start
    was 5° off one frame later and lost (session 25). Here the old weighting lost the start at
    frame 30 for 43 of 45 frames and let the others drift to 5.6 % / 4.5° and 9 % / 6.9°; now
    none is lost and the worst is 1.2 % / 1.8°."""
    from quatrack.recognition.video import Tracker

    model, seq = cube
    d = model.mesh.extent
    tracker = Tracker(model, seq.camera, TrackerParams(), index=index_for(model))
    tracker.init_pose(seq.poses[start].t, seq.poses[start].q_wxyz)
    steps = [tracker.step(seq.image(k), k / seq.fps) for k in range(start, len(seq))]
    assert steps[0].reason.startswith("given pose: no trained view shows this side"), steps[0].reason
    assert all(s.has_pose for s in steps), [(k + start, s.reason) for k, s in enumerate(steps) if not s.has_pose][:3]
    err = np.array([B.pose_error(s, seq.poses[start + k], model.mesh) for k, s in enumerate(steps)])
    assert err[:, 0].max() < 0.03 * d and err[:, 1].max() < 3.0, err.max(axis=0)
    assert err[:, 0].mean() < 0.015 * d and err[:, 1].mean() < 1.5, err.mean(axis=0)


def test_the_bench_computes_its_figures_from_the_truth(cube):
    model, seq = cube
    d = model.mesh.extent
    run = B.Run()
    for k, pose in enumerate(seq.poses[:10]):
        run.status.append("lost" if k in (3, 4) else "tracking")
        run.t_err.append(float("nan") if k in (3, 4) else (0.08 * d if k == 7 else 0.001 * d))
        run.r_err.append(float("nan") if k in (3, 4) else 0.1)
        run.nees.append(float("nan") if k in (3, 4) else 6.0)
        run.timings.append({"total": 150.0 if k in (3, 4) else 12.0, "klt": 3.0})
    f = B.figures(run, np.full(10, 0.9), d)
    assert (f["lost"], f["lost_visible"], f["bad"], f["first_pose"]) == (2, 2, 1, 0)
    assert f["t_max_pct"] == pytest.approx(8.0) and f["step_p50_ms"] == 12.0
    # the lost frames' own cost: 2 × 150 ms of the steps' 8 × 12 + 300 ms
    assert f["untracked_step_p50_ms"] == 150.0 and f["untracked_share_pct"] == pytest.approx(100 * 300 / 396)
    miss = B.shortfalls(f)
    assert any("lost" in m for m in miss) and any("> 5 %" in m for m in miss) and any("step" in m for m in miss)
    # a tiny real study: one object, one second, the truth-initialised and live passes
    res = B.study(("small-cube-cm",), seconds=1.0, passes=("truth", "live"), backgrounds=_backgrounds(), progress=False)
    s = res["sequences"]["small-cube-cm"]
    assert s["frames"] == 30 and s["truth"]["frames"] == 30 and s["truth"]["t_mean_pct"] is not None
    assert s["truth"]["background_mean_ms"] is None  # (offline: everything in the step)
    assert s["live"]["frames"] == 30 and s["live"]["t_mean_pct"] is not None and s["live"]["background_mean_ms"] > 0
    text = B.report(res)
    assert "small-cube-cm" in text and "live stream" in text


def test_a_walk_through_a_distorted_lens_is_tracked_as_accurately(tmp_path):
    """--lens: photo, walk and tracker see through a lens with OpenCV's distortion (a webcam's
    barrel, ~14 px at the corners); the tracker, which projects and renders through it, follows
    a short walk to its end within 1 % of the diameter and 1° on average (through a pinhole:
    0.37 % / 0.43°), and the report names the lens."""
    lens = [-0.15, 0.05, 0.0, 0.0, 0.0]
    res = B.study(("small-cube-cm",), seconds=1.0, passes=("truth",), orbit=short_orbit(1.0),
                  backgrounds=_backgrounds(), progress=False, dist_coeffs=lens)
    f = res["sequences"]["small-cube-cm"]["truth"]
    assert res["dist_coeffs"] == lens and f["frames"] == 30 and f["lost"] == 0 and f["bad"] == 0
    assert f["t_mean_pct"] < 1.0 and f["r_mean_deg"] < 1.0, f
    assert "lens distortion [-0.15, 0.05" in B.report(res)
    model, seq = B.prepare("small-cube-cm", 1.0, 0, tmp_path, _backgrounds(), dist_coeffs=lens)
    assert seq.camera.has_distortion and np.allclose(seq.camera.dist_coeffs, lens)
    assert np.allclose(model.viewsets[0].camera.dist_coeffs, lens)  # (trained through the lens it was shot with)


def _record_study(monkeypatch) -> dict:
    """Replace ``study`` by a stand-in that records the options the CLI passed and returns an
    empty result stating them (size, grey), so the report can be checked without a walk."""
    seen = {}

    def study(names, seconds, **kw):
        seen.update(kw)
        return {"machine": "test", "load_before": (0.0,), "load_after": (0.0,), "seconds": seconds, "renderings": 1,
                "learned_viewsets_api": True, "size": [kw["width"], kw["height"]], "grey": kw["grey"],
                "passes": list(kw["passes"]), "calm": kw.get("orbit") is not None, "sequences": {}, "total_s": 0.0}

    monkeypatch.setattr(B, "study", study)
    return seen


def test_another_image_size_frames_the_walk_alike(monkeypatch, capsys, tmp_path):
    """--size WxH: the walk is rendered and tracked at that size with the zoo camera's field of
    view, so the object fills the same share of each frame (its pixels scale with the width);
    the CLI passes the size on and the report names it."""
    from quatrack.cli import main

    _, small = B.prepare("small-cube-cm", 0.2, 0, tmp_path / "a", _backgrounds())
    _, big = B.prepare("small-cube-cm", 0.2, 0, tmp_path / "b", _backgrounds(), width=1280, height=720)
    assert big.camera.width == 1280 and big.camera.height == 720 and big.image(0).shape[:2] == (720, 1280)
    for k in (0, len(big) - 1):  # the same framing: pixel coordinates ×2 (less the principal point's half pixel)
        ca = small.camera.project(small.poses[k].apply(np.zeros((1, 3))))[0] / [small.camera.width, small.camera.height]
        cb = big.camera.project(big.poses[k].apply(np.zeros((1, 3))))[0] / [big.camera.width, big.camera.height]
        assert np.abs(ca[0] - cb[0]) < 0.01, (ca, cb)
    seen = _record_study(monkeypatch)
    assert main(["bench", "track-zoo", "--size", "1280x720", "--sequences", "small-cube-cm"]) == 0
    assert (seen["width"], seen["height"]) == (1280, 720) and "images 1280x720" in capsys.readouterr().out
    assert main(["bench", "track-zoo", "--sequences", "small-cube-cm"]) == 0
    assert (seen["width"], seen["height"]) == (640, 480) and "images" not in capsys.readouterr().out


def test_a_grey_walk_is_the_colour_walk_in_one_channel(monkeypatch, capsys, tmp_path):
    """--grey: a monochrome camera — the training photo and every frame have one channel, the
    same renderings converted (so grey and colour walks compare frame for frame); a short grey
    walk is followed to its end; the CLI passes the flag on and the report names it."""
    from quatrack.cli import main

    _, grey = B.prepare("small-cube-cm", 0.2, 0, tmp_path / "g", _backgrounds(), grey=True)
    _, colour = B.prepare("small-cube-cm", 0.2, 0, tmp_path / "c", _backgrounds())
    photos = [cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in sorted((tmp_path / "g").rglob("*.jp*g"))]
    for k in (0, len(grey) - 1):
        g, c = grey.image(k), colour.image(k)
        assert g.ndim == 2 and c.ndim == 3
        assert np.array_equal(g, cv2.cvtColor(c, cv2.COLOR_BGR2GRAY))
    assert photos and all(ph.ndim == 2 for ph in photos)  # (trained from a grey photo)
    res = B.study(("small-cube-cm",), seconds=1.0, passes=("truth",), orbit=short_orbit(1.0),
                  backgrounds=_backgrounds(), progress=False, grey=True)
    f = res["sequences"]["small-cube-cm"]["truth"]
    assert res["grey"] is True and f["frames"] == 30 and f["lost"] == 0 and f["bad"] == 0, f
    assert "grey images" in B.report(res)
    seen = _record_study(monkeypatch)
    assert main(["bench", "track-zoo", "--grey", "--sequences", "small-cube-cm"]) == 0
    assert seen["grey"] is True and "grey images" in capsys.readouterr().out
    assert main(["bench", "track-zoo", "--sequences", "small-cube-cm"]) == 0
    assert seen["grey"] is False and "grey" not in capsys.readouterr().out


def test_a_calm_walk_turns_round_the_object_without_the_hard_phases(monkeypatch, capsys):
    """--calm: the walk of ``calm_orbit`` — a whole turn round the object with nothing of the
    harsh walk's phases (no frame half out of the image, blurred, dimmed or occluded: the object
    fully in view throughout), the apparent size within ×1.5; the CLI passes it on and the
    report names it; without the flag the harsh walk is used."""
    from quatrack.cli import main

    obj, cam = Z.textured("small-cube-cm"), Z.zoo_camera()
    seq = render_orbit(obj, cam, _backgrounds(), calm_orbit(1.0), seed=0)
    assert len(seq) == 30 and all(ph == () for ph in seq.phases), seq.phases
    assert seq.visible.min() > 0.99 and seq.occluded.max() == 0.0
    views = np.array([p.viewing_direction(obj.mesh.centre) for p in seq.poses])
    assert np.degrees(np.arccos(np.clip(views[0] @ views[len(seq) // 2], -1, 1))) > 90  # (round the object)
    depth = np.array([p.apply(obj.mesh.centre[None])[0, 2] for p in seq.poses])
    assert 1.1 < depth.max() / depth.min() < 1.5 + 1e-6
    harsh = render_orbit(obj, cam, _backgrounds(), replace(OrbitParams(), seconds=1.0), seed=0)
    assert any(ph != () for ph in harsh.phases)  # (the phases the calm walk leaves out are there)
    seen = _record_study(monkeypatch)
    assert main(["bench", "track-zoo", "--calm", "--sequences", "small-cube-cm"]) == 0
    assert seen["orbit"] == calm_orbit(10.0) and "calm walks" in capsys.readouterr().out
    assert main(["bench", "track-zoo", "--sequences", "small-cube-cm"]) == 0
    assert seen["orbit"] is None and "calm" not in capsys.readouterr().out


def test_passes_pick_what_runs(monkeypatch, capsys):
    """--passes A,B: only those passes run (in the benchmark's order, whatever the order given),
    the report says which; an unknown name, or the learned pass without the truth pass whose
    views it uses, is refused in one line (exit status 2) before anything runs."""
    from quatrack.cli import main

    seen = _record_study(monkeypatch)
    assert main(["bench", "track-zoo", "--sequences", "small-cube-cm", "--passes", "live"]) == 0
    assert seen["passes"] == ("live",) and "passes: live" in capsys.readouterr().out
    assert main(["bench", "track-zoo", "--sequences", "small-cube-cm", "--passes", "learned,truth"]) == 0
    assert seen["passes"] == ("truth", "learned") and "passes: truth, learned" in capsys.readouterr().out
    assert main(["bench", "track-zoo", "--sequences", "small-cube-cm"]) == 0
    assert seen["passes"] == B.PASSES and "passes" not in capsys.readouterr().out
    seen.clear()
    for bad in ("live,nope", "learned", ","):
        assert main(["bench", "track-zoo", "--sequences", "small-cube-cm", "--passes", bad]) == 2
        err = capsys.readouterr().err
        assert "--passes" in err and "Traceback" not in err
    assert seen == {}  # (refused before the study ran)


def test_more_renderings_are_other_walks_and_the_first_is_the_usual_one():
    """--renderings N: every object walked N times with other seeds; the first rendering of each
    object has the seed it always had (its place in SEQUENCES, whatever --sequences picks)."""
    from quatrack.bench.track_zoo import SEQUENCES, walks

    w = walks(SEQUENCES, 3)
    assert len(w) == 18 and len({key for key, _, _ in w}) == 18 and len({seed for _, _, seed in w}) == 18
    assert [(key, seed) for key, _, seed in w[:6]] == [(n, k) for k, n in enumerate(SEQUENCES)]
    assert walks(["hex-prism-m"], 2) == [("hex-prism-m", "hex-prism-m", 4), ("hex-prism-m#1", "hex-prism-m", 14)]


def test_the_nees_halves_judge_the_centre_and_the_rotation_apart():
    """A pose off only by a shift has a rotation NEES of 0; one turned about the object's centre
    (not its origin, which then moves) has a centre NEES of 0; each half is eᵀP⁻¹e of its own
    error under the matching block of P (worked out by hand below)."""
    from types import SimpleNamespace

    from quatrack.tracking import quaternion as quat
    from quatrack.tracking.pose import Pose

    centre = np.array([1.0, 0.0, 0.0])  # the mesh's centre lies 1 unit along x of its origin
    P = np.diag([0.01] * 3 + [1e-4] * 3)
    est = SimpleNamespace(t=np.array([0.0, 0.0, 5.0]), q_wxyz=np.array([1.0, 0.0, 0.0, 0.0]), covariance=P)
    shifted = Pose(est.q_wxyz, est.t + [0.1, 0.0, 0.0])
    c, r = B.nees_parts(est, shifted, centre)
    # centre covariance 0.01 I + 1e-4 (‖Rc‖² I − Rc Rcᵀ) = diag(0.01, 0.0101, 0.0101); error along x
    assert c == pytest.approx(0.1**2 / 0.01) and r == pytest.approx(0.0, abs=1e-12)
    # turned by 0.02 rad about z round the centre: the origin moves, the centre does not
    q = quat.from_rotvec(np.array([0.0, 0.0, 0.02]))
    R = quat.to_matrix(q)
    turned = Pose(q, est.t + centre - R @ centre)
    c, r = B.nees_parts(est, turned, centre)
    assert c == pytest.approx(0.0, abs=1e-12) and r == pytest.approx(0.02**2 / 1e-4)
    # the 6-dof NEES of the same pose counts the origin's move as an error of position too
    assert B.nees(est, turned) == pytest.approx(r + 0.02**2 / 0.01, rel=1e-3)  # the origin moved 0.02 along y


def test_the_nees_figures_are_medians_and_the_ellipsoid_share_over_tracked_frames():
    run = B.Run()
    for k in range(10):
        lost = k in (3, 4)
        run.status.append("lost" if lost else "tracking")
        run.t_err.append(float("nan") if lost else 0.1)
        run.r_err.append(float("nan") if lost else 0.1)
        run.nees.append(float("nan") if lost else (20.0 if k < 2 else 4.0))  # 2 of 8 beyond χ²₆'s 95 %
        run.nees_centre.append(float("nan") if lost else float(k))
        run.nees_rotation.append(float("nan") if lost else 2.0 * k)
        run.timings.append({"total": 1.0})
    f = B.figures(run, np.ones(10), 1.0)
    assert f["nees_in95_pct"] == pytest.approx(75.0)
    tracked = [0, 1, 2, 5, 6, 7, 8, 9]
    assert f["nees_centre_median"] == pytest.approx(np.median(tracked))
    assert f["nees_rotation_median"] == pytest.approx(2.0 * np.median(tracked))
    # a Run without the halves (older callers) reports them as missing, not as zero
    run.nees_centre, run.nees_rotation = [], []
    f = B.figures(run, np.ones(10), 1.0)
    assert f["nees_centre_median"] is None and f["nees_rotation_median"] is None


def test_the_centre_error_is_split_along_and_across_the_line_of_sight():
    """A pose put 6 % of the diameter too close, right across the line of sight and in rotation,
    counts as beyond the criterion *only by its depth*; one shifted 6 % sideways does not
    (worked by hand: the true centre 10 units straight ahead, a diameter of 10)."""
    from types import SimpleNamespace

    from quatrack.tracking.pose import Pose

    mesh = SimpleNamespace(centre=np.array([0.0, 0.0, 1.0]))  # the centre 1 unit along the object's z
    truth = Pose(np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 0.0, 9.0]))  # true centre (0, 0, 10)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    closer = SimpleNamespace(q_wxyz=q, t=np.array([0.0, 0.0, 9.0 - 0.6]))
    aside = SimpleNamespace(q_wxyz=q, t=np.array([0.6, 0.0, 9.0]))
    assert B.centre_error_split(closer, truth, mesh) == pytest.approx((-0.6, 0.0))
    assert B.centre_error_split(aside, truth, mesh) == pytest.approx((0.0, 0.6))
    run = B.Run()
    for k, step in enumerate([closer, aside, None]):
        run.status.append("lost" if step is None else "tracking")
        d, lat = B.centre_error_split(step, truth, mesh) if step else (float("nan"), float("nan"))
        run.t_err.append(float(np.hypot(d, lat)))
        run.r_err.append(0.1 if step else float("nan"))
        run.nees.append(float("nan"))
        run.depth_err.append(d)
        run.lateral_err.append(lat)
        run.timings.append({"total": 1.0})
    f = B.figures(run, np.ones(3), 10.0)
    assert (f["bad"], f["bad_depth"]) == (2, 1)
    assert f["depth_mean_pct"] == pytest.approx(3.0) and f["lateral_mean_pct"] == pytest.approx(3.0)
    run.depth_err, run.lateral_err = [], []  # a Run without the split (older callers): missing, not zero
    f = B.figures(run, np.ones(3), 10.0)
    assert f["bad_depth"] is None and f["depth_mean_pct"] is None


def test_the_image_floor_only_widens_the_reported_covariance(cube):
    """The systematic floors enter nothing the tracker decides: with and without the image floor
    the same frames give the same statuses and poses, and the reported covariances differ by
    exactly image_floor at the reported pose (the object's vertices, ``systematic_px`` px)."""
    from quatrack.recognition.video import Tracker
    from quatrack.tracking import quaternion as quat
    from quatrack.tracking.systematic import image_floor

    model, seq = cube
    on, off = (Tracker(model, seq.camera, TrackerParams(systematic_px=px), index=index_for(model)) for px in (0.3, None))
    for tr in (on, off):
        tr.init_pose(seq.poses[0].t, seq.poses[0].q_wxyz)
    for k in range(8):
        a, b = on.step(seq.image(k), k / seq.fps), off.step(seq.image(k), k / seq.fps)
        assert a.status == b.status and a.has_pose
        assert np.array_equal(a.t, b.t) and np.array_equal(a.q_wxyz, b.q_wxyz)
        F = image_floor(seq.camera, quat.to_matrix(a.q_wxyz), a.t, model.mesh.vertices, 0.3)
        assert np.any(F) and np.allclose(np.asarray(a.covariance) - np.asarray(b.covariance), F, rtol=1e-6, atol=1e-15)


def test_the_sources_disagreement_only_widens_the_reported_covariance(cube):
    """The disagreement factor (TrackerParams.disagreement_scale) enters nothing the tracker
    decides: with and without it the same frames give the same statuses, poses and filter states,
    and the reported covariances differ by a non-negative multiple of the filter's pose
    covariance — positive in some frame of the zoo cube's walk, where the outline and the edges
    disagree with the points by more than their covariances say."""
    from quatrack.recognition.video import Tracker

    model, seq = cube
    index = index_for(model)
    on, off = (Tracker(model, seq.camera, TrackerParams(disagreement_scale=d), index=index) for d in (True, False))
    for tr in (on, off):
        tr.init_pose(seq.poses[0].t, seq.poses[0].q_wxyz)
    grown = 0
    for k in range(8):
        a, b = on.step(seq.image(k), k / seq.fps), off.step(seq.image(k), k / seq.fps)
        assert a.status == b.status and a.has_pose
        assert np.array_equal(a.t, b.t) and np.array_equal(a.q_wxyz, b.q_wxyz)
        P = on.filter.state.pose_covariance
        assert np.array_equal(P, off.filter.state.pose_covariance)
        D = np.asarray(a.covariance) - np.asarray(b.covariance)
        c = float(np.trace(np.linalg.solve(P, D))) / 6.0  # D = c·P, c = the factor − 1
        assert c >= -1e-9 and np.allclose(D, c * P, rtol=1e-6, atol=1e-18)
        grown += c > 1e-6
    assert grown >= 1

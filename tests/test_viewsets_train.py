"""Training end to end: viewsets' 3-D points, synthetic views on the right surfaces, the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from quatrack.cli import main
from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.mesh import make_mesh, planar_groups
from quatrack.viewsets.novel import render_textured_view
from quatrack.viewsets.render import cast_rays, render, undistort_pixels
from quatrack.tracking.pose import Pose
from quatrack.viewsets.errors import SpecError
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.store import list_models, load_model
from quatrack.viewsets.train import TrainParams, train_object
from quatrack.viewsets.novel import NovelViewParams

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cookie-box"


@pytest.fixture(scope="module")
def trained_store(tmp_path_factory):
    store = tmp_path_factory.mktemp("store")
    assert main(["train", str(EXAMPLE / "object.json"), "--store", str(store), "--jobs", "2"]) == 0
    return store


def test_cli_train_end_to_end(trained_store, capsys):
    assert list_models(trained_store) == ["cookie-box"]
    model = load_model(trained_store, "cookie-box")
    real = [v for v in model.viewsets if not v.synthetic]
    synthetic = [v for v in model.viewsets if v.synthetic]
    assert len(real) == 1 and len(synthetic) >= 8
    assert len(real[0]) >= 200  # a textured photo gives hundreds of lifted keypoints
    m = model.manifest
    assert m["schema_version"] == 1 and m["spec"]["sha256"] == load_spec(EXAMPLE / "object.json").checksum
    assert m["training_summary"]["points3d_total"] == sum(len(v) for v in model.viewsets)
    assert abs(model.rfch.histogram.sum() - 1.0) < 1e-9
    assert model.rfch.size_min[0] <= model.rfch.size_max[0]
    assert main(["models", "list", "--store", str(trained_store)]) == 0
    assert "cookie-box" in capsys.readouterr().out
    assert main(["models", "show", "cookie-box", "--store", str(trained_store)]) == 0
    assert json.loads(capsys.readouterr().out)["name"] == "cookie-box"


@pytest.mark.parametrize("option, value", [("--rfch-scales", "1e9"), ("--rfch-scales", "0"), ("--rfch-scales", "-1"),
                                           ("--max-features", str(2**31)), ("--max-features", "0")])
def test_train_options_out_of_range_are_one_line(tmp_path, capsys, option, value):
    """`--rfch-scales 1e9` reached OpenCV's Gaussian blur: a cv2.error traceback (1e7: all the
    memory, then std::bad_alloc); `--max-features 2147483648` OpenCV's SIFT, which takes a C
    int: a traceback too. Both are bounded, as the pair distance is."""
    store = tmp_path / "store"
    assert main(["train", str(EXAMPLE / "object.json"), "--store", str(store), option, value]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"quatrack train: error: {option}") and err.count("\n") == 1
    assert not store.exists()


def test_skip_existing_trains_only_what_is_missing_or_changed(tmp_path, capsys):
    store = tmp_path / "store"
    spec = tmp_path / "object.json"
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / data["mesh"])
    data["views"][0]["image"] = str(EXAMPLE / data["views"][0]["image"])
    spec.write_text(json.dumps(data))
    args = ["train", str(spec), "--store", str(store), "--skip-existing", "--novel-views", "none", "--novel-scales", "none"]
    assert main(args) == 0 and "trained" in capsys.readouterr().out
    stamp = (store / "cookie-box" / "manifest.json").stat().st_mtime_ns
    assert main(args) == 0 and "nothing to do" in capsys.readouterr().out
    assert (store / "cookie-box" / "manifest.json").stat().st_mtime_ns == stamp
    data["views"][0]["pose"]["tvec"][2] += 0.5  # the spec changed: train again
    spec.write_text(json.dumps(data))
    assert main(args) == 0 and "trained" in capsys.readouterr().out


def test_a_missing_mask_is_one_line_naming_it_and_nothing_else(tmp_path, capfd):
    """The user's spec names a mask that is not there: one line says which, exit status 2, the
    store untouched — and no OpenCV warning on the same stderr (capfd: OpenCV writes to fd 2)."""
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / data["mesh"])
    data["views"][0]["image"] = str(EXAMPLE / data["views"][0]["image"])
    data["views"][0]["mask"] = "no_such_mask.png"
    spec = tmp_path / "object.json"
    spec.write_text(json.dumps(data))
    store = tmp_path / "store"
    assert main(["train", str(spec), "--store", str(store)]) == 2
    err = capfd.readouterr().err.strip()
    assert "no_such_mask.png: file not found" in err and "\n" not in err and "WARN" not in err
    assert not store.exists() or list_models(store) == []


def test_a_photo_over_the_pixel_budget_is_trained_downscaled_with_its_camera(tmp_path, monkeypatch):
    """A 6000×4000 photo took 10 GB of memory and 80 s (230 s before the weak-texture fix) to
    train, for keypoints and colour pairs at scales no query shows (locate reads at most 4 MP).
    Over ``MAX_PHOTO_PIXELS`` the photo, its camera and its mask are downscaled together (the
    budget is lowered here so the bundled photo, 718×480, is over it)."""
    import quatrack.viewsets.train as T
    from quatrack.recognition.images import DEFAULT_MAX_PIXELS

    assert T.MAX_PHOTO_PIXELS == DEFAULT_MAX_PIXELS  # (as locate reads a query)
    monkeypatch.setattr(T, "MAX_PHOTO_PIXELS", 718 * 480 // 4)
    spec0 = load_spec(EXAMPLE / "object.json")
    from quatrack.viewsets.mesh import load_mesh

    cv2.imwrite(str(tmp_path / "mask.png"), render(load_mesh(spec0.mesh_path), spec0.views[0].camera, spec0.views[0].pose).mask)
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / data["mesh"])
    data["views"][0]["image"] = str(EXAMPLE / data["views"][0]["image"])
    data["views"][0]["mask"] = "mask.png"
    (tmp_path / "object.json").write_text(json.dumps(data))
    model = train_object(load_spec(tmp_path / "object.json"), TrainParams(novel=None))
    cam = model.viewsets[0].camera
    assert (cam.width, cam.height) == (359, 240) and cam.fx == pytest.approx(spec0.views[0].camera.fx / 2, rel=1e-3)
    assert len(model.viewsets[0]) > 200
    # its keypoints' 3-D points project onto them in the downscaled photo
    uv = cam.project(model.viewsets[0].pose.apply(model.viewsets[0].points3d))
    assert np.median(np.linalg.norm(uv - model.viewsets[0].keypoints, axis=1)) < 0.5


@pytest.mark.parametrize("kind", ["labels16", "cutout"])
def test_a_16_bit_or_transparent_mask_is_read_as_stored(tmp_path, kind):
    """'non-zero = object': a 16-bit label mask (1 = object) read as 8 bits was all zeros
    ("empty (no non-zero pixel)"); an RGBA cut-out (alpha = object, as an editor exports it) was
    read through its colour, here black: refused as empty too."""
    spec0 = load_spec(EXAMPLE / "object.json")
    from quatrack.viewsets.mesh import load_mesh

    v = spec0.views[0]
    silhouette = render(load_mesh(spec0.mesh_path), v.camera, v.pose).mask > 0
    if kind == "labels16":
        m = silhouette.astype(np.uint16)
    else:
        m = np.zeros(silhouette.shape + (4,), np.uint8)
        m[..., 3] = 255 * silhouette
    cv2.imwrite(str(tmp_path / "mask.png"), m)
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / data["mesh"])
    data["views"][0]["image"] = str(EXAMPLE / data["views"][0]["image"])
    data["views"][0]["mask"] = "mask.png"
    (tmp_path / "object.json").write_text(json.dumps(data))
    from quatrack.viewsets.train import _prepare_view

    spec = load_spec(tmp_path / "object.json")
    view = _prepare_view(load_mesh(spec.mesh_path), spec.views[0])
    np.testing.assert_array_equal(view.mask > 0, silhouette)


def test_a_photo_turned_by_its_exif_orientation_is_named_as_such(tmp_path):
    """A phone stores a portrait photo's pixels sideways with an EXIF tag to turn them; OpenCV
    turns them, and the message said "image is 480×718 but the view's camera is 718×480" of a
    file every tool shows as 718×480 stored pixels. Now it says why."""
    tiff = (b"MM\x00\x2a\x00\x00\x00\x08" + b"\x00\x01"
            + b"\x01\x12\x00\x03\x00\x00\x00\x01\x00\x06\x00\x00" + b"\x00\x00\x00\x00")  # Orientation = 6
    app1 = b"Exif\x00\x00" + tiff
    jpeg = (EXAMPLE / "resized_IMG_3875.JPG").read_bytes()
    (tmp_path / "photo.jpg").write_bytes(jpeg[:2] + b"\xff\xe1" + (len(app1) + 2).to_bytes(2, "big") + app1 + jpeg[2:])
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / data["mesh"])
    data["views"][0]["image"] = "photo.jpg"
    (tmp_path / "object.json").write_text(json.dumps(data))
    with pytest.raises(SpecError, match="image is 480×718 as shown \\(its EXIF orientation turns the 718×480 pixels"):
        train_object(load_spec(tmp_path / "object.json"), TrainParams(novel=None))


@pytest.mark.parametrize("cut", [20000, -3000])
def test_a_truncated_photo_is_one_line_naming_it(tmp_path, capfd, cut):
    """A photo cut short (an interrupted copy): OpenCV decodes it anyway, its missing part grey,
    with only libjpeg's "Premature end of JPEG file" on stderr; training then learned the grey,
    or failed with 'no keypoints ... is the pose right?'. Now: one line naming the file."""
    photo = tmp_path / "photo.jpg"
    photo.write_bytes((EXAMPLE / "resized_IMG_3875.JPG").read_bytes()[:cut])
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / data["mesh"])
    data["views"][0]["image"] = "photo.jpg"
    spec = tmp_path / "object.json"
    spec.write_text(json.dumps(data))
    store = tmp_path / "store"
    assert main(["train", str(spec), "--store", str(store), "--novel-views", "none", "--novel-scales", "none"]) == 2
    err = capfd.readouterr().err.strip()
    assert "photo.jpg: the file is truncated" in err and "\n" not in err and "Premature" not in err
    assert not store.exists() or list_models(store) == []


def test_train_object_names_an_argument_of_the_wrong_kind():
    # train_object("object.json") was AttributeError 'mesh_path', a dict of params AttributeError 'viewsets'
    with pytest.raises(TypeError, match=r"spec: an ObjectSpec \(quatrack.viewsets.spec.load_spec"):
        train_object(str(EXAMPLE / "object.json"))
    with pytest.raises(TypeError, match="params: a TrainParams"):
        train_object(load_spec(EXAMPLE / "object.json"), {"novel": None})

def test_every_stored_point_reprojects_onto_its_keypoint(trained_store):
    model = load_model(trained_store, "cookie-box")
    for vs in model.viewsets:
        assert vs.descriptors.dtype == np.float32 and vs.descriptors.shape == (len(vs), 128)
        uv = vs.camera.project(vs.pose.apply(vs.points3d))
        err = np.linalg.norm(uv - vs.keypoints, axis=1)
        assert err.max() < 1.0, vs.label
        # and every point lies on the box's surface (cm)
        lo, hi = model.mesh.vertices.min(0), model.mesh.vertices.max(0)
        P = vs.points3d
        assert np.all((P >= lo - 1e-6) & (P <= hi + 1e-6))
        assert np.all(np.min(np.minimum(np.abs(P - lo), np.abs(P - hi)), axis=1) < 1e-6)


def test_real_viewset_matches_the_photo():
    """Keypoints of the registered view are where SIFT finds them in the photo (not invented)."""
    spec = load_spec(EXAMPLE / "object.json")
    model = train_object(spec, TrainParams(novel=None))
    vs = model.viewsets[0]
    img = cv2.imread(str(spec.views[0].image_path), cv2.IMREAD_GRAYSCALE)
    kps, _ = cv2.SIFT_create().detectAndCompute(img, None)
    ref = np.array([k.pt for k in kps])
    d = np.min(np.linalg.norm(vs.keypoints[:, None, :].astype(float) - ref[None], axis=2), axis=1)
    assert np.median(d) < 0.5


# --- a second object of our own: a box with a procedural texture known at every 3-D point ---

FREQ = np.random.default_rng(7).normal(0.0, 1.6, size=(3, 4, 3))  # channel × wave × xyz, rad/cm
PHASE = np.random.default_rng(8).uniform(0, 2 * np.pi, size=(3, 4))


def texture(X: np.ndarray) -> np.ndarray:
    """BGR colour (n, 3) of the surface at object points X (n, 3)."""
    waves = np.sin(np.einsum("cwk,nk->ncw", FREQ, X) + PHASE[None])
    return np.clip(128 + 110 * np.tanh(1.5 * waves.sum(axis=2)), 0, 255)


def box(sx, sy, sz):
    from scipy.spatial import ConvexHull

    V = np.array([[x, y, z] for x in (0, sx) for y in (0, sy) for z in (0, sz)], float)
    return make_mesh(V, ConvexHull(V).simplices)


def write_ply(path, mesh):
    lines = ["ply", "format ascii 1.0", f"element vertex {len(mesh.vertices)}",
             "property float x", "property float y", "property float z",
             f"element face {len(mesh.faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(f"{c:g}" for c in v) for v in mesh.vertices]
    lines += ["3 " + " ".join(str(i) for i in f) for f in mesh.faces]
    path.write_text("\n".join(lines) + "\n")


def photograph(mesh, camera, pose):
    h, w = camera.height, camera.width
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    uv = np.stack([u.ravel(), v.ravel()], 1)
    X, f, _ = cast_rays(mesh, pose, undistort_pixels(camera, uv))
    img = np.full((h * w, 3), 90.0)
    img[f >= 0] = texture(X[f >= 0])
    return img.reshape(h, w, 3).astype(np.uint8)


@pytest.fixture(scope="module")
def textured_box(tmp_path_factory):
    d = tmp_path_factory.mktemp("tbox")
    mesh = box(12.0, 9.0, 6.0)
    camera = PinholeCamera(600.0, 600.0, 200.0, 150.0, width=400, height=300)
    rvec = np.array([2.1, -0.6, 0.3])
    R = cv2.Rodrigues(rvec)[0]
    t = np.array([0.0, 0.0, 45.0]) - R @ mesh.centre
    img = photograph(mesh, camera, Pose.from_matrix(R, t))
    cv2.imwrite(str(d / "photo.png"), img)
    write_ply(d / "box.ply", mesh)
    spec = {"name": "tbox", "mesh": "box.ply", "views": [{
        "image": "photo.png",
        "camera": {"width": 400, "height": 300, "fx": 600.0, "fy": 600.0, "cx": 200.0, "cy": 150.0},
        "pose": {"rvec": rvec.tolist(), "tvec": t.tolist()}}]}
    (d / "spec.json").write_text(json.dumps(spec))
    return d, mesh


def test_synthetic_viewsets_land_on_the_right_surfaces(textured_box):
    d, mesh = textured_box
    spec = load_spec(d / "spec.json")
    params = TrainParams(novel=NovelViewParams(angles_deg=(25.0,), axes="xy", scales=(0.7,)), jobs=2)
    model = train_object(spec, params)
    src = spec.views[0]
    photo = cv2.imread(str(src.image_path))
    src_buf = render(mesh, src.camera, src.pose)
    groups = planar_groups(mesh)
    synthetic = [v for v in model.viewsets if v.synthetic]
    assert len(synthetic) >= 4
    checked = 0
    for vs in synthetic:
        if len(vs) == 0:
            continue
        # the synthetic image (warped from the photo) must show, at each keypoint, the colour the
        # procedural texture has at the keypoint's stored 3-D point
        synth, textured, _ = render_textured_view(mesh, groups, photo, src.camera, src.pose, src_buf, vs.camera, vs.pose)
        ui = np.rint(vs.keypoints[:, 0]).astype(int)
        vi = np.rint(vs.keypoints[:, 1]).astype(int)
        err = np.abs(synth[vi, ui].astype(float) - texture(vs.points3d)).max(axis=1)
        assert np.median(err) < 25, vs.label
        assert np.mean(err < 60) > 0.9, vs.label
        # and the whole synthetic image agrees with an independent ray-cast rendering of the texture
        truth = photograph(mesh, vs.camera, vs.pose).astype(float)
        diff = np.abs(synth.astype(float) - truth).max(axis=2)[textured > 0]
        assert np.median(diff) < 15, vs.label
        uv = vs.camera.project(vs.pose.apply(vs.points3d))
        assert np.linalg.norm(uv - vs.keypoints, axis=1).max() < 1.0
        checked += len(vs)
    assert checked > 150


def test_keypoints_come_from_the_texture_not_the_background(textured_box):
    """Points of a synthetic viewset are textured-surface points: none on untextured faces."""
    d, mesh = textured_box
    spec = load_spec(d / "spec.json")
    model = train_object(spec, TrainParams(novel=NovelViewParams(angles_deg=(40.0,), axes="x", scales=())))
    src = spec.views[0].pose
    centre = -src.R.T @ src.t
    normals = mesh.face_normals
    for vs in model.viewsets:
        _, f, _ = cast_rays(mesh, vs.pose, undistort_pixels(vs.camera, vs.keypoints))
        assert np.all(f >= 0)
        # every hit face is one the photo sees from its front (a face hidden in the photo has no texture)
        to_cam = centre - mesh.triangles[f].mean(axis=1)
        assert np.all(np.einsum("ij,ij->i", normals[f], to_cam) * np.sign(
            np.einsum("ij,ij->i", normals[f], mesh.triangles[f].mean(axis=1) - mesh.centre)) > 0)


def test_query_features_describe_like_training(trained_store):
    from quatrack.viewsets.viewset import extract_query_features, params_from_manifest

    model = load_model(trained_store, "cookie-box")
    params = params_from_manifest(model.manifest)
    img = cv2.imread(str(EXAMPLE / "resized_IMG_3875.JPG"))
    q = extract_query_features(img, None, params)
    vs = [v for v in model.viewsets if not v.synthetic][0]
    # every stored keypoint of the photo's viewset is found again, with the same descriptor
    close, desc_err = _found_again(vs, q, 0.5)
    assert close.mean() > 0.8
    assert np.median(desc_err) < 0.1 * np.median(np.linalg.norm(vs.descriptors, axis=1))


def _found_again(a, b, px: float):
    """Which keypoints of ``a`` have one of ``b`` within ``px``, and how far those two's
    descriptors are apart."""
    d = np.linalg.norm(a.keypoints[:, None, :] - b.keypoints[None], axis=2)
    j = np.argmin(d, axis=1)
    close = d[np.arange(len(j)), j] < px
    return close, np.linalg.norm(a.descriptors[close] - b.descriptors[j[close]], axis=1)


def test_a_dim_query_is_brightened_before_sift_and_a_bright_one_is_left_alone():
    """``extract_query_features`` brightens a dim image until its 99th percentile reaches
    ``RUN_TIME_STRETCH`` (SIFT's contrast threshold is absolute): the zoo cube under 0.45 of the
    light keeps most of its keypoints, which plain SIFT loses, and they describe as under the
    full light (the same keypoints match their bright selves). A bright image is described
    exactly as without the stretch (training's photos are never stretched)."""
    from quatrack.testing import zoo as Z
    from quatrack.viewsets.features import RUN_TIME_STRETCH, extract_features
    from quatrack.viewsets.viewset import ViewsetParams, extract_query_features

    obj, cam = Z.textured("cube-m"), Z.zoo_camera()
    pose = Z.orbit_pose(obj, cam, 35.0)
    bright = Z.compose(*obj.render(cam, pose), Z.real_backgrounds()[0])
    bright = cv2.convertScaleAbs(bright, alpha=240.0 / np.percentile(cv2.cvtColor(bright, cv2.COLOR_BGR2GRAY), 99))
    dim = cv2.convertScaleAbs(bright, alpha=0.45)
    params = ViewsetParams()
    plain = dict(max_features=params.max_features, use_root_sift=params.root_sift,
                 contrast_threshold=params.contrast_threshold)
    full = extract_query_features(bright, None, params)
    unchanged = extract_features(bright, None, **plain)
    assert np.array_equal(full.keypoints, unchanged.keypoints) and np.array_equal(full.descriptors, unchanged.descriptors)
    raw = extract_features(dim, None, **plain)
    query = extract_query_features(dim, None, params)
    assert len(raw) < 0.6 * len(full) and len(query) > 0.8 * len(full), (len(raw), len(query), len(full))
    # the brightened keypoints are the bright image's: same place, nearly the same descriptor
    near, desc = _found_again(query, full, 1.0)
    assert near.mean() > 0.7
    assert np.median(desc) < 0.15 * np.median(np.linalg.norm(full.descriptors, axis=1))
    assert RUN_TIME_STRETCH > 200


@settings(max_examples=300, deadline=None)
@given(hnp.arrays(np.uint8, st.integers(1, 3000), elements=st.integers(0, 255)))
def test_the_percentile_from_the_histogram_is_numpys(values):
    """``percentile_99`` (a count, not a sort) gives np.percentile's very float: the dim-image
    rule it feeds was measured with np.percentile."""
    from quatrack.viewsets.features import percentile_99

    assert percentile_99(values) == float(np.percentile(values, 99))


def test_views_holding_max_features_are_not_weak_texture_however_large_their_box():
    """Keypoints per pixel of the box cannot exceed ``max_features`` over the box: a photo of
    6000×4000 px (or ``--max-features 100`` on the cookie box) read as weak texture, and training
    built the registered views three more times, at lower thresholds that could add nothing, and
    warned falsely. Views holding max_features keep the threshold asked for."""
    from quatrack.viewsets.viewset import ViewsetParams

    warnings = []
    params = TrainParams(novel=None, viewsets=ViewsetParams(max_features=100))
    model = train_object(load_spec(EXAMPLE / "object.json"), params, warn=warnings.append)
    assert model.manifest["parameters"]["viewsets"]["contrast_threshold"] == 0.04
    assert not any("weak texture" in w for w in warnings), warnings


def test_a_weakly_textured_object_is_trained_with_a_lower_contrast_threshold(tmp_path):
    """SIFT's contrast threshold is absolute: on a dark, weakly textured object (the zoo's tall
    box, a night sky: ~3 keypoints per 10 000 px of its box at 0.04) it keeps a handful of
    keypoints a view, too few for recognition. Training lowers it until the registered views give
    ``min_keypoint_density`` (down to ``min_contrast_threshold``), says so, and stores it with the
    model, so that queries are described alike; a well textured object keeps the default."""
    from quatrack.testing import zoo as Z
    from quatrack.viewsets.train import keypoint_density
    from quatrack.viewsets.viewset import params_from_manifest

    bgs = Z.real_backgrounds()[:1]
    fixed = TrainParams(novel=None, min_keypoint_density=None)
    adaptive = TrainParams(novel=None)
    weak = load_spec(Z.write_spec("tall-box-cm", tmp_path / "weak", 1, backgrounds=bgs))
    warnings: list[str] = []
    before, after = train_object(weak, fixed), train_object(weak, adaptive, warn=warnings.append)
    assert keypoint_density(before.viewsets) < adaptive.min_keypoint_density
    ct = params_from_manifest(after.manifest).contrast_threshold
    assert adaptive.min_contrast_threshold <= ct < params_from_manifest(before.manifest).contrast_threshold
    assert keypoint_density(after.viewsets) > 2 * keypoint_density(before.viewsets)
    assert sum(len(v) for v in after.viewsets) > 2 * sum(len(v) for v in before.viewsets)
    said = [w for w in warnings if "weak texture" in w]
    assert len(said) == 1 and f"lowered to {ct:g}" in said[0]  # (once, with the threshold kept)
    rich = load_spec(Z.write_spec("cube-m", tmp_path / "rich", 1, backgrounds=bgs))
    model = train_object(rich, adaptive, warn=warnings.append)
    assert keypoint_density(model.viewsets) >= adaptive.min_keypoint_density
    assert params_from_manifest(model.manifest).contrast_threshold == fixed.viewsets.contrast_threshold


@pytest.mark.parametrize("subdivisions", [4, 5], ids=["3072 faces", "12288 faces, decimated"])
def test_a_scanned_mesh_trains_synthetic_views_as_the_plain_one(tmp_path, subdivisions):
    """A scanned object's mesh — thousands of facets, each a plane of its own, its vertices a
    little off the true surface — trains synthetic views as the plain mesh does: their
    keypoints nearly as many, on the texture the photo shows at their 3-D points. (Until
    session 57 its facets were matched to the photo's by plane id, which a facet a few photo
    pixels wide rarely passes: no synthetic view kept a keypoint, and lifting them took minutes.)
    Over ``RUN_TIME_MAX_FACES`` faces the synthetic views are rendered on the mesh's decimation
    (``Mesh.run_time``), whose facets are the surface's, not the jitter's."""
    from quatrack.testing.scans import scanned
    from quatrack.viewsets.mesh import RUN_TIME_MAX_FACES

    plain = box(12.0, 9.0, 6.0)
    scan = scanned(plain, subdivisions, 0.0005, seed=0)
    assert len(scan.faces) >= 3000 and (len(scan.faces) > RUN_TIME_MAX_FACES) == (subdivisions == 5)
    camera = PinholeCamera(600.0, 600.0, 200.0, 150.0, width=400, height=300)
    rvec = np.array([2.1, -0.6, 0.3])
    R = cv2.Rodrigues(rvec)[0]
    t = np.array([0.0, 0.0, 45.0]) - R @ plain.centre
    params = TrainParams(novel=NovelViewParams(angles_deg=(25.0,), axes="xy", scales=()))
    kept = {}
    for name, mesh in (("plain", plain), ("scan", scan)):
        d = tmp_path / name
        d.mkdir()
        cv2.imwrite(str(d / "photo.png"), photograph(mesh, camera, Pose.from_matrix(R, t)))
        write_ply(d / "box.ply", mesh)
        spec = {"name": name, "mesh": "box.ply", "views": [{
            "image": "photo.png",
            "camera": {"width": 400, "height": 300, "fx": 600.0, "fy": 600.0, "cx": 200.0, "cy": 150.0},
            "pose": {"rvec": rvec.tolist(), "tvec": t.tolist()}}]}
        (d / "spec.json").write_text(json.dumps(spec))
        model = train_object(load_spec(d / "spec.json"), params)
        synthetic = [vs for vs in model.viewsets if vs.synthetic]
        kept[name] = sum(len(vs) for vs in synthetic)
        if name == "scan":
            assert len(synthetic) == 4
            photo = cv2.imread(str(d / "photo.png"))
            run = mesh.run_time  # (what the synthetic views were rendered on)
            for vs in synthetic:  # the colour at each keypoint is the texture's at its 3-D point
                synth, _, _ = render_textured_view(run, planar_groups(run), photo, camera, Pose.from_matrix(R, t),
                                                   render(run, camera, Pose.from_matrix(R, t)), vs.camera, vs.pose)
                ui, vi = np.rint(vs.keypoints[:, 0]).astype(int), np.rint(vs.keypoints[:, 1]).astype(int)
                err = np.abs(synth[vi, ui].astype(float) - texture(vs.points3d)).max(axis=1)
                assert np.median(err) < 25, vs.label
    assert kept["plain"] > 150 and kept["scan"] > (0.8 if subdivisions == 5 else 0.7) * kept["plain"]


def test_a_pose_locate_would_not_accept_in_its_own_photo_is_warned_of(tmp_path, capsys):
    """The registered rotation transposed (a camera → object rotation, or R written by columns):
    training learned the background around the misplaced mesh without a word. Now a warning
    says the mesh's edges miss the photo's; the correct pose gives none."""
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / data["mesh"])
    data["views"][0]["image"] = str(EXAMPLE / data["views"][0]["image"])
    pose = data["views"][0]["pose"]
    R = cv2.Rodrigues(np.array(pose["rvec"], float))[0]
    data["views"][0]["pose"] = {"R": R.T.tolist(), "t": pose["tvec"]}
    (tmp_path / "object.json").write_text(json.dumps(data))
    args = ["--store", str(tmp_path / "store"), "--novel-views", "none", "--novel-scales", "none"]
    assert main(["train", str(tmp_path / "object.json"), *args]) == 0
    assert "view 0: the mesh's edges at its pose lie on the photo's edges for" in capsys.readouterr().err
    assert main(["train", str(EXAMPLE / "object.json"), *args]) == 0
    assert "edges" not in capsys.readouterr().err

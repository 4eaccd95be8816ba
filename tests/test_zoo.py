"""The benchmark zoo: shapes in mm/cm/m, textured renders at known poses, trainable specs."""

import numpy as np
import pytest

from quatrack.testing import zoo as Z
from quatrack.viewsets.spec import load_spec


def test_zoo_has_shapes_units_and_textures():
    objs = Z.ZOO
    assert len(objs) >= 6
    assert {o.unit for o in objs} == {"mm", "cm", "m"}
    assert {o.shape for o in objs} >= {"box", "cylinder", "prism"}
    assert len({o.texture for o in objs}) >= 6
    for o in objs:
        assert Z.texture_path(o.texture).is_file()


def test_mesh_units_scale_the_same_shape():
    cube_m = Z.textured("cube-m")
    assert cube_m.diameter == pytest.approx(0.1 * np.sqrt(3), rel=1e-9)  # a 10 cm cube, in metres
    flat = Z.textured("flat-box-mm")
    assert np.ptp(flat.mesh.vertices, axis=0) == pytest.approx([240.0, 160.0, 40.0])


def test_render_is_textured_and_matches_the_silhouette():
    cam = Z.zoo_camera(320, 240)
    obj = Z.textured("cube-m")
    pose = Z.training_poses(obj, cam, 1)[0]
    img, sil = obj.render(cam, pose)
    assert 0.05 < sil.mean() < 0.5
    assert np.all(img[~sil] == 0)
    assert img[sil].std() > 20  # a photo's texture, not a flat colour
    # the silhouette's centre is where the pose puts the object's centre
    ys, xs = np.nonzero(sil)
    uv = cam.project((pose.R @ obj.mesh.centre + pose.t)[None])[0]
    assert abs(xs.mean() - uv[0]) < 6 and abs(ys.mean() - uv[1]) < 6


def test_scenes_are_deterministic_and_shift_out_of_frame():
    cam = Z.zoo_camera(320, 240)
    obj = Z.textured("hex-prism-m")
    base = Z.training_poses(obj, cam, 1)[0]
    bgs = (np.full((240, 320, 3), 90, np.uint8),)
    a = Z.random_scene(np.random.default_rng(3), obj, cam, base, bgs, 30.0, 0.4, grey=True)
    b = Z.random_scene(np.random.default_rng(3), obj, cam, base, bgs, 30.0, 0.4, grey=True)
    assert np.array_equal(a.image, b.image) and a.image.ndim == 2
    assert 0.3 < a.outside < 0.5


def test_written_spec_loads_with_its_views(tmp_path):
    path = Z.write_spec("small-cube-cm", tmp_path, n_views=4, grey=True, masks=True)
    spec = load_spec(path)
    assert len(spec.views) == 4 and spec.mesh_path.is_file()
    import cv2

    photo = cv2.imread(str(spec.views[0].image_path), cv2.IMREAD_UNCHANGED)
    assert photo.shape == (480, 640)  # grey: one channel
    mask = cv2.imread(str(spec.views[2].mask_path), cv2.IMREAD_GRAYSCALE)
    assert mask.any()


def test_backgrounds_are_frozen_files_installed_as_package_data(monkeypatch):
    """The scenes' room backgrounds are stored files (a change to recognition must not redraw
    the benchmark's scenes), loaded without running recognition, and listed as package data so
    a non-editable install has them."""
    from quatrack.recognition import locate as L
    from quatrack.testing import backgrounds as B
    from quatrack.testing import scenes as S

    def no_locate(*a, **k):
        raise AssertionError("backgrounds must be loaded, not recomputed by locate")

    monkeypatch.setattr(L, "locate", no_locate)
    B.frozen_backgrounds.cache_clear()
    bgs = S.video_backgrounds()
    assert len(bgs) == B.COUNT == 20
    assert all(a is b for a, b in zip(Z.real_backgrounds(), bgs, strict=True))  # one set, loaded once
    assert all(a is b for a, b in zip(S.video_backgrounds(limit=4), bgs[:4], strict=True))
    for bg in bgs:
        assert bg.shape == (480, 640, 3) and bg.dtype == np.uint8 and not bg.flags.writeable
        assert bg.std() > 20  # a photograph, not a blank frame
    files = B.background_paths()
    assert sum(p.stat().st_size for p in files) < 1_000_000
    assert (B.DATA / "README.md").is_file()  # source and licence
    from test_packaging_layout import shipped  # (pyproject's packages and package-data, as setuptools reads them)

    for p in [*files, B.DATA / "README.md"]:
        assert shipped(p.resolve()), f"{p} is not package data"


def test_the_example_store_is_removed_when_the_process_ends(tmp_path):
    # example_store() (bench locate / track, the tests) left a 2.6 MB quatrack-bench-* folder in
    # the temp dir after every process
    import os
    import subprocess
    import sys

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    r = subprocess.run([sys.executable, "-c", "from quatrack.testing.scenes import example_store as s; "
                        "p = s(); print(p, (p / 'cookie-box').is_dir())"],
                       env={**os.environ, "TMPDIR": str(tmp)}, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-500:]
    path, made = r.stdout.split()
    assert made == "True" and path.startswith(str(tmp))
    assert not list(tmp.iterdir())

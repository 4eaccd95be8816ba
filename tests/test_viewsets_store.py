"""The model store: atomic writes, name checks, and bad training input leaving the store untouched."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import quatrack.viewsets.store as store_mod
import quatrack.viewsets.viewset as viewset_mod
from quatrack.cli import main
from quatrack.viewsets.errors import StoreError
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.store import default_store, list_models, load_model, model_path, save_model
from quatrack.viewsets.train import TrainParams, train_object

from conftest import EXAMPLE, FAST_TRAIN as FAST  # (base_store and store: conftest's fixtures)


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file (and folder) under root with its bytes: equal snapshots = untouched store."""
    out = {}
    for p in sorted(root.rglob("*")):
        out[str(p.relative_to(root))] = p.read_bytes() if p.is_file() else b"<dir>"
    return out


def make_spec(tmp_path: Path, **view_changes) -> Path:
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / "box.ply")
    data["views"][0]["image"] = str(EXAMPLE / "resized_IMG_3875.JPG")
    mesh = view_changes.pop("mesh", None)
    if mesh is not None:
        data["mesh"] = mesh
    data["views"][0].update(view_changes)
    p = tmp_path / "spec.json"
    p.write_text(json.dumps(data))
    return p


def test_store_roundtrip_is_exact(base_store):
    m = load_model(base_store, "cookie-box")
    tmp = base_store.parent / "roundtrip"
    save_model(tmp, m)
    m2 = load_model(tmp, "cookie-box")
    for a, b in zip(m.viewsets, m2.viewsets):
        assert a.label == b.label and a.bbox == b.bbox
        np.testing.assert_array_equal(a.descriptors, b.descriptors)
        np.testing.assert_array_equal(a.points3d, b.points3d)
        np.testing.assert_array_equal(a.pose.R, b.pose.R)
        assert a.camera.fx == b.camera.fx and a.camera.width == b.camera.width
    np.testing.assert_array_equal(m.rfch.histogram, m2.rfch.histogram)
    np.testing.assert_array_equal(m.mesh.faces, m2.mesh.faces)
    assert len(m.appearance) == len(m2.appearance) == 1  # the photo's crop (viewsets/texture.py)
    for a, b in zip(m.appearance, m2.appearance):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.mask, b.mask)
        np.testing.assert_array_equal(a.pose.R, b.pose.R)
        assert (a.camera.fx, a.camera.cx, a.camera.width) == (b.camera.fx, b.camera.cx, b.camera.width)


def test_a_model_stored_without_photos_loads_with_none(base_store, tmp_path):
    """Models stored before session 36 have no ``ap_*`` arrays: they load, and recognition does
    not judge their poses by texture (LocateParams.min_texture_ncc needs photos)."""
    from dataclasses import replace

    m = load_model(base_store, "cookie-box")
    save_model(tmp_path, replace(m, appearance=[]))
    with np.load(model_path(tmp_path, "cookie-box") / store_mod.ARRAYS) as z:
        assert not [k for k in z.files if k.startswith("ap_")]
    assert load_model(tmp_path, "cookie-box").appearance == []


def test_the_photo_crop_keeps_what_the_photo_shows_of_the_object(base_store):
    """The stored crop is the photo's grey pixels round the object, and its mask is the object's
    silhouette at the photo's pose: the crop's camera projects the mesh where the crop shows it."""
    from quatrack.viewsets.render import render

    ref = load_model(base_store, "cookie-box").appearance[0]
    spec = load_spec(EXAMPLE / "object.json")
    photo = cv2.cvtColor(cv2.imread(str(spec.views[0].image_path)), cv2.COLOR_BGR2GRAY)
    sil = render(load_model(base_store, "cookie-box").mesh, ref.camera, ref.pose).face >= 0
    assert ref.mask.shape == ref.image.shape == sil.shape
    assert np.mean((ref.mask > 0) == sil) > 0.99 and sil.mean() > 0.5
    x0, y0 = int(round(spec.views[0].camera.cx - ref.camera.cx)), int(round(spec.views[0].camera.cy - ref.camera.cy))
    h, w = ref.image.shape
    np.testing.assert_array_equal(ref.image, photo[y0 : y0 + h, x0 : x0 + w])


def test_default_store_honours_env(monkeypatch, tmp_path):
    monkeypatch.delenv("QUATRACK_STORE", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert default_store() == tmp_path / "xdg" / "quatrack" / "models"
    monkeypatch.setenv("QUATRACK_STORE", str(tmp_path / "env"))
    assert default_store() == tmp_path / "env"


def test_cli_uses_quatrack_store_env(monkeypatch, tmp_path):
    monkeypatch.setenv("QUATRACK_STORE", str(tmp_path / "envstore"))
    assert main(["train", str(EXAMPLE / "object.json"), *FAST]) == 0
    assert list_models(tmp_path / "envstore") == ["cookie-box"]


@pytest.mark.parametrize("many", [False, True])
def test_a_full_disk_is_one_line_naming_the_object_and_the_store(store, capsys, monkeypatch, many):
    """The line said only "quatrack train: error: [Errno 28] No space left on device" (several
    specs: "SPEC: [Errno 28] ...", from viewsets.batch.train_one)."""
    import errno

    from quatrack.viewsets.batch import train_one

    def full(f, **arrays):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(store_mod.np, "savez_compressed", full)
    before = snapshot(store)
    if many:
        err = train_one(str(EXAMPLE / "object.json"), str(store), TrainParams(novel=None)).error
    else:
        assert main(["train", str(EXAMPLE / "object.json"), "--store", str(store), *FAST]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1
    assert f"cannot save 'cookie-box' in {store}: No space left on device" in err
    assert snapshot(store) == before


def test_delete_from_a_read_only_store_is_one_line_naming_the_object(store, capsys, monkeypatch):
    """The message named the temporary folder: "[Errno 30] Read-only file system: 'S/.del-cookie-box-3b75fim5'"."""
    import errno

    def read_only(src, dst, *a, **kw):
        raise OSError(errno.EROFS, "Read-only file system", str(src), None, str(dst))

    monkeypatch.setattr(os, "rename", read_only)  # (the folder is renamed to .del-NAME-… first)
    assert main(["models", "delete", "cookie-box", "--store", str(store)]) == 2
    err = capsys.readouterr().err
    assert f"cannot delete 'cookie-box' from {store} (Read-only file system)" in err and ".del-" not in err
    assert list_models(store) == ["cookie-box"]


def test_a_store_that_cannot_be_written_is_refused_before_training(tmp_path, capsys, monkeypatch):
    """A read-only store (a read-only mount, another user's folder): the whole training ran, then
    saving failed with "[Errno 30] Read-only file system: 'store/.tmp-cookie-box-5spzihae'"."""
    import quatrack.viewsets.train as train_mod

    store = tmp_path / "store"
    store.mkdir()
    store.chmod(0o555)
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == store else real(p, mode, **kw))  # (root ignores 0o555)
    monkeypatch.setattr(train_mod, "train_object", lambda *a, **kw: pytest.fail("trained"))
    try:
        for where in (store, store / "sub"):
            assert main(["train", str(EXAMPLE / "object.json"), "--store", str(where), *FAST]) == 2
            err = capsys.readouterr().err
            assert f"cannot write in {store}" in err and err.count("\n") == 1
    finally:
        store.chmod(0o755)


@pytest.mark.parametrize("action", [["list"], ["show", "cookie-box"], ["delete", "cookie-box"]])
def test_models_on_a_store_that_is_a_file_is_one_line(tmp_path, capsys, action):
    """`models list --store FILE` listed nothing, exit 0, as for an empty store (a typo'd path
    looked like a store without models); train says "not a directory": so do the models commands."""
    (tmp_path / "models").write_text("not a folder")
    assert main(["models", *action, "--store", str(tmp_path / "models")]) == 2
    err = capsys.readouterr().err
    assert "not a directory" in err and err.count("\n") == 1


def test_save_model_names_an_argument_of_the_wrong_kind(base_store, tmp_path):
    # save_model(store, "cookie-box") was AttributeError 'name'; save_model(None, model) pathlib's
    # "expected str, bytes or os.PathLike object, not NoneType"
    model = load_model(base_store, "cookie-box")
    with pytest.raises(TypeError, match="model: an ObjectModel"):
        save_model(tmp_path, "cookie-box")
    with pytest.raises(TypeError, match=r"store: a folder's path .*resolve_store"):
        save_model(None, model)
    assert not any(tmp_path.iterdir())

@pytest.mark.parametrize("name", ["../x", "..", ".hidden", "a/b", "", "x" * 65, "a b"])
def test_bad_names_cannot_escape(store, name):
    with pytest.raises(StoreError):
        model_path(store, name)
    before = snapshot(store)
    assert main(["models", "delete", name, "--store", str(store)]) == 2
    assert snapshot(store) == before


def test_failure_while_writing_leaves_old_model_intact(store, monkeypatch):
    before = snapshot(store)
    model = load_model(store, "cookie-box")
    model.manifest["marker"] = "new"

    def broken_savez(f, **arrays):
        f.write(b"PK partial")
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(store_mod.np, "savez_compressed", broken_savez)
    with pytest.raises(OSError):
        save_model(store, model)
    assert snapshot(store) == before  # no partial model, no temporary folder left


def test_failure_at_the_final_rename_restores_old_model(store, monkeypatch):
    before = snapshot(store)
    model = load_model(store, "cookie-box")
    real_replace = os.replace
    calls = []

    def flaky_replace(a, b):
        calls.append((a, b))
        if len(calls) == 2:  # the swap of the new folder into place
            raise OSError("rename failed (simulated)")
        return real_replace(a, b)

    monkeypatch.setattr(store_mod.os, "replace", flaky_replace)
    with pytest.raises(OSError):
        save_model(store, model)
    assert snapshot(store) == before


def test_failure_mid_training_leaves_store_untouched(store, monkeypatch, capsys):
    before = snapshot(store)
    calls = []
    real = viewset_mod.extract_features

    def failing(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise OSError("simulated crash in the middle of training")
        return real(*a, **k)

    monkeypatch.setattr(viewset_mod, "extract_features", failing)
    assert main(["train", str(EXAMPLE / "object.json"), "--store", str(store), "--jobs", "1"]) == 2
    assert len(calls) == 3
    assert snapshot(store) == before
    assert "simulated crash" in capsys.readouterr().err


def test_retraining_replaces_model(store):
    old = (store / "cookie-box" / "manifest.json").read_bytes()
    assert main(["train", str(EXAMPLE / "object.json"), "--store", str(store), *FAST, "--max-features", "300"]) == 0
    assert (store / "cookie-box" / "manifest.json").read_bytes() != old
    assert all(len(v) <= 300 for v in load_model(store, "cookie-box").viewsets)
    assert [p.name for p in store.iterdir()] == ["cookie-box"]


def test_a_model_folder_is_as_readable_as_the_umask_lets_it(base_store, tmp_path):
    """The model was written in a folder made by mkdtemp, 0700, and renamed into place with that
    mode: a server run by another user than the training (a system-wide store) could not read it.
    Its files followed the umask; now the folder does too."""
    model = load_model(base_store, "cookie-box")
    umask = os.umask(0o022)
    try:
        path = save_model(tmp_path / "store", model)
    finally:
        os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o755
    assert (path / "manifest.json").stat().st_mode & 0o777 == 0o644


def test_delete(store):
    assert main(["models", "delete", "cookie-box", "--store", str(store)]) == 0
    assert list_models(store) == [] and list(store.iterdir()) == []
    assert main(["models", "delete", "cookie-box", "--store", str(store)]) == 2


def _bad_inputs(tmp_path: Path) -> dict[str, tuple[Path, list[str], list[str]]]:
    """name → (spec, extra CLI args, words the one-line error must contain)."""
    garbage = tmp_path / "garbage.JPG"
    garbage.write_bytes(b"not a jpeg at all")
    pointcloud = tmp_path / "points.ply"
    pointcloud.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                          "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.full((480, 718, 3), 128, np.uint8))
    cases = {}
    d = tmp_path
    for key, changes, words in [
        ("missing image", {"image": str(d / "nope.jpg")}, ["view 0", "nope.jpg", "not found"]),
        ("unreadable image", {"image": str(garbage)}, ["view 0", "garbage.JPG", "unreadable"]),
        ("mesh without faces", {"mesh": str(pointcloud)}, ["points.ply", "no faces"]),
        ("non-positive focal", {"camera": {"width": 718, "height": 480, "fx": -1770.0, "fy": 1771.0, "cx": 359.0, "cy": 240.0}},
         ["view 0", "focal"]),
        ("behind camera", {"pose": {"rvec": [2.0269, -0.785, 0.3385], "tvec": [-0.6, 11.4, -116.5]}}, ["view 0", "behind the camera"]),
        ("outside image", {"pose": {"rvec": [2.0269, -0.785, 0.3385], "tvec": [300.0, 11.4, 116.5]}}, ["view 0", "0 pixels inside the image"]),
        ("unknown pose format", {"pose": {"euler": [1, 2, 3], "position": [0, 0, 1]}}, ["view 0", "unknown pose format"]),
        ("no keypoints anywhere", {"image": str(grey)}, ["no keypoints"]),
    ]:
        sub = d / key.replace(" ", "_")
        sub.mkdir()
        cases[key] = (make_spec(sub, **changes), [], words)
    return cases


CASES = ["missing image", "unreadable image", "mesh without faces", "non-positive focal", "behind camera",
         "outside image", "unknown pose format", "no keypoints anywhere"]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_refused_store_unchanged(store, tmp_path, capsys, case):
    spec, extra, words = _bad_inputs(tmp_path)[case]
    before = snapshot(store)
    code = main(["train", str(spec), "--store", str(store), *FAST, *extra])
    err = capsys.readouterr().err
    assert code == 2  # the README: bad input exits with status 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("quatrack train: error:"), err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert snapshot(store) == before


def test_duplicate_name_with_no_overwrite(store, capsys):
    before = snapshot(store)
    assert main(["train", str(EXAMPLE / "object.json"), "--store", str(store), "--no-overwrite", *FAST]) == 2
    assert "already exists" in capsys.readouterr().err
    assert snapshot(store) == before


def test_view_with_too_few_keypoints_warns_but_trains(tmp_path, capsys):
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.full((480, 718, 3), 128, np.uint8))
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / "box.ply")
    data["views"][0]["image"] = str(EXAMPLE / "resized_IMG_3875.JPG")
    data["views"].append(dict(data["views"][0], image=str(grey)))
    (tmp_path / "two.json").write_text(json.dumps(data))
    assert main(["train", str(tmp_path / "two.json"), "--store", str(tmp_path / "s"), *FAST]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "view1" in err
    model = load_model(tmp_path / "s", "cookie-box")
    assert [v.label for v in model.viewsets] == ["view0"]  # the empty view left no viewset


def test_training_is_deterministic():
    spec = load_spec(EXAMPLE / "object.json")
    a = train_object(spec, TrainParams(novel=None))
    b = train_object(spec, TrainParams(novel=None, jobs=2))
    np.testing.assert_array_equal(a.viewsets[0].descriptors, b.viewsets[0].descriptors)
    np.testing.assert_array_equal(a.rfch.centres, b.rfch.centres)
    np.testing.assert_array_equal(a.rfch.histogram, b.rfch.histogram)


# --- corrupt models: always that object's StoreError, never a traceback from deep inside ------------

CORRUPTIONS = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 0.999)),
    st.tuples(st.just("zero"), st.floats(0.0, 0.999), st.integers(1, 4096)),
    st.tuples(st.just("garble"), st.lists(st.tuples(st.floats(0.0, 0.999), st.integers(1, 255)), min_size=1, max_size=8)),
    st.tuples(st.just("manifest-key"), st.sampled_from([("parameters",), ("rfch",), ("viewsets",), ("schema_version",),
                                                      ("parameters", "rfch"), ("parameters", "rfch", "scales"),
                                                      ("rfch", "size_min")])),
    st.tuples(st.just("manifest-text"), st.sampled_from(["", "{", "[]", "null", '{"schema_version": 1}', "\x00" * 64,
                                                         "[" * 100_000])),
    st.tuples(st.just("remove"), st.sampled_from([store_mod.ARRAYS])),
)


def corrupt(folder: Path, how: tuple) -> None:
    arrays, manifest = folder / store_mod.ARRAYS, folder / store_mod.MANIFEST
    kind = how[0]
    if kind in ("truncate", "zero", "garble"):
        data = bytearray(arrays.read_bytes())
        if kind == "truncate":
            data = data[: int(how[1] * len(data))]
        elif kind == "zero":
            start = int(how[1] * len(data))
            data[start:start + how[2]] = bytes(len(data[start:start + how[2]]))
        else:
            for where, xor in how[1]:
                data[int(where * len(data))] ^= xor
        arrays.write_bytes(bytes(data))
    elif kind == "manifest-key":
        m = json.loads(manifest.read_text())
        node = m
        for key in how[1][:-1]:
            node = node[key]
        del node[how[1][-1]]
        manifest.write_text(json.dumps(m))
    elif kind == "manifest-text":
        manifest.write_text(how[1])
    else:
        (folder / how[1]).unlink()


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(how=CORRUPTIONS)
def test_any_corrupt_model_is_that_objects_store_error(base_store, tmp_path, how):
    """Fuzz: truncated, zeroed, garbled arrays and broken manifests. Loading raises StoreError
    naming the object in one line — or, when the damage missed the data (the zip's CRCs check
    every byte of it), returns exactly the original model."""
    import shutil

    s = tmp_path / "fuzz"
    shutil.rmtree(s, ignore_errors=True)
    shutil.copytree(base_store, s)
    corrupt(s / "cookie-box", how)
    assert list_models(s) == ["cookie-box"]  # still listed: it is broken, not absent
    try:
        model = load_model(s, "cookie-box")
    except StoreError as exc:
        msg = str(exc)
        assert "'cookie-box'" in msg and "\n" not in msg and len(msg) <= 500, msg
        return
    original = load_model(base_store, "cookie-box")
    np.testing.assert_array_equal(model.rfch.histogram, original.rfch.histogram)
    for a, b in zip(model.viewsets, original.viewsets, strict=True):
        np.testing.assert_array_equal(a.descriptors, b.descriptors)
        np.testing.assert_array_equal(a.points3d, b.points3d)
    for a, b in zip(model.appearance, original.appearance, strict=True):
        np.testing.assert_array_equal(a.image, b.image)


@pytest.mark.parametrize("how", [("truncate", 0.5), ("truncate", 0.0), ("zero", 0.3, 4096),
                                 ("manifest-key", ("parameters",))], ids=["truncated", "empty", "zeroed", "no-parameters"])
def test_cli_reports_a_corrupt_model_in_one_line(store, tmp_path, capsys, how):
    """The issue's four cases: BadZipFile, EOFError, zlib.error and KeyError tracebacks before."""
    import shutil

    shutil.copytree(store / "cookie-box", store / "other-box")
    m = json.loads((store / "other-box" / store_mod.MANIFEST).read_text())
    (store / "other-box" / store_mod.MANIFEST).write_text(json.dumps({**m, "name": "other-box"}))
    corrupt(store / "cookie-box", how)
    img = tmp_path / "x.png"
    cv2.imwrite(str(img), np.zeros((480, 640, 3), np.uint8))
    cam = str(EXAMPLE / "camera.json")
    for cmd in (["locate", "--object", "cookie-box", "--camera", cam, str(img)],
                ["track", "--object", "cookie-box", "--camera", cam, "--video", str(EXAMPLE / "box.mp4"), "--max-frames", "1",
                 "--out", str(tmp_path / "poses.csv")]):
        assert main([*cmd, "--store", str(store)]) == 2, cmd
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "'cookie-box'" in err and "Traceback" not in err, err
    assert main(["models", "list", "--store", str(store)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and lines[0].startswith("cookie-box\tBROKEN\t") and lines[1].startswith("other-box\t")
    assert "BROKEN" not in lines[1]
    assert main(["locate", "--object", "other-box", "--camera", cam, str(img), "--store", str(store)]) == 0
    capsys.readouterr()
    # --object all skips it with one warning line, as the other commands' warnings are written
    assert main(["locate", "--object", "all", "--camera", cam, str(img), "--store", str(store)]) == 0
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("quatrack locate: warning: object 'cookie-box': ") and \
        err.endswith("; skipped"), err


def test_stale_temporaries_are_removed_when_the_store_opens(store):
    """A training killed mid-write leaves .tmp-NAME-*; a retraining killed between its two
    renames leaves the previous model in .old-NAME-*/model with NAME missing."""
    import time

    old_time = time.time() - 2 * store_mod.STALE_AFTER_S
    stale = store / ".tmp-cookie-box-abc123"
    fresh = store / ".tmp-cookie-box-def456"
    for d in (stale, fresh):
        d.mkdir()
        (d / "model.npz").write_bytes(b"partial")
    orphan = store / ".old-cookie-box-xyz_9"
    orphan.mkdir()
    os.replace(store / "cookie-box", orphan / "model")
    for d in (stale, orphan):
        os.utime(d, (old_time, old_time))
    assert list_models(store) == []
    assert main(["models", "list", "--store", str(store)]) == 0  # opening the store cleans it
    assert sorted(p.name for p in store.iterdir()) == [fresh.name, "cookie-box"]  # a young one may be in use
    assert load_model(store, "cookie-box").name == "cookie-box"  # the previous model was put back

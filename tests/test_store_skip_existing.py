"""``train --skip-existing``: skips only a model that loads and was trained from these very inputs.

A store operator's trial: a broken model (truncated ``model.npz``) was "already trained … nothing
to do" for ever; an edited photo, mesh or camera file, or other training options, too (only the
spec file's bytes were compared); and with nothing to do, ``--no-overwrite`` ("already exists")
or a read-only store ("cannot write") failed the call, ``--no-overwrite`` naming only the first
existing object of several.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import pytest

import quatrack.viewsets.store as S
from quatrack.cli import main

from conftest import EXAMPLE, FAST_TRAIN

NAME = "cookie-box"


@pytest.fixture
def spec(tmp_path) -> Path:
    """The example object in a folder of its own: spec, mesh, photo and a camera file."""
    d = tmp_path / "obj"
    d.mkdir()
    data = json.loads((EXAMPLE / "object.json").read_text())
    shutil.copy(EXAMPLE / data["mesh"], d / "box.ply")
    shutil.copy(EXAMPLE / data["views"][0]["image"], d / "photo.jpg")
    (d / "camera.json").write_text(json.dumps(data["views"][0]["camera"]))
    data["mesh"] = "box.ply"
    data["views"][0].update(image="photo.jpg", camera="camera.json")
    (d / "object.json").write_text(json.dumps(data))
    return d / "object.json"


def train(spec: Path | list[Path], store: Path, *more: str) -> int:
    specs = spec if isinstance(spec, list) else [spec]
    return main(["train", *map(str, specs), "--store", str(store), "--skip-existing", *FAST_TRAIN, *more])


def trained_again(capsys) -> bool:
    out = capsys.readouterr().out
    assert ("nothing to do" in out) != out.startswith("trained "), out
    return out.startswith("trained ")


def test_a_broken_model_is_trained_again(spec, tmp_path, capsys):
    store = tmp_path / "store"
    assert train(spec, store) == 0 and trained_again(capsys)
    arrays = store / NAME / S.ARRAYS
    arrays.write_bytes(arrays.read_bytes()[:1000])  # truncated
    assert train(spec, store) == 0
    out, err = capsys.readouterr()
    assert out.startswith("trained "), out
    assert f"warning: {NAME!r} in {store}: the stored model is broken (" in err and "training it again" in err
    S.load_model(store, NAME)  # repaired
    assert train(spec, store) == 0 and not trained_again(capsys)


@pytest.mark.parametrize("change", ["photo", "mesh", "camera file", "option", "older manifest"])
def test_what_the_model_is_trained_from_is_compared(spec, tmp_path, capsys, change):
    store = tmp_path / "store"
    assert train(spec, store) == 0 and trained_again(capsys)
    assert train(spec, store) == 0 and not trained_again(capsys)
    more = []
    if change == "photo":
        img = cv2.imread(str(spec.parent / "photo.jpg"))
        img[:40, :40] = 255
        cv2.imwrite(str(spec.parent / "photo.jpg"), img)
    elif change == "mesh":
        with open(spec.parent / "box.ply", "a") as f:
            f.write("\n")  # (same mesh, other bytes: the file is what is compared)
    elif change == "camera file":
        cam = json.loads((spec.parent / "camera.json").read_text())
        (spec.parent / "camera.json").write_text(json.dumps({**cam, "fx": cam["fx"] * 1.01}))
    elif change == "option":
        more = ["--max-features", "1000"]
    else:  # a model trained before the inputs' checksum was recorded
        path = store / NAME / S.MANIFEST
        manifest = json.loads(path.read_text())
        del manifest["spec"]["inputs_sha256"]
        path.write_text(json.dumps(manifest))
    assert train(spec, store, *more) == 0
    out, err = capsys.readouterr()
    assert out.startswith("trained "), out
    why = "trained by an older quatrack" if change == "older manifest" else "the files it names or the training options changed"
    assert why in err
    assert train(spec, store, *more) == 0 and not trained_again(capsys)


def test_nothing_to_do_is_not_refused_by_no_overwrite_or_a_read_only_store(spec, tmp_path, capsys, monkeypatch):
    store = tmp_path / "store"
    assert train(spec, store) == 0 and trained_again(capsys)
    assert train(spec, store, "--no-overwrite") == 0 and not trained_again(capsys)
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **kw: False if Path(p) == store else real(p, mode, *a, **kw))
    assert train(spec, store) == 0 and not trained_again(capsys)
    second = spec.with_name("other.json")
    second.write_text(json.dumps({**json.loads(spec.read_text()), "name": "other"}))
    assert train([spec, second], store, "--jobs", "1") == 2  # (one to train: the store is refused)
    assert "cannot write in" in capsys.readouterr().err and not (store / "other").exists()


def test_no_overwrite_names_every_existing_object(spec, tmp_path, capsys, monkeypatch):
    store = tmp_path / "store"
    second = spec.with_name("other.json")
    second.write_text(json.dumps({**json.loads(spec.read_text()), "name": "other"}))
    assert train([spec, second], store, "--jobs", "1") == 0
    assert "2 of 2 objects trained" in capsys.readouterr().out
    assert train([spec, second], store, "--jobs", "1", "--no-overwrite") == 0  # nothing to do
    assert "0 of 2 objects trained locally" in capsys.readouterr().out
    with monkeypatch.context() as m:  # a read-only store with nothing to do: not refused either
        real = os.access
        m.setattr(os, "access", lambda p, mode, *a, **kw: False if Path(p) == store else real(p, mode, *a, **kw))
        assert train([spec, second], store, "--jobs", "1") == 0
        assert "0 of 2 objects trained locally" in capsys.readouterr().out
    args = ["train", str(spec), str(second), "--store", str(store), "--no-overwrite", "--jobs", "1", *FAST_TRAIN]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err == f"quatrack train: error: objects {NAME!r}, 'other' already exist in {store} (and --no-overwrite was given)\n"


def test_skip_existing_with_no_overwrite_says_one_thing(spec, tmp_path, capsys):
    """Inputs changed: ``--skip-existing --no-overwrite`` warned "…; training it again" and then
    failed with "already exists" (user report F8); now one error line says both."""
    store = tmp_path / "store"
    assert train(spec, store) == 0 and trained_again(capsys)
    photo = spec.parent / "photo.jpg"
    img = cv2.imread(str(photo))
    img[0, 0] = 255 - img[0, 0]
    cv2.imwrite(str(photo), img)
    second = spec.with_name("other.json")
    second.write_text(json.dumps({**json.loads(spec.read_text()), "name": "other"}))
    for specs in (spec, [spec, second]):
        assert train(specs, store, "--no-overwrite", "--jobs", "1") == 2
        out, err = capsys.readouterr()
        assert "training it again" not in err and "warning" not in err and len(err.splitlines()) == 1, err
        assert "already exist" in err and "--no-overwrite" in err and f"would train {NAME!r} again (" in err, err

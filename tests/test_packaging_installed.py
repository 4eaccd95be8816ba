"""The commands as someone who installed quatrack (a wheel, another folder) meets them.

A trial user found: ``train --skip-existing`` training again the same inputs copied to another
path (the checksum hashed absolute paths); ``quatrack train examples/cookie-box/object.json`` —
the README's line — outside a checkout saying only "cannot read spec (No such file or
directory)"; and ``quatrack register`` of the bundled example writing into site-packages.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import quatrack.register_cli as R
from quatrack.cli import main
from quatrack.examples import example_dir
from quatrack.viewsets.batch import inputs_checksum
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.train import TrainParams

from conftest import EXAMPLE


def _copy_example(to: Path) -> Path:
    """The example's spec with its mesh and photo, in ``to`` (as a user copies a folder)."""
    to.mkdir(parents=True)
    data = json.loads((EXAMPLE / "object.json").read_text())
    for f in (data["mesh"], data["views"][0]["image"]):
        shutil.copy(EXAMPLE / f, to / f)
    (to / "object.json").write_text(json.dumps(data))
    return to / "object.json"


def test_the_inputs_checksum_does_not_depend_on_where_the_inputs_are(tmp_path):
    a, b = _copy_example(tmp_path / "one"), _copy_example(tmp_path / "elsewhere" / "two")
    params = TrainParams()
    assert inputs_checksum(load_spec(a), params) == inputs_checksum(load_spec(b), params)
    photo = b.parent / json.loads(b.read_text())["views"][0]["image"]
    photo.write_bytes(photo.read_bytes()[:-1] + b"\0")  # (its contents still count)
    assert inputs_checksum(load_spec(a), params) != inputs_checksum(load_spec(b), params)


def test_train_of_the_readme_s_example_path_outside_a_checkout_says_where_it_is(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["train", "examples/cookie-box/object.json", "--store", str(tmp_path / "store")]) == 2
    err = capsys.readouterr().err.strip()
    installed = example_dir() / "object.json"
    assert err.startswith("quatrack train: error: examples/cookie-box/object.json: cannot read spec (No such file")
    assert f"the bundled example is installed at {installed}" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "store").exists()
    # another missing spec: the message as before, no hint
    assert main(["train", "mine/object.json", "--store", str(tmp_path / "store")]) == 2
    assert "bundled" not in capsys.readouterr().err


def test_register_of_a_spec_inside_the_installed_package_writes_to_the_current_folder(tmp_path, monkeypatch, capsys):
    installed = tmp_path / "site-packages" / "quatrack"
    spec = _copy_example(installed / "examples" / "cookie-box")
    here = tmp_path / "work"
    here.mkdir()
    monkeypatch.chdir(here)
    monkeypatch.setattr(R, "_package_folder", lambda: installed.resolve())
    assert main(["register", str(spec), "--no-edges"]) == 0
    out = capsys.readouterr().out
    assert not (spec.parent / "object.registered.json").exists()
    written = here / "object.registered.json"
    assert "is inside the installed quatrack, so in the current folder" in out and "wrote object.registered.json" in out
    assert load_spec(written).mesh_path == (spec.parent / "box.ply").resolve()  # (its paths rewritten for here)


def test_register_beside_the_spec_otherwise(tmp_path, monkeypatch, capsys):
    spec = _copy_example(tmp_path / "mine")
    monkeypatch.chdir(tmp_path)
    assert R.default_out(spec) == (spec.parent / "object.registered.json", None)
    monkeypatch.setattr(R.os, "access", lambda path, mode: Path(path) != spec.parent.resolve())  # (as root: chmod is no test)
    target, why = R.default_out(spec)
    assert target == Path("object.registered.json") and why.startswith(f"the spec's folder {spec.parent.resolve()} cannot be written")

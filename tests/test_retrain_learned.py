"""A retraining of an object whose model learned views while tracking (``track --learn``).

``quatrack train`` replaced the model and the learned views with it, after a warning before the
training. Now they are carried into the new model when they still fit it — the same mesh, the
same kind of descriptors — read and written under the store's lock (a ``track --learn`` run
storing its views meanwhile loses nothing); otherwise, or with ``--drop-learned``, they go and
the user is told how many. The cookie box trained without synthetic views (conftest's ``store``)
stands for the object; its learned views are its first view seen from cameras turned about its
centre (test_store_changes' ``turned_views``): new directions, real keypoints on the mesh.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import threading

import numpy as np
import trimesh

from conftest import EXAMPLE, FAST_TRAIN
from quatrack.cli import main
from quatrack.viewsets import learn as L
from quatrack.viewsets import store as S
from test_store_changes import turned_views

NAME = "cookie-box"


def _learned(store) -> list[str]:
    return [vs.label for vs in S.load_model(store, NAME).viewsets if vs.learned]


def _train(store, *extra, spec=EXAMPLE / "object.json") -> int:
    return main(["train", str(spec), "--store", str(store), *FAST_TRAIN, *extra])


def test_retraining_on_the_same_mesh_keeps_the_learned_views(store, capsys):
    model = S.load_model(store, NAME)
    assert L.merge_learned(store, NAME, turned_views(model), model.mesh)[1] == 2
    capsys.readouterr()
    assert _train(store, "--max-features", "300") == 0
    out, err = capsys.readouterr()
    assert "learned" not in err, err  # (no warning: nothing lost)
    assert "  views learned while tracking: 2 kept\n" in out, out
    back = S.load_model(store, NAME)
    assert _learned(store) == ["learned1", "learned2"] and back.manifest["learned_viewsets"] == 2
    trained = [vs for vs in back.viewsets if not vs.learned]
    assert trained and all(len(vs) <= 300 for vs in trained)  # (the new training's views)
    kept = {vs.label: vs for vs in back.viewsets if vs.learned}
    for vs in turned_views(model):  # the very views, points and descriptors
        assert np.array_equal(kept[vs.label].points3d, vs.points3d)
        assert np.array_equal(kept[vs.label].descriptors, vs.descriptors)
    assert not [p for p in store.iterdir() if p.name.startswith((".tmp-", ".old-"))]


def test_drop_learned_forgets_them_without_a_warning(store, capsys):
    model = S.load_model(store, NAME)
    L.merge_learned(store, NAME, turned_views(model), model.mesh)
    capsys.readouterr()
    assert _train(store, "--drop-learned") == 0
    out, err = capsys.readouterr()
    assert err == "" and "  views learned while tracking: 0 kept, 2 dropped (--drop-learned)\n" in out, (out, err)
    assert _learned(store) == [] and not S.load_model(store, NAME).manifest.get("learned_viewsets")


def _remodelled_spec(tmp_path):
    """The example's spec copied with its box scaled by 1.002 (a remodelled box: the learned
    views' points no longer lie on it); returns the spec's path."""
    spec_dir = tmp_path / "spec"
    shutil.copytree(EXAMPLE, spec_dir, ignore=shutil.ignore_patterns("*.mp4"))
    mesh = trimesh.load(spec_dir / "box.ply", process=False)
    mesh.vertices = mesh.vertices * 1.002
    mesh.export(spec_dir / "box.ply")
    return spec_dir / "object.json"


def test_a_new_mesh_drops_them_with_a_warning_saying_how_many(store, tmp_path, capsys):
    model = S.load_model(store, NAME)
    L.merge_learned(store, NAME, turned_views(model), model.mesh)
    capsys.readouterr()
    assert _train(store, spec=_remodelled_spec(tmp_path)) == 0
    out, err = capsys.readouterr()
    assert (f"quatrack train: warning: 'cookie-box' in {store} held 2 view(s) learned while tracking; 2 dropped: "
            f"the mesh changed (their 3-D points lie on the old one) (track --learn learns them again)") in err, err
    assert "0 kept, 2 dropped\n" in out and _learned(store) == []


def test_other_descriptors_drop_them(base_store):
    model = S.load_model(base_store, NAME)
    learned = L.with_learned(model, turned_views(model))
    manifest = json.loads(json.dumps(model.manifest))
    manifest["parameters"]["viewsets"]["root_sift"] = True
    rootsift = dataclasses.replace(model, manifest=manifest)
    carried, n, why = L.carry_learned(learned, rootsift)
    assert carried is rootsift and n == 0 and "descriptors" in why
    carried, n, why = L.carry_learned(learned, model)  # (the same settings: carried)
    assert n == 2 and why is None and carried.manifest["learned_viewsets"] == 2


def test_views_stored_while_the_retraining_is_saved_are_kept(store, monkeypatch):
    """A `track --learn` run storing its views between the retraining's read of the old model
    and its write: both hold the store's lock, so the run's merge waits and merges into the
    retrained model (without the lock the retraining's write replaced the merged model)."""
    model = S.load_model(store, NAME)
    views = turned_views(model, (60.0, 120.0, 180.0))
    L.merge_learned(store, NAME, views[:2], model.mesh)
    real = L.load_model
    threads = []

    def read_then_merge(store_, name):
        stored = real(store_, name)
        if not threads:  # (the retraining's read: a run stores its third view now)
            t = threading.Thread(target=L.merge_learned, args=(store, NAME, views[2:], model.mesh))
            t.start()
            threads.append(t)
            t.join(timeout=1.5)  # (held back by the lock: the retraining goes on and writes first)
        return stored

    monkeypatch.setattr(L, "load_model", read_then_merge)
    retrained = dataclasses.replace(model, manifest={**model.manifest, "created": "the retraining"})
    saved = L.save_trained(store, retrained)
    for t in threads:
        t.join()
    assert (saved.kept, saved.dropped) == (2, 0)
    back = S.load_model(store, NAME)
    assert back.manifest["created"] == "the retraining" and len(_learned(store)) == 3


def test_a_model_without_learned_views_is_replaced_without_a_word(store):
    saved = L.save_trained(store, S.load_model(store, NAME))
    assert (saved.kept, saved.dropped, saved.note(NAME, store)) == (0, 0, None)


def test_an_unreadable_model_with_learned_views_is_replaced_saying_they_were_lost(store, capsys):
    manifest = json.loads((store / NAME / "manifest.json").read_text())
    manifest["viewsets"][0]["learned"] = True
    (store / NAME / "manifest.json").write_text(json.dumps(manifest))
    (store / NAME / "model.npz").write_bytes(b"garbage")
    assert _train(store) == 0
    err = capsys.readouterr().err
    assert "held 1 view(s) learned while tracking; 1 dropped: the stored model cannot be read" in err, err
    assert _learned(store) == []


# -- several specs in one `train` (viewsets/batch.py): as one spec does ---------------------------

def _train_many(store, *specs, extra=()) -> int:
    """``train`` with the cookie box's spec(s) and a second object (test_train_many's renamed
    spec): the several-specs path, in this process (``--jobs 1``)."""
    return main(["train", *map(str, specs), "--store", str(store), "--jobs", "1", *FAST_TRAIN, *extra])


def test_several_specs_keep_the_learned_views_as_one_does(store, tmp_path, capsys):
    """They were dropped, after a warning that retraining replaces them, when the spec was
    trained with another (viewsets/batch.py saved with save_model, not save_trained)."""
    from test_train_many import renamed_spec

    model = S.load_model(store, NAME)
    assert L.merge_learned(store, NAME, turned_views(model), model.mesh)[1] == 2
    capsys.readouterr()
    assert _train_many(store, EXAMPLE / "object.json", renamed_spec(tmp_path, "box-two")) == 0
    out, err = capsys.readouterr()
    assert "learned" not in err, err
    line = next(x for x in out.splitlines() if x.startswith(f"trained {NAME!r}"))
    assert ", views learned while tracking: 2 kept," in line, out
    assert "learned" not in next(x for x in out.splitlines() if x.startswith("trained 'box-two'"))
    assert _learned(store) == ["learned1", "learned2"] and S.load_model(store, NAME).manifest["learned_viewsets"] == 2


def test_several_specs_pass_drop_learned_through(store, tmp_path, capsys):
    from test_train_many import renamed_spec

    model = S.load_model(store, NAME)
    L.merge_learned(store, NAME, turned_views(model), model.mesh)
    capsys.readouterr()
    assert _train_many(store, EXAMPLE / "object.json", renamed_spec(tmp_path, "box-two"), extra=["--drop-learned"]) == 0
    out, err = capsys.readouterr()
    assert "learned" not in err and ", views learned while tracking: 0 kept, 2 dropped (--drop-learned)," in out, (out, err)
    assert _learned(store) == []


def test_several_specs_say_per_object_why_learned_views_were_dropped(store, tmp_path, capsys):
    from test_train_many import renamed_spec

    model = S.load_model(store, NAME)
    L.merge_learned(store, NAME, turned_views(model), model.mesh)
    capsys.readouterr()
    spec = _remodelled_spec(tmp_path)
    assert _train_many(store, spec, renamed_spec(tmp_path, "box-two")) == 0
    out, err = capsys.readouterr()
    warned = [x for x in err.splitlines() if "learned while tracking" in x]
    assert warned == [f"quatrack train: warning: {spec}: 'cookie-box' in {store} held 2 view(s) "
                      f"learned while tracking; 2 dropped: the mesh changed (their 3-D points lie on the old one) "
                      f"(track --learn learns them again)"], err
    assert ", views learned while tracking: 0 kept, 2 dropped," in out and _learned(store) == []

"""Learned views survive a retraining on the same geometry written otherwise (trial report, item 1).

``learn.same_mesh`` compared the vertex and face arrays index by index: a re-export of the very
box (its vertices in another order) or the same triangles as STL (each triangle's corners stored
apart) was "the mesh changed", and ``train`` dropped every view learned on a walk round the
object. It now compares the surfaces: the sets of triangles by their corners' positions, within a
tolerance relative to the mesh's size. A mesh truly changed (scaled, a corner moved) still drops.
"""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import trimesh

from conftest import EXAMPLE, FAST_TRAIN
from quatrack.cli import main
from quatrack.viewsets import learn as L
from quatrack.viewsets import store as S
from quatrack.viewsets.mesh import load_mesh, make_mesh
from test_store_changes import turned_views

NAME = "cookie-box"


@pytest.fixture(scope="module")
def box():
    return load_mesh(EXAMPLE / "box.ply")


def _permuted(mesh, seed=7):
    """The same triangles with the vertices, the faces and each face's corners (cyclically, so the
    winding stays) in another order: what a re-export writes."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(mesh.vertices))
    inverse = np.argsort(perm)
    faces = inverse[mesh.faces][rng.permutation(len(mesh.faces))]
    faces = np.array([np.roll(f, int(k)) for f, k in zip(faces, rng.integers(0, 3, len(faces)))])
    return make_mesh(mesh.vertices[perm], faces)


def _split(mesh):
    """Each triangle's corners stored apart, as in an STL file (rounded to float32, as STL stores them)."""
    V = mesh.triangles.reshape(-1, 3).astype(np.float32).astype(float)
    return make_mesh(V, np.arange(len(V)).reshape(-1, 3))


def test_the_same_triangles_in_another_order_are_the_same_mesh(box):
    p = _permuted(box)
    assert not np.array_equal(p.vertices, box.vertices)  # (the old index-by-index comparison failed here)
    assert L.same_mesh(box, p) and L.same_mesh(p, box)


def test_the_same_triangles_with_split_vertices_are_the_same_mesh(box):
    s = _split(box)
    assert len(s.vertices) == 3 * len(box.faces) != len(box.vertices)
    assert L.same_mesh(box, s) and L.same_mesh(s, _permuted(box, seed=3))


def test_a_changed_mesh_is_another_mesh(box):
    assert not L.same_mesh(box, make_mesh(box.vertices * 1.002, box.faces))  # (remodelled: scaled)
    moved = box.vertices.copy()
    moved[0] += 0.01 * box.extent  # (one corner moved by 1 % of the size)
    assert not L.same_mesh(box, make_mesh(moved, box.faces))
    assert not L.same_mesh(box, make_mesh(box.vertices, box.faces[:-1]))  # (a face fewer)
    assert not L.same_mesh(box, make_mesh(box.vertices + 0.01 * box.extent, box.faces))  # (moved)


def test_carry_learned_keeps_the_views_on_a_permuted_or_split_mesh(base_store, box):
    model = S.load_model(base_store, NAME)
    learned = L.with_learned(model, turned_views(model))
    for mesh in (_permuted(model.mesh), _split(model.mesh)):
        carried, n, why = L.carry_learned(learned, dataclasses.replace(model, mesh=mesh))
        assert (n, why) == (2, None)
    changed = dataclasses.replace(model, mesh=make_mesh(model.mesh.vertices * 1.002, model.mesh.faces))
    assert L.carry_learned(learned, changed)[1:] == (0, "the mesh changed (their 3-D points lie on the old one)")


@pytest.mark.parametrize("fmt", ["ply", "stl"])
def test_train_on_a_reexported_mesh_keeps_the_learned_views(store, tmp_path, capsys, fmt):
    """End to end: the cookie box's spec with its mesh re-exported (vertices permuted) or as STL."""
    model = S.load_model(store, NAME)
    assert L.merge_learned(store, NAME, turned_views(model), model.mesh)[1] == 2
    spec_dir = tmp_path / "spec"
    shutil.copytree(EXAMPLE, spec_dir, ignore=shutil.ignore_patterns("*.mp4"))
    mesh = _permuted(load_mesh(spec_dir / "box.ply"))
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(spec_dir / f"again.{fmt}")
    spec = json.loads((spec_dir / "object.json").read_text())
    spec["mesh"] = f"again.{fmt}"
    (spec_dir / "object.json").write_text(json.dumps(spec))
    capsys.readouterr()
    assert main(["train", str(spec_dir / "object.json"), "--store", str(store), *FAST_TRAIN]) == 0
    out, err = capsys.readouterr()
    assert "dropped" not in err + out and "  views learned while tracking: 2 kept\n" in out, (out, err)
    assert [vs.label for vs in S.load_model(store, NAME).viewsets if vs.learned] == ["learned1", "learned2"]

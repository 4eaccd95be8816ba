"""Repeated and zero-area faces in a user's mesh file (viewsets/mesh.py): dropped on load with one
warning that counts them; what they broke (edges, closedness) is as the clean mesh's."""

import warnings

import numpy as np
import pytest
import trimesh

from quatrack.examples import example_dir
from quatrack.recognition.visibility import sharp_edges
from quatrack.viewsets.mesh import load_mesh, repeated_faces


@pytest.fixture(scope="module")
def box():
    return load_mesh(example_dir() / "box.ply")


def _write(tmp_path, vertices, faces, name="mesh.ply"):
    path = tmp_path / name
    trimesh.Trimesh(vertices, faces, process=False).export(str(path))
    return path


def test_repeated_faces_are_dropped_on_load_with_a_warning_that_counts_them(tmp_path, box):
    # a triangle of the box again, as given, turned and reversed: each edge of it had 3 faces,
    # the face's diagonal became a sharp edge (wireframe, the tracker's edges), a crease was
    # paired with the face's own copy (lost to the edge evidence) and the box was no longer closed
    F = box.faces
    mid = box.vertices[F[0, :2]].mean(axis=0)  # a point on an edge: a sliver of zero area through it
    V = np.r_[box.vertices, mid[None]]
    extra = np.array([F[0], F[0, [1, 2, 0]], F[3, ::-1],  # repeated: as given, turned, reversed
                      [F[0, 0], F[0, 1], len(box.vertices)], [F[1, 0], F[1, 0], F[1, 2]]])  # zero area
    told = []
    mesh = load_mesh(_write(tmp_path, V, np.r_[F, extra]), warn=told.append)
    assert told == [f"{tmp_path / 'mesh.ply'}: dropped 3 repeated faces (a triangle given again, in any corner order) "
                    f"and 2 faces of zero area"]
    assert np.array_equal(mesh.faces, box.faces) and np.array_equal(mesh.vertices, box.vertices)
    assert mesh.closed_outward and mesh.edge_faces[2].tolist() == [2] * 18
    assert len(sharp_edges(mesh)[0]) == len(sharp_edges(box)[0]) == 12


def test_repeats_are_found_by_position_as_an_stl_file_stores_its_triangles(tmp_path, box):
    # (an STL file stores each triangle's corners apart: its repeats share no vertex index)
    path = tmp_path / "box.stl"
    trimesh.Trimesh(box.vertices, np.r_[box.faces, box.faces[4:6, ::-1]], process=False).export(str(path))
    told = []
    mesh = load_mesh(path, warn=told.append)
    assert len(mesh.faces) == 12 and mesh.closed_outward
    assert told == [f"{path}: dropped 2 repeated faces (a triangle given again, in any corner order)"]


def test_without_warn_a_library_caller_gets_a_user_warning(tmp_path, box):
    path = _write(tmp_path, box.vertices, np.r_[box.faces, box.faces[:1]])
    with pytest.warns(UserWarning, match=r"dropped 1 repeated face \(a triangle"):
        assert len(load_mesh(path).faces) == 12


def test_a_clean_mesh_loads_as_before_without_a_word(tmp_path, box):
    told = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = load_mesh(_write(tmp_path, box.vertices, box.faces), warn=told.append)
    assert told == [] and np.array_equal(again.faces, box.faces) and np.array_equal(again.vertices, box.vertices)


def test_repeated_faces_marks_later_copies_only():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 0.0]])  # vertex 4 is vertex 1's position
    F = np.array([[0, 1, 2], [0, 2, 3], [2, 0, 4], [3, 2, 0], [1, 2, 3]])
    assert repeated_faces(V, F).tolist() == [False, False, True, True, False]
    assert repeated_faces(V, np.array([[0, 1, 9]])).tolist() == [False]  # (invalid: left to make_mesh)


def test_two_parts_of_a_scene_in_the_same_place_are_one_surface(tmp_path, box):
    # a GLB whose second part lies on the first (its node's transform puts it back there): the
    # same triangles twice; the scene's note and the repeats' count, one surface left
    T = np.eye(4)
    T[:3, 3] = [10.0, 0, 0]
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.Trimesh(box.vertices, box.faces, process=False), node_name="body")
    scene.add_geometry(trimesh.Trimesh(box.vertices - [10.0, 0, 0], box.faces, process=False), node_name="lid",
                       transform=T)
    scene.export(str(tmp_path / "parts.glb"))
    told = []
    mesh = load_mesh(tmp_path / "parts.glb", warn=told.append)
    assert len(mesh.faces) == 12 and mesh.closed_outward and len(mesh.vertices) == 8
    assert len(told) == 2 and "its 2 meshes" in told[0] and "dropped 12 repeated faces" in told[1]

"""Faces joined by position, not by vertex index (viewsets/mesh.py, Mesh.edge_faces): a mesh whose
triangles store their corners apart (STL) or whose vertices a seam splits has the edges of the
same mesh stored joined."""

import numpy as np
import pytest
import trimesh

from quatrack.examples import example_dir
from quatrack.recognition.evidence import EdgeParams, edge_samples
from quatrack.recognition.visibility import sharp_edges
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import load_mesh, make_mesh


@pytest.fixture(scope="module")
def box():
    return load_mesh(example_dir() / "box.ply")


def _segments(E: np.ndarray) -> set:
    return {tuple(sorted(map(tuple, np.round(e, 9).tolist()))) for e in E}


def test_an_stl_mesh_has_the_edges_of_the_same_mesh_joined(tmp_path, box):
    # by index every edge of the STL box was its boundary: 36 "sharp" edges, the faces' diagonals
    # among them, which the edge evidence and the tracker then looked for in the image
    path = tmp_path / "box.stl"
    trimesh.Trimesh(box.vertices, box.faces, process=False).export(str(path))
    stl = load_mesh(path)
    assert len(stl.vertices) == 36 and len(stl.faces) == 12  # (its corners stay apart)
    assert stl.edge_faces[2].tolist() == [2] * 18
    assert _segments(sharp_edges(stl)[0]) == _segments(sharp_edges(box)[0]) and len(sharp_edges(box)[0]) == 12
    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, width=640, height=480)
    turn = Pose.from_rvec([0.5, 0.6, 0.2], [0.0, 0.0, 0.0])
    pose = Pose.from_rvec([0.5, 0.6, 0.2], -turn.apply(box.centre[None])[0] + [0.0, 0.0, 6 * box.extent])
    ours, theirs = edge_samples(stl, cam, pose, EdgeParams()), edge_samples(box, cam, pose, EdgeParams())
    assert len(ours[0]) == len(theirs[0]) > 0
    assert {tuple(p) for p in np.round(ours[0], 6)} == {tuple(p) for p in np.round(theirs[0], 6)}


def test_a_seam_does_not_open_the_surface_and_a_joined_mesh_is_unchanged(box):
    # one face's corners given again as vertices of their own (a texture seam): the same edges
    V = np.r_[box.vertices, box.vertices[box.faces[0]]]
    F = box.faces.copy()
    F[0] = len(box.vertices) + np.arange(3)
    seam = make_mesh(V, F)
    assert seam.edge_faces[2].tolist() == [2] * 18
    assert _segments(sharp_edges(seam)[0]) == _segments(sharp_edges(box)[0])
    fresh = make_mesh(box.vertices, box.faces)
    edges, faces, counts = fresh.edge_faces  # joined already: the arrays the indices gave, dtype too
    F = box.faces
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    assert edges.dtype == F.dtype and {tuple(x) for x in edges.tolist()} == {tuple(x) for x in e.tolist()}


def _area(mesh) -> float:
    tri = mesh.triangles
    return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


def test_an_stl_scans_run_time_mesh_is_decimated_as_the_same_scan_stored_joined(tmp_path, box):
    # decimation collapses edges between faces sharing vertices: the STL scan's triangles share
    # none, and its run-time mesh was 5 000 of its 49 152 triangles kept — a surface of holes
    from quatrack.testing.scans import scanned

    scan = scanned(box, 6, 0.001, 0)
    trimesh.Trimesh(scan.vertices, scan.faces, process=False).export(str(tmp_path / "scan.stl"))
    stl = load_mesh(tmp_path / "scan.stl")
    assert len(stl.vertices) == 3 * len(stl.faces) and len(stl.faces) > 5000
    ours, theirs = stl.run_time, scan.run_time
    assert len(ours.faces) == len(theirs.faces) and len(ours.vertices) == len(theirs.vertices)
    assert abs(_area(ours) / _area(theirs) - 1.0) < 0.01 and _area(ours) > 0.9 * _area(scan)  # (was ~0.1: holes)

"""Users' mesh files as exporters write them (viewsets/mesh.py: load_mesh, simplified): valid
files read as they mean, a wrong or broken file named by its cause in one line."""

import numpy as np
import pytest

from quatrack.examples import example_dir
from quatrack.viewsets.mesh import load_mesh


@pytest.fixture(scope="module")
def box():
    return load_mesh(example_dir() / "box.ply")


def _sorted_triangles(mesh):
    """The mesh's triangles as sets of corner positions, in one order (for comparing files)."""
    tri = np.round(mesh.triangles, 9)
    tri = np.sort(tri.view([("", tri.dtype)] * 3).reshape(-1, 3), axis=1)
    return sorted(map(tuple, tri.tolist()))


def test_an_obj_of_relative_indices_after_each_triangles_vertices_reads_every_triangle(tmp_path, box):
    # "v a; v b; v c; f -3 -2 -1" again and again (valid OBJ): trimesh counted back from the
    # file's last vertex, every face was the last triangle, and training made a 1-triangle model
    path = tmp_path / "relative.obj"
    with open(path, "w") as f:
        for tri in box.triangles:
            f.writelines("v %.17g %.17g %.17g\n" % tuple(p) for p in tri)
            f.write("vn 0 0 1\nf -3//-1 -2//-1 -1//-1\n")
    told = []
    mesh = load_mesh(path, warn=told.append)
    assert told == []
    assert len(mesh.faces) == 12 and mesh.closed_outward
    assert _sorted_triangles(mesh) == _sorted_triangles(box)

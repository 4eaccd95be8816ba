"""Users' mesh files as exporters write them (viewsets/mesh.py: load_mesh, simplified): valid
files read as they mean, a wrong or broken file named by its cause in one line."""

import numpy as np
import pytest

from quatrack.examples import example_dir
from quatrack.viewsets.mesh import load_mesh, make_mesh, simplified


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


def _scan(seed=0, subdivisions=4):
    """A jittered sphere of ~5 000 triangles in metres, as a scan's surface (seeded)."""
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.08)
    V = np.asarray(tm.vertices) * (1 + 0.002 * np.random.default_rng(seed).standard_normal((len(tm.vertices), 1)))
    return make_mesh(V + [0.3, -0.1, 0.05], tm.faces)


def test_a_scan_is_decimated_alike_in_mm_and_m():
    # fast_simplification's thresholds are absolute: the same scan in mm, cm and m was decimated
    # to other facets (other planar groups, other locate results per unit)
    metres = _scan()
    in_m = simplified(metres, 800)
    in_mm = simplified(make_mesh(metres.vertices * 1000.0, metres.faces), 800)
    assert np.array_equal(in_mm.faces, in_m.faces)
    assert np.allclose(in_mm.vertices, in_m.vertices * 1000.0, rtol=0, atol=1e-9 * 1000.0 * metres.extent)

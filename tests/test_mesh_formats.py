"""Users' mesh files as exporters write them (viewsets/mesh.py: load_mesh, simplified): valid
files read as they mean, a wrong or broken file named by its cause in one line."""

import numpy as np
import pytest

from quatrack.examples import example_dir
from quatrack.viewsets.errors import SpecError
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


def _load_error(path):
    with pytest.raises(SpecError) as info:
        load_mesh(path, warn=lambda _: None)
    return str(info.value)


def test_an_empty_mesh_file_is_named_as_empty(tmp_path):
    # (was "the mesh has no vertices", or "cannot read mesh (ValueError: Not a ply file!)")
    for name in ("empty.obj", "empty.stl", "empty.ply"):
        (tmp_path / name).write_bytes(b"")
        assert _load_error(tmp_path / name) == f"{tmp_path / name}: the file is empty (0 bytes)"


@pytest.mark.parametrize("real, named", [("ply", "obj"), ("stl", "obj"), ("off", "obj"), ("ply", "stl"),
                                         ("stl", "ply"), ("obj", "ply"), ("glb", "ply")])
def test_a_mesh_file_under_another_format_s_extension_is_told_to_be_renamed(tmp_path, box, real, named):
    # (a PLY/STL/OFF as .obj, a PLY as .stl: "the mesh has no vertices"; an STL/OBJ/GLB as .ply:
    # "cannot read mesh (ValueError: Not a ply file!)")
    import trimesh

    tm = trimesh.Trimesh(box.vertices, box.faces, process=False)
    path = tmp_path / f"box.{named}"
    data = tm.export(file_type=real)
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    name = {"ply": "PLY", "stl": "STL", "off": "OFF", "obj": "OBJ", "glb": "GLB"}
    assert _load_error(path) == (f"{path}: its content looks like {name[real]}, not {name[named]} as its extension "
                                 f"says (rename it to .{real})")
    renamed = path.rename(tmp_path / f"box.{real}")
    assert len(load_mesh(renamed, warn=lambda _: None).faces) == 12


def test_a_binary_stl_cut_short_says_so(tmp_path, box):
    import trimesh

    data = trimesh.Trimesh(box.vertices, box.faces, process=False).export(file_type="stl")
    (tmp_path / "cut.stl").write_bytes(data[:300])
    assert _load_error(tmp_path / "cut.stl") == (f"{tmp_path / 'cut.stl'}: not a whole binary STL file: its header "
                                                 f"counts 12 triangles, 684 bytes, the file has 300 (cut short?)")
    # a binary STL whose header begins with "solid" (as some exporters write it) is read as binary
    (tmp_path / "solid.stl").write_bytes(b"solid box" + data[9:])
    assert len(load_mesh(tmp_path / "solid.stl", warn=lambda _: None).faces) == 12


def test_an_obj_face_naming_a_vertex_the_file_lacks_names_both(tmp_path, box):
    # (was "cannot read mesh (IndexError: index 98 is out of bounds for axis 0 with size 8)")
    lines = ["v %.17g %.17g %.17g" % tuple(p) for p in box.vertices]
    lines += ["f %d %d %d" % tuple(f + 1) for f in box.faces] + ["f 1 2 99"]
    (tmp_path / "bad.obj").write_text("\n".join(lines) + "\n")
    assert _load_error(tmp_path / "bad.obj") == f"{tmp_path / 'bad.obj'}: face 13 refers to vertex 99 of 8"
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nf -1 -2 -3\n")
    assert _load_error(tmp_path / "bad.obj") == f"{tmp_path / 'bad.obj'}: face 1 refers to vertex -3 of the 2 given before it"


def test_a_gltf_without_its_buffer_file_names_the_missing_file(tmp_path, box):
    # (was "cannot read mesh (FileNotFoundError: gltf_buffer_0.bin)")
    import trimesh

    scene = trimesh.Scene(trimesh.Trimesh(box.vertices, box.faces, process=False))
    for name, data in scene.export(file_type="gltf").items():
        (tmp_path / name).write_bytes(data)
    buffers = sorted(p.name for p in tmp_path.glob("*.bin"))
    assert buffers and len(load_mesh(tmp_path / "model.gltf", warn=lambda _: None).faces) == 12
    (tmp_path / buffers[0]).rename(tmp_path / "elsewhere")
    assert _load_error(tmp_path / "model.gltf") == (f"{tmp_path / 'model.gltf'}: the glTF's buffer file {buffers[0]} "
                                                    f"is missing beside it")


def _octagon_box():
    """A 2×2×2 box whose six sides are each one polygon of 8 corners: its 4 corners and the
    midpoints of its 4 edges between them (as a CAD exporter writes a side its neighbours split)."""
    points, polygons = [], []

    def at(p):
        p = tuple(float(c) for c in p)
        if p not in points:
            points.append(p)
        return points.index(p)

    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        for sign in (-1, 1):
            ring = []
            for cu, cv in [(-1, -1), (1, -1), (1, 1), (-1, 1)]:
                p = np.zeros(3)
                p[axis], p[u], p[v] = sign, cu, cv
                ring.append(p)
            corners = []
            for k in range(4):
                corners += [at(ring[k]), at((ring[k] + ring[(k + 1) % 4]) / 2)]
            polygons.append(corners)
    return points, polygons


@pytest.mark.parametrize("kind", ["obj", "off", "ply"])
def test_faces_dropped_from_triangulated_polygons_are_not_blamed_on_the_file(tmp_path, kind):
    # trimesh fans a polygon out from one corner: an 8-corner side with its edges' midpoints gives
    # triangles of zero area (and repeated ones), and the warning said the file gave them
    points, polygons = _octagon_box()
    path = tmp_path / f"octagons.{kind}"
    if kind == "obj":
        text = "".join("v %g %g %g\n" % p for p in points) + "".join(
            "f " + " ".join(str(i + 1) for i in poly) + "\n" for poly in polygons)
    elif kind == "off":
        text = f"OFF\n{len(points)} {len(polygons)} 0\n" + "".join("%g %g %g\n" % p for p in points) + "".join(
            f"{len(poly)} " + " ".join(map(str, poly)) + "\n" for poly in polygons)
    else:
        text = (f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
                f"property float z\nelement face {len(polygons)}\nproperty list uchar int vertex_indices\n"
                f"end_header\n" + "".join("%g %g %g\n" % p for p in points)
                + "".join(f"{len(poly)} " + " ".join(map(str, poly)) + "\n" for poly in polygons))
    path.write_text(text)
    told = []
    mesh = load_mesh(path, warn=told.append)
    assert len(told) == 1 and told[0].startswith(f"{path}: dropped ")
    assert told[0].endswith(" after triangulating its polygons") and "given again" not in told[0]
    assert np.allclose(mesh.vertices.min(axis=0), -1) and np.allclose(mesh.vertices.max(axis=0), 1)


def test_the_seam_between_two_bodies_of_a_scene_that_touch_flat_is_no_edge(tmp_path):
    # two halves of a box joined at x = 0, each placed by its node's translation: each half's side
    # at x = 0 lay inside the object, and the ring round it (four faces on each edge) was a sharp
    # edge of the model the photo does not show
    import trimesh

    from quatrack.recognition.visibility import sharp_edges

    scene = trimesh.Scene()
    for name, x in (("left", -40.0), ("right", 40.0)):
        scene.add_geometry(trimesh.creation.box(extents=(80, 110, 60)), node_name=name,
                           transform=trimesh.transformations.translation_matrix([x, 0, 0]))
    scene.export(str(tmp_path / "halves.glb"))
    told = []
    mesh = load_mesh(tmp_path / "halves.glb", warn=told.append)
    assert told[-1] == f"{tmp_path / 'halves.glb'}: dropped 4 faces where its meshes touch (inside the object)"
    assert mesh.closed_outward and len(mesh.faces) == 20
    E, _ = sharp_edges(mesh)
    whole = sharp_edges(make_mesh(trimesh.creation.box(extents=(160, 110, 60)).vertices,
                                  trimesh.creation.box(extents=(160, 110, 60)).faces))[0]
    assert not np.any(np.all(np.abs(E[:, :, 0]) < 1e-9, axis=1))  # no edge runs along the seam
    length = lambda e: float(np.linalg.norm(e[:, 1] - e[:, 0], axis=1).sum())  # noqa: E731
    assert length(E) == pytest.approx(length(whole))

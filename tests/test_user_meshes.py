"""Users' own meshes and specs: the formats exporters write, their quirks, and the messages a
mistake gets (one line, naming the culprit, nothing stored)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from quatrack.cli import main
from quatrack.viewsets.errors import SpecError
from quatrack.viewsets.mesh import load_mesh
from quatrack.viewsets.spec import parse_pose

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cookie-box"

# a 2 × 3 × 1 box: 8 corners, its 6 sides as quads (outward)
CORNERS = np.array([[x, y, z] for x in (0, 2.0) for y in (0, 3.0) for z in (0, 1.0)])
QUADS = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]


def _triangles(quads):
    return np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def test_a_folder_named_as_the_mesh_is_called_a_folder(tmp_path):
    (tmp_path / "box.ply").mkdir()
    with pytest.raises(SpecError, match="a folder, not a mesh file"):
        load_mesh(tmp_path / "box.ply")


def test_a_file_of_another_kind_named_as_the_mesh_says_which_formats_are_read(tmp_path):
    cv2.imwrite(str(tmp_path / "texture.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(SpecError) as info:
        load_mesh(tmp_path / "texture.png")
    msg = str(info.value)
    assert "not a mesh file format" in msg and ".png" in msg and "PLY, OBJ" in msg
    assert "NotImplementedError" not in msg


def _rotation(seed=3):
    return cv2.Rodrigues(np.random.default_rng(seed).normal(size=(3, 1)))[0]


def test_a_4x4_matrix_for_a_pose_is_told_how_to_give_it():
    R, t = _rotation(), [1.0, 2.0, 30.0]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    with pytest.raises(SpecError, match="'R' is a 4×4 matrix; give its top-left 3×3 as 'R'"):
        parse_pose({"R": T.tolist(), "t": t}, "view 0: pose")
    with pytest.raises(SpecError, match="'T' is a 4×4 matrix; give its top-left 3×3 as 'R'"):
        parse_pose({"T": T.tolist()}, "view 0: pose")
    done = parse_pose({"R": T[:3, :3].tolist(), "t": T[:3, 3].tolist()})  # (as the message says)
    np.testing.assert_allclose(done.R, R, atol=1e-12)


def test_a_rotation_written_with_three_decimals_is_taken():
    """Rounded to 3 decimals, R·Rᵀ is up to 1.5e-3 off the identity: one in five such matrices
    was refused as 'not a rotation matrix'."""
    worst = max(range(200), key=lambda s: np.abs(np.round(_rotation(s), 3) @ np.round(_rotation(s), 3).T - np.eye(3)).max())
    Rr = np.round(_rotation(worst), 3)
    assert np.abs(Rr @ Rr.T - np.eye(3)).max() > 1e-3  # (what was refused)
    pose = parse_pose({"R": Rr.tolist(), "t": [0, 0, 1]})
    np.testing.assert_allclose(pose.R, _rotation(worst), atol=2e-3)
    assert np.allclose(pose.R @ pose.R.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("change, words", [
    (lambda R: 10 * R, "it scales by 10"),
    (lambda R: -R, "determinant is -1 (a mirror"),
    (lambda R: R + [[0, 0.2, 0], [0, 0, 0], [0, 0, 0]], "differs from the identity by up to"),
])
def test_a_matrix_that_is_no_rotation_is_said_what_it_is(change, words):
    with pytest.raises(SpecError) as info:
        parse_pose({"R": change(_rotation()).tolist(), "t": [0, 0, 1]}, "view 2: pose")
    assert "view 2: pose: field 'R' is not a rotation matrix" in str(info.value) and words in str(info.value)


@pytest.mark.parametrize("case", range(6))
def test_a_large_mesh_is_rewound_as_trimesh_rewinds_it(case):
    """Above FAST_WINDING_FACES faces, a mesh wound inconsistently (part of a scan's normals
    inverted) is re-wound on arrays (trimesh's fix_winding, a Python loop over the faces, took 27 s
    of a 590 000-face scan's 47 s of training): the same faces as fix_winding's wherever it is used,
    and None (fix_winding then) where its answer rests on its traversal order."""
    import trimesh

    from quatrack.viewsets.mesh import _rewound

    rng = np.random.default_rng(case)
    base = [trimesh.creation.icosphere(2), trimesh.creation.cylinder(1, 2, sections=20),
            trimesh.creation.annulus(1, 2, 3)][case % 3]
    F = np.asarray(base.faces).copy()
    flip = rng.random(len(F)) < (0.1, 0.5)[case // 3]
    F[flip] = F[flip][:, ::-1]
    if case % 3 == 2:  # (an open surface: which way it ends up rests on the first face)
        F = F[rng.permutation(len(F))[: len(F) * 4 // 5]]
    tm = trimesh.Trimesh(base.vertices, F, process=False)
    ours = _rewound(trimesh.Trimesh(base.vertices, F.copy(), process=False))
    trimesh.repair.fix_winding(tm)
    if ours is not None:
        assert np.array_equal(ours, np.asarray(tm.faces))
    else:
        assert case % 3 == 2  # (a surface cut in parts)


def test_two_separate_parts_and_a_moebius_strip_are_left_to_trimesh():
    import trimesh

    from quatrack.viewsets.mesh import _rewound

    two = trimesh.util.concatenate([trimesh.creation.box(), trimesh.creation.box().apply_translation([5, 0, 0])])
    F = np.asarray(two.faces).copy()
    F[:3] = F[:3, ::-1]
    assert _rewound(trimesh.Trimesh(two.vertices, F, process=False)) is None
    n = 12  # a Möbius strip: a quad strip closed with a half twist
    V = [[np.cos(2 * np.pi * k / n), np.sin(2 * np.pi * k / n), z] for k in range(n) for z in (-0.2, 0.2)]
    faces = []
    for k in range(n):
        a, b = 2 * k, 2 * k + 1
        c, d = (2 * (k + 1), 2 * (k + 1) + 1) if k < n - 1 else (1, 0)
        faces += [[a, c, d], [a, d, b]]
    faces = np.array(faces)
    faces[1] = faces[1, ::-1]
    assert _rewound(trimesh.Trimesh(np.array(V, float), faces, process=False)) is None


def _write_obj(path, texture=False):
    lines = ["mtllib box.mtl"] if texture else []
    lines += ["v %g %g %g" % tuple(v) for v in CORNERS]
    if texture:
        lines += ["vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1", "usemtl paper"]
    lines += ["f " + " ".join(f"{i + 1}/{k + 1}" if texture else str(i + 1) for k, i in enumerate(q)) for q in QUADS]
    path.write_text("\n".join(lines) + "\n")
    if texture:
        (path.parent / "box.mtl").write_text("newmtl paper\nmap_Kd paper.png\n")
        cv2.imwrite(str(path.parent / "paper.png"), np.full((8, 8, 3), 200, np.uint8))


def test_a_textured_obj_of_quads_loads_as_its_box_and_says_its_texture_is_not_used(tmp_path):
    _write_obj(tmp_path / "box.obj", texture=True)
    said = []
    mesh = load_mesh(tmp_path / "box.obj", warn=said.append)
    assert len(mesh.faces) == 12 and mesh.closed_outward
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [2, 3, 1])
    assert len(said) == 1 and "texture is not used" in said[0] and "registered photos" in said[0]
    _write_obj(tmp_path / "plain.obj")
    said.clear()
    load_mesh(tmp_path / "plain.obj", warn=said.append)
    assert said == []


def test_vertex_colours_of_a_binary_ply_are_said_to_be_unused(tmp_path):
    import trimesh

    tm = trimesh.Trimesh(CORNERS, _triangles(QUADS), vertex_colors=np.tile([255, 0, 0, 255], (8, 1)), process=False)
    tm.export(str(tmp_path / "box.ply"), encoding="binary")
    said = []
    assert len(load_mesh(tmp_path / "box.ply", warn=said.append).faces) == 12
    assert len(said) == 1 and "colours are not used" in said[0]


def test_a_glb_scene_of_two_parts_is_one_object_placed_by_its_transforms_and_says_so(tmp_path):
    import trimesh

    T = np.eye(4)
    T[:3, 3] = [13.0, 0, 0]
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.Trimesh(CORNERS, _triangles(QUADS), process=False), node_name="body")
    scene.add_geometry(trimesh.Trimesh(CORNERS - [10.0, 0, 0], _triangles(QUADS), process=False), node_name="lid",
                       transform=T)  # (its vertices at -10, its node moves them by +13: a second box beside the first;
    # one on the first would be the same triangles twice, dropped: tests/test_mesh_repeated_faces.py)
    scene.export(str(tmp_path / "parts.glb"))
    said = []
    mesh = load_mesh(tmp_path / "parts.glb", warn=said.append)
    assert len(mesh.faces) == 24
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [5, 3, 1], atol=1e-6)
    assert len(said) == 1 and "its 2 meshes" in said[0] and "one object" in said[0] and "scene transforms" in said[0]


def test_a_photo_named_by_two_views_is_warned_of(tmp_path):
    from quatrack.viewsets.spec import load_spec

    spec = json.loads((EXAMPLE / "object.json").read_text())
    view = spec["views"][0]
    view["image"] = str(EXAMPLE / view["image"])
    moved = json.loads(json.dumps(view))
    moved["pose"]["tvec"][2] += 5.0
    spec["mesh"] = str(EXAMPLE / "box.ply")
    spec["views"] = [view, json.loads(json.dumps(view)), moved]
    (tmp_path / "twice.json").write_text(json.dumps(spec))
    said = []
    load_spec(tmp_path / "twice.json", warn=said.append)
    assert len(said) == 2
    assert "view 1 repeats view 0 (the same photo at the same pose)" in said[0]
    assert "view 2 gives view 0's photo another pose (0° and 5 mesh units apart)" in said[1]
    spec["views"] = [view]
    (tmp_path / "once.json").write_text(json.dumps(spec))
    load_spec(tmp_path / "once.json", warn=said.append)
    assert len(said) == 2

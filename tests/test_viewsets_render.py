"""Z-buffer rendering, ray casting and keypoint lifting against independent geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import closed_prism

from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.mesh import make_mesh, planar_groups
from quatrack.viewsets.render import cast_rays, lift_keypoints, render, undistort_pixels
from quatrack.tracking.pose import Pose


def box_mesh(sx=18.9, sy=25.8, sz=7.5):
    V = np.array([[x, y, z] for x in (0, sx) for y in (0, sy) for z in (0, sz)], float)
    hull = __import__("scipy.spatial", fromlist=["ConvexHull"]).ConvexHull(V)
    return make_mesh(V, hull.simplices)


def pose_looking_at(centre, rvec, distance):
    R = cv2.Rodrigues(np.asarray(rvec, float))[0]
    t = np.array([0.0, 0.0, distance]) - R @ np.asarray(centre, float)
    return Pose.from_matrix(R, t)


CAM = PinholeCamera(700.0, 690.0, 322.0, 241.0, width=640, height=480)
CAM_DIST = PinholeCamera(700.0, 690.0, 322.0, 241.0, np.array([-0.2, 0.08, 0.001, -0.0015, 0.0]), width=640, height=480)


def test_box_groups_into_six_planes():
    g = planar_groups(box_mesh())
    assert len(np.unique(g)) == 6 and np.all(np.bincount(g) == 2)


def test_mask_matches_convex_hull_of_projected_corners():
    mesh = box_mesh()
    pose = pose_looking_at(mesh.centre, [0.5, -0.4, 0.3], 80.0)
    buf = render(mesh, CAM, pose)
    uv = CAM.project(pose.apply(mesh.vertices))
    ref = np.zeros((480, 640), np.uint8)
    cv2.fillConvexPoly(ref, np.round(cv2.convexHull(uv.astype(np.float32))[:, 0] * 16).astype(np.int32), 255,
                       lineType=cv2.LINE_8, shift=4)
    a, b = buf.mask > 0, ref > 0
    iou = (a & b).sum() / (a | b).sum()
    assert iou > 0.98


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_depth_buffer_agrees_with_ray_casting(camera):
    mesh = box_mesh()
    pose = pose_looking_at(mesh.centre, [2.0, -0.8, 0.3], 90.0)
    buf = render(mesh, camera, pose)
    rng = np.random.default_rng(0)
    vs, us = np.nonzero(buf.face >= 0)
    pick = rng.choice(len(us), 300, replace=False)
    uv = np.stack([us[pick], vs[pick]], 1).astype(float)
    X, f, _ = cast_rays(mesh, pose, undistort_pixels(camera, uv))
    assert np.all(f >= 0)
    z = pose.apply(X)[:, 2]
    np.testing.assert_allclose(z, buf.depth[vs[pick], us[pick]], rtol=1e-6)


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_lifted_points_reproject_onto_their_keypoints(camera):
    mesh = box_mesh()
    pose = pose_looking_at(mesh.centre, [2.0, -0.8, 0.3], 55.0)
    buf = render(mesh, camera, pose)
    rng = np.random.default_rng(3)
    uv = rng.uniform([0, 0], [639, 479], (3000, 2))
    X, keep = lift_keypoints(mesh, camera, pose, uv, buffers=buf)
    assert keep.sum() > 300
    err = np.linalg.norm(camera.project(pose.apply(X[keep])) - uv[keep], axis=1)
    assert err.max() < 1e-3
    # points outside the object (or within 3 px of its silhouette) were dropped
    vi, ui = np.rint(uv[keep, 1]).astype(int), np.rint(uv[keep, 0]).astype(int)
    inner = cv2.erode(buf.mask, np.ones((5, 5), np.uint8))
    assert np.all(inner[vi, ui] > 0)


def test_grazing_points_are_dropped():
    mesh = box_mesh()
    # look almost edge-on at the x = 0 face (normal −x): rotate 80° about the y axis
    pose = pose_looking_at(mesh.centre, [0.0, np.radians(80), 0.0], 120.0)
    uv = np.stack(np.meshgrid(np.arange(0, 640, 4.0), np.arange(0, 480, 4.0)), -1).reshape(-1, 2)
    X, f, cos = cast_rays(mesh, pose, undistort_pixels(CAM, uv))
    _, keep = lift_keypoints(mesh, CAM, pose, uv, min_cos=0.2)
    assert np.any((f >= 0) & (cos < 0.2))
    assert not np.any(keep & (cos < 0.2))
    assert np.any(keep)


def _reference_render(mesh, camera, pose):
    """The z-buffer the plain way: every triangle over every pixel, nearest first-come wins."""
    w, h = camera.width, camera.height
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    ray = undistort_pixels(camera, np.stack([u.ravel(), v.ravel()], 1))
    rx, ry = ray[:, 0], ray[:, 1]
    depth, face = np.full(h * w, np.inf), np.full(h * w, -1)
    for i, tri in enumerate(pose.apply(mesh.vertices)[mesh.faces]):
        n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        off = n @ tri[0]
        if np.any(tri[:, 2] <= 1e-6) or off == 0.0:
            continue
        p = tri[:, :2] / tri[:, 2:3]
        e = [(p[b, 0] - p[a, 0]) * (ry - p[a, 1]) - (p[b, 1] - p[a, 1]) * (rx - p[a, 0]) for a, b in ((0, 1), (1, 2), (2, 0))]
        inside = ((e[0] >= 0) & (e[1] >= 0) & (e[2] >= 0)) | ((e[0] <= 0) & (e[1] <= 0) & (e[2] <= 0))
        with np.errstate(divide="ignore", invalid="ignore"):
            z = off / (n[0] * rx + n[1] * ry + n[2])
        closer = inside & (z > 1e-6) & (z < depth)
        depth[closer], face[closer] = z[closer], i
    return depth.reshape(h, w), face.reshape(h, w)


def _occluding_scene():
    """A concave scene: an L of two boxes and a plate floating in front of it (self-occlusion,
    a hole between parts, open geometry seen from both sides)."""
    parts, V = [], []
    for lo, hi in (((0, 0, 0), (30, 6, 6)), ((0, 6, 0), (6, 30, 6)), ((8, 8, 14), (20, 20, 14.5))):
        b = box_mesh(*(np.subtract(hi, lo)))
        parts.append(b.faces + sum(len(v) for v in V))
        V.append(b.vertices + np.asarray(lo, float))
    return make_mesh(np.concatenate(V), np.concatenate(parts))


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
@pytest.mark.parametrize("scale", [0.25, 1.0])
def test_render_equals_the_plain_z_buffer_on_a_concave_occluding_scene(camera, scale):
    """The render gives exactly the faces of the plain per-pixel z-buffer, and its depths to
    rounding, wherever parts hide each other."""
    from quatrack.recognition.visibility import scaled_camera

    mesh = _occluding_scene()
    cam = scaled_camera(camera, scale)
    for rvec, dist in (([0.3, -0.5, 0.2], 70.0), ([2.4, 0.6, -0.3], 55.0), ([0.1, 0.1, 0.0], 40.0)):
        pose = pose_looking_at(mesh.centre, rvec, dist)
        buf = render(mesh, cam, pose)
        depth, face = _reference_render(mesh, cam, pose)
        assert (face >= 0).sum() > 0.05 * face.size
        assert len(np.unique(face[face >= 0])) > 6  # several parts in view
        np.testing.assert_array_equal(buf.face, face)
        np.testing.assert_array_equal(np.isfinite(buf.depth), np.isfinite(depth))
        np.testing.assert_allclose(buf.depth[face >= 0], depth[face >= 0], rtol=1e-12)


def test_the_buffers_drawn_faces_are_the_ids_their_pixels_hold():
    """``RenderBuffers.drawn`` (read once per buffers by every texture reference rendered over
    them) holds exactly the triangle ids some pixel shows, ascending, on a scene where parts
    hide each other: none hidden counted, none drawn left out."""
    mesh = _occluding_scene()
    for rvec, dist in (([0.3, -0.5, 0.2], 70.0), ([2.4, 0.6, -0.3], 55.0)):
        buf = render(mesh, CAM, pose_looking_at(mesh.centre, rvec, dist))
        shown = np.unique(buf.face[buf.face >= 0])
        assert 6 < len(shown) < len(mesh.faces)  # several parts in view, some faces hidden
        np.testing.assert_array_equal(buf.drawn, shown)
        assert buf.drawn is buf.drawn  # (computed once)


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
@pytest.mark.parametrize("scale", [0.25, 0.5])
def test_the_compiled_render_equals_the_triangle_loop(camera, scale):
    """The compiled z-buffer (``_zbuffer``) gives the plain numpy loop over every triangle's box
    (``render_reference``) bit for bit, and the per-pixel reference's faces: a mesh of many
    small triangles, also partly out of the image, and with a concave scene added (occlusion
    between parts)."""
    from quatrack.recognition.visibility import scaled_camera
    from quatrack.viewsets import render as R

    cyl = closed_prism(48, 20.0, 35.0)  # a cylinder of many small triangles (tested together)
    scene = _occluding_scene()
    both = make_mesh(np.concatenate([cyl.vertices, scene.vertices + [25.0, 0.0, 0.0]]),
                     np.concatenate([cyl.faces, scene.faces + len(cyl.vertices)]))
    cam = scaled_camera(camera, scale)
    for mesh in (cyl, both):
        for rvec, dist, shift in (([0.3, -0.5, 0.2], 120.0, 0.0), ([2.4, 0.6, -0.3], 90.0, 0.0),
                                  ([1.2, 0.1, 0.4], 100.0, 45.0), ([0.1, 0.1, 0.0], 160.0, -60.0)):
            pose = pose_looking_at(mesh.centre, rvec, dist)
            pose = Pose(pose.q_wxyz, pose.t + [shift, 0.3 * shift, 0.0])
            buf, ref = render(mesh, cam, pose), R.render_reference(mesh, cam, pose)
            assert (buf.face >= 0).any()
            np.testing.assert_array_equal(buf.face, ref.face)
            np.testing.assert_array_equal(buf.depth, ref.depth)
            _, face = _reference_render(mesh, cam, pose)
            np.testing.assert_array_equal(buf.face, face)


def test_render_ties_go_to_the_lower_triangle():
    """Coplanar triangles are exactly as near (here bit for bit: integer corners, the identity
    rotation): the lower index wins, in the compiled test as in the plain loop, between large
    and small triangles alike."""
    from quatrack.viewsets import render as R

    big = [[-40, -20, 0], [-24, -20, 0], [40, -4, 0]]  # n = (0, 0, 256): a 80×16 box
    small = [[-40, -20, 0], [-24, -20, 0], [-24, -4, 0]]  # the same plane and n: a 16×16 box
    V, F = [], []
    for tri in ([big, small] + [[[x, 25, -3], [x + 3, 25, -3], [x, 28, -3]] for x in range(-60, 60, 3)] + [big, small]):
        F.append([len(V), len(V) + 1, len(V) + 2])
        V += tri
    mesh = make_mesh(np.array(V, float), np.array(F))
    cam = PinholeCamera(200.0, 200.0, 80.0, 60.0, width=160, height=120)
    pose = Pose(np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 0.0, 200.0]))
    buf, ref = render(mesh, cam, pose), R.render_reference(mesh, cam, pose)
    np.testing.assert_array_equal(buf.face, ref.face)
    np.testing.assert_array_equal(buf.depth, ref.depth)
    seen = set(np.unique(buf.face).tolist())
    assert {0, 1} <= seen and not seen & {len(F) - 2, len(F) - 1}  # the first copies win every tie


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_a_window_of_the_render_equals_the_whole_render_there(camera):
    """render_window over a pixel box gives the whole frame's buffers there bit for bit (boxes
    that cut triangles, hold the whole object, lie at the border or miss it), and the footprint
    holds every pixel the render draws."""
    from quatrack.viewsets.render import footprint, render_window

    cyl = closed_prism(48, 20.0, 35.0)
    scene = _occluding_scene()
    rng = np.random.default_rng(5)
    cut = shown = 0
    for mesh in (cyl, scene):
        for rvec, dist, shift in (([0.3, -0.5, 0.2], 120.0, 0.0), ([2.4, 0.6, -0.3], 90.0, 30.0),
                                  ([1.2, 0.1, 0.4], 100.0, 75.0)):
            pose = pose_looking_at(mesh.centre, rvec, dist)
            pose = Pose(pose.q_wxyz, pose.t + [shift, 0.3 * shift, 0.0])
            full = render(mesh, camera, pose)
            box = footprint(mesh, camera, pose)
            ys, xs = np.nonzero(full.face >= 0)
            if box is None:
                assert not len(xs)
                continue
            shown += 1
            assert box[0] <= xs.min() and box[1] <= ys.min() and xs.max() < box[2] and ys.max() < box[3]
            windows = [box, (0, 0, 640, 480), (600, 400, 640, 480), (0, 0, 1, 1), (5, 7, 5, 9)]
            for _ in range(6):
                (x0, x1), (y0, y1) = np.sort(rng.integers(0, 641, 2)), np.sort(rng.integers(0, 481, 2))
                windows.append((int(x0), int(y0), int(x1), int(y1)))
            for x0, y0, x1, y1 in windows:
                part = render_window(mesh, camera, pose, (x0, y0, x1, y1))
                np.testing.assert_array_equal(part.face, full.face[y0:y1, x0:x1])
                np.testing.assert_array_equal(part.depth, full.depth[y0:y1, x0:x1])
                cut += int((part.face >= 0).any() and (full.face >= 0).sum() > (part.face >= 0).sum())
    assert cut >= 6 and shown >= 4


def test_a_closed_outward_mesh_is_recognised_and_a_flipped_or_open_one_is_not():
    """:attr:`Mesh.closed_outward` decides whether the z-buffer may skip faces turned away."""
    box = box_mesh()
    # (the hull's simplices are wound either way: the box made outward, as load_mesh does)
    from quatrack.viewsets.mesh import outward_faces

    box = make_mesh(box.vertices, outward_faces(box.vertices, box.faces))
    assert box.closed_outward
    assert not make_mesh(box.vertices, box.faces[:, ::-1]).closed_outward  # inside out
    assert not make_mesh(box.vertices, box.faces[1:]).closed_outward  # a hole
    # a seam: the vertices of one face duplicated (as exporters split them for texture
    # coordinates); merged by position it is still closed
    V = np.vstack([box.vertices, box.vertices[box.faces[0]]])
    F = box.faces.copy()
    F[0] = len(box.vertices) + np.arange(3)
    assert make_mesh(V, F).closed_outward


def test_an_stl_s_mixed_windings_are_made_outward(tmp_path):
    """An STL stores every triangle's corners apart (no shared vertex): load_mesh must still
    wind its faces outward, joining them through vertices at the same position (before, the
    winding was left as exported, and locate refused the right pose as 'a mirrored pose')."""
    import trimesh

    from quatrack.viewsets.mesh import load_mesh

    box = box_mesh()
    F = box.faces.copy()
    F[::3] = F[::3, ::-1]  # mixed windings, as the bundled box.ply has
    trimesh.Trimesh(box.vertices, F, process=False).export(tmp_path / "box.stl")
    mesh = load_mesh(tmp_path / "box.stl")
    assert len(mesh.vertices) == 3 * len(F)  # (the soup as stored)
    out = np.einsum("ij,ij->i", mesh.face_normals, mesh.face_centroids - mesh.centre)
    assert np.all(out > 0)
    assert mesh.closed_outward


def test_a_vertex_no_face_uses_is_dropped(tmp_path):
    """A leftover vertex far off (exporters keep them) moved the bounding box's centre, about
    which the synthetic views turn the object, out of the object: every synthetic view of the
    cookie box kept 0 keypoints and locate found nothing."""
    import trimesh

    from quatrack.viewsets.mesh import load_mesh

    box = box_mesh()
    V = np.vstack([[1e6, 1e6, 1e6], box.vertices])
    trimesh.Trimesh(V, box.faces + 1, process=False).export(tmp_path / "box.ply")
    mesh = load_mesh(tmp_path / "box.ply")
    assert len(mesh.vertices) == 8
    np.testing.assert_allclose(mesh.centre, box.centre)
    np.testing.assert_allclose(mesh.triangles, make_mesh(box.vertices, mesh.faces).triangles)


@pytest.mark.parametrize("name", ["cube-m", "cylinder-mm", "hex-prism-m"])
def test_skipping_the_faces_a_closed_mesh_turns_away_changes_no_pixel(name):
    """Faces turned away are hidden behind faces turned towards the camera: the culled render's
    mask and depths equal the full z-buffer's, and its faces too but at exact ties on a shared
    silhouette edge (none occur here)."""
    from quatrack.testing import zoo as Z
    from quatrack.viewsets.render import _rasterise

    mesh = Z.textured(name).mesh
    assert mesh.closed_outward
    cam = Z.zoo_camera()
    rng = np.random.default_rng(3)
    for _ in range(12):
        a, e = rng.uniform(0, 2 * np.pi), rng.uniform(-1.3, 1.3)
        eye = mesh.centre + 2.5 * mesh.extent * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        pose = Z.look_at(eye, mesh.centre)
        culled, full = _rasterise(mesh, cam, pose, cull=True), _rasterise(mesh, cam, pose, cull=False)
        seen = full.face >= 0
        assert seen.sum() > 1000
        np.testing.assert_array_equal(culled.face >= 0, seen)
        np.testing.assert_array_equal(culled.depth[seen], full.depth[seen])
        assert (culled.face != full.face).sum() <= 1e-4 * seen.sum()


def test_no_face_is_skipped_with_the_camera_inside_the_mesh():
    """From inside a closed mesh every face seen is turned away from the camera: none may be
    skipped (the camera inside the bounding box turns the culling off)."""
    box = box_mesh()
    from quatrack.viewsets.mesh import outward_faces

    box = make_mesh(box.vertices, outward_faces(box.vertices, box.faces))
    inside = Pose.from_matrix(np.eye(3), -box.centre)  # the camera at the box's centre, looking along +z
    buf = render(box, CAM, inside)
    assert (buf.face >= 0).all()


def test_the_z_buffer_compiles_without_a_writable_cache(monkeypatch):
    """A read-only install without a home directory has nowhere to keep numba's cache: the
    z-buffer is then compiled in the process, and renders the same."""
    import numba.core.caching as caching

    from quatrack.viewsets import render as R

    monkeypatch.setattr(caching.CacheImpl, "_locator_classes", [])
    R._compiled_zbuffer.cache_clear()
    try:
        box = box_mesh()
        pose = pose_looking_at(box.centre, [0.3, -0.5, 0.2], 40.0)
        buf, ref = render(box, CAM, pose), R.render_reference(box, CAM, pose)
        assert (buf.face >= 0).any()
        np.testing.assert_array_equal(buf.face, ref.face)
        np.testing.assert_array_equal(buf.depth, ref.depth)
    finally:
        R._compiled_zbuffer.cache_clear()  # (the next render compiles again, with the cache)


def _reference_textured_lookup(mesh, groups, src_camera, src_pose, src_face, src_mask, face, rays, pose, min_cos,
                                depth=None, src_depth=None):
    """The homography lookup of ``render_textured_view`` written plainly in numpy, plane group
    by plane group (the code before it was compiled): the photo's coordinates of each pixel.
    With the depths, a pixel whose photo pixel shows another plane's face is textured when that
    face turns by less than 30° from its own and lies within 1 % of the extent of its depth."""
    from quatrack.viewsets.novel import plane_homography

    h, w = face.shape
    src_group = np.where(src_face >= 0, groups[np.maximum(src_face, 0)], -1)
    offsets = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles[:, 0])
    centre = -src_pose.R.T @ src_pose.t
    map_x, map_y = np.full((h, w), -1.0, np.float32), np.full((h, w), -1.0, np.float32)
    textured = np.zeros((h, w), bool)
    pix_group = np.where(face >= 0, groups[np.maximum(face, 0)], -1)
    for g in np.unique(pix_group[pix_group >= 0]):
        f0 = int(np.nonzero(groups == g)[0][0])
        n, d = mesh.face_normals[f0], offsets[f0]
        ray = mesh.triangles[groups == g].reshape(-1, 3).mean(axis=0) - centre
        if abs(n @ ray) / np.linalg.norm(ray) < min_cos:
            continue
        vs, us = np.nonzero(pix_group == g)
        r = rays[vs, us]
        Xs = np.column_stack([r, np.ones(len(r))]) @ plane_homography(n, d, pose, src_pose).T
        front = Xs[:, 2] > 0
        uv = np.full((len(r), 2), -1.0)
        uv[front] = src_camera.project(Xs[front])
        ui, vi = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        inside = front & (ui >= 0) & (vi >= 0) & (ui < src_face.shape[1]) & (vi < src_face.shape[0])
        seen = np.zeros(len(r), bool)
        seen[inside] = src_group[vi[inside], ui[inside]] == g
        if depth is not None:
            sf = src_face[vi[inside], ui[inside]]
            f = face[vs[inside], us[inside]]
            turn = np.einsum("ij,ij->i", mesh.face_normals[f], mesh.face_normals[np.maximum(sf, 0)])
            near = np.abs(src_depth[vi[inside], ui[inside]] - depth[vs[inside], us[inside]] * Xs[inside, 2])
            seen[inside] |= (sf >= 0) & (turn >= np.cos(np.radians(30.0))) & (near <= 0.01 * mesh.extent)
        if src_mask is not None:
            seen[inside] &= src_mask[vi[inside], ui[inside]] > 0
        map_x[vs[seen], us[seen]], map_y[vs[seen], us[seen]] = uv[seen, 0], uv[seen, 1]
        textured[vs[seen], us[seen]] = True
    return map_x, map_y, textured


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
@pytest.mark.parametrize("masked", [False, True], ids=["whole", "masked"])
def test_the_compiled_texture_lookup_equals_the_numpy_one(camera, masked):
    """``render_textured_view``'s per-pixel lookup runs compiled (numba): the photo's pixel of
    every rendered pixel, hence the rendered image, the same bits as the plain numpy lookup —
    over a window of the image, with lens distortion, with the user's mask of the photo, and
    with faces the photo sees too obliquely to texture."""
    from quatrack.viewsets.novel import render_textured_view
    from quatrack.viewsets.render import pixel_rays

    mesh = box_mesh()
    groups = planar_groups(mesh)
    src_pose = pose_looking_at(mesh.centre, [0.5, -0.6, 0.2], 60.0)
    src_buf = render(mesh, camera, src_pose)
    rng = np.random.default_rng(1)
    photo = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    mask = None
    if masked:
        mask = np.zeros((480, 640), np.uint8)
        mask[:, :330] = 255  # the user masked out the photo's right part
    checked, untextured = 0, 0
    # (the last pose shows only a face the photo sees too obliquely: nothing textured)
    for rvec, window in [([0.9, -0.2, 0.1], None), ([0.7, -0.4, 0.1], (150, 100, 470, 400)), ([1.5, 0.2, 0.0], None)]:
        pose = pose_looking_at(mesh.centre, rvec, 55.0)
        cam = camera if window is None else camera.cropped(*window)
        img, textured, buf = render_textured_view(mesh, groups, photo, camera, src_pose, src_buf, cam, pose, 0.3, mask)
        mx, my, tex = _reference_textured_lookup(mesh, groups, camera, src_pose, src_buf.face, mask, buf.face,
                                                 pixel_rays(cam), pose, 0.3)
        np.testing.assert_array_equal(textured > 0, tex)
        ref = cv2.remap(photo, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(127,) * 3)
        ref[~tex] = 127
        np.testing.assert_array_equal(img, ref)
        checked += int(tex.sum())
        untextured += int(((buf.face >= 0) & ~tex).sum())
    assert checked > 50000 and untextured > 30000  # textured faces, and faces the photo cannot texture


@pytest.mark.parametrize("cx", [322.0, 321.123456789])
def test_a_crop_s_rays_are_its_own_pixels_rays(cx):
    """pixel_rays of a crop (PinholeCamera.cropped, a crop of a crop too): a distorted camera's
    are the whole image's sliced, equal to the crop's own pixels undistorted to 1e-12 (and no
    new undistortion: the whole image's array is shared); an undistorted camera's are computed
    for the crop, ``(u − cx)/fx`` bit for bit. A crop reaching outside the image it claims is
    undistorted for itself."""
    from quatrack.viewsets.render import pixel_rays

    def own(cam):
        u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
        return undistort_pixels(cam, np.stack([u.ravel(), v.ravel()], axis=1)).reshape(cam.height, cam.width, 2)

    whole = PinholeCamera(700.0, 690.0, cx, 241.3, CAM_DIST.dist_coeffs, width=640, height=480)
    rng = np.random.default_rng(11)
    for _ in range(5):
        (x0, x1), (y0, y1) = np.sort(rng.choice(641, 2, replace=False)), np.sort(rng.choice(481, 2, replace=False))
        crop = whole.cropped(x0, y0, x1, y1)
        inner = crop.cropped(1, 2, crop.width - 1, crop.height)
        for cam in (crop, inner):
            rays = pixel_rays(cam)
            assert rays.shape == (cam.height, cam.width, 2) and not rays.flags.writeable
            np.testing.assert_allclose(rays, own(cam), rtol=0, atol=1e-12)
            assert np.shares_memory(rays, pixel_rays(whole))
        plain = PinholeCamera(700.0, 690.0, cx, 241.3, width=640, height=480).cropped(x0, y0, x1, y1)
        np.testing.assert_array_equal(pixel_rays(plain), own(plain))
    beyond = whole.cropped(600, 400, 700, 500)  # (reaches past the 640 × 480 image)
    np.testing.assert_allclose(pixel_rays(beyond), own(beyond), rtol=0, atol=1e-12)
    assert not np.shares_memory(pixel_rays(beyond), pixel_rays(whole))


def dense_cylinder(radius=4.0, height=12.0, sections=256):
    """A finely faceted cylinder (a curved surface: every side facet is a plane of its own)."""
    import trimesh

    tm = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    return make_mesh(np.asarray(tm.vertices, float), np.asarray(tm.faces, np.int64))


def noisy_box(subdivisions=3, noise=0.0005, seed=0):
    """The box finely subdivided, its vertices jittered by ``noise`` × its extent: a scanned
    object's mesh in miniature (every facet a plane of its own)."""
    from quatrack.testing.scans import scanned

    return scanned(box_mesh(), subdivisions, noise, seed)


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_the_compiled_lookup_follows_a_curved_surface_as_the_numpy_one(camera):
    """On a curved surface of many facets each facet is a plane of its own, and the photo's
    pixel of a point mostly shows a neighbouring facet: the compiled lookup textures it when
    that facet turns by less than 30° and lies at the point's depth (render_textured_view),
    the same pixels as the plain numpy rule: over 90 % of the surface in view, which the plane
    test alone leaves a quarter of untextured."""
    from quatrack.viewsets.novel import render_textured_view
    from quatrack.viewsets.render import pixel_rays

    mesh = dense_cylinder()
    groups = planar_groups(mesh)
    src_pose = pose_looking_at(mesh.centre, [1.4, 0.0, 0.0], 40.0)
    src_buf = render(mesh, camera, src_pose)
    photo = np.random.default_rng(2).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    pose = pose_looking_at(mesh.centre, [1.4, 0.35, 0.0], 38.0)
    img, textured, buf = render_textured_view(mesh, groups, photo, camera, src_pose, src_buf, camera, pose, 0.3)
    mx, my, tex = _reference_textured_lookup(mesh, groups, camera, src_pose, src_buf.face, None, buf.face,
                                             pixel_rays(camera), pose, 0.3, buf.depth, src_buf.depth)
    np.testing.assert_array_equal(textured > 0, tex)
    ref = cv2.remap(photo, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(127,) * 3)
    ref[~tex] = 127
    np.testing.assert_array_equal(img, ref)
    *_, planes_only = _reference_textured_lookup(mesh, groups, camera, src_pose, src_buf.face, None, buf.face,
                                                 pixel_rays(camera), pose, 0.3)
    drawn = int((buf.face >= 0).sum())
    assert tex.sum() > 0.9 * drawn > planes_only.sum() + 0.1 * drawn


def test_a_scanned_box_is_textured_as_the_plain_box():
    """A box finely subdivided and jittered (a scan's mesh) textures a turned view from the
    photo nearly as the plain box does: most of its pixels, with the same colours."""
    from quatrack.viewsets.novel import render_textured_view

    plain, scan = box_mesh(), noisy_box()
    src_pose = pose_looking_at(plain.centre, [2.0, -0.8, 0.3], 70.0)
    pose = pose_looking_at(plain.centre, [2.2, -0.5, 0.3], 70.0)
    photo = cv2.GaussianBlur(np.random.default_rng(4).integers(0, 256, (480, 640, 3), dtype=np.uint8), (0, 0), 3.0)
    out = {}
    for name, mesh in (("plain", plain), ("scan", scan)):
        img, tex, buf = render_textured_view(mesh, planar_groups(mesh), photo, CAM, src_pose, render(mesh, CAM, src_pose),
                                             CAM, pose, 0.3)
        out[name] = (img, tex > 0, buf.face >= 0)
    (a, ta, da), (b, tb, _) = out["plain"], out["scan"]
    assert tb.sum() > 0.9 * ta.sum() and ta.sum() > 0.9 * da.sum()
    both = cv2.erode((ta & tb).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert np.median(np.abs(a[both].astype(int) - b[both].astype(int))) <= 2


@pytest.mark.parametrize("behind", [False, True], ids=["in front", "reaching behind the camera"])
def test_ray_casting_through_a_grid_equals_every_ray_against_every_triangle(behind, monkeypatch):
    """A mesh of many triangles is ray-cast through a grid over the rays (cast_rays'
    _binned_hits): the same faces and the same points as testing every ray against every
    triangle — also with part of the mesh behind the camera, which no grid can hold."""
    import quatrack.viewsets.render as R

    mesh = noisy_box(subdivisions=3)
    assert len(mesh.faces) >= R.BINNED_MIN_TRIANGLES
    distance = 8.0 if behind else 60.0
    pose = pose_looking_at(mesh.centre, [2.0, -0.8, 0.3], distance)
    if behind:
        assert np.any(pose.apply(mesh.vertices)[:, 2] <= 0) and np.any(pose.apply(mesh.vertices)[:, 2] > 0)
    rng = np.random.default_rng(5)
    xy = rng.uniform(-0.35, 0.35, (1500, 2))
    X, f, cos = cast_rays(mesh, pose, xy)
    monkeypatch.setattr(R, "BINNED_MIN_TRIANGLES", 10**9)
    X0, f0, cos0 = cast_rays(mesh, pose, xy)
    assert (f0 >= 0).sum() > 200 and (behind or (f0 < 0).sum() > 100)  # rays that hit (and miss)
    np.testing.assert_array_equal(f, f0)
    np.testing.assert_allclose(X, X0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cos, cos0, rtol=0, atol=1e-12)


def test_planar_groups_equal_the_face_by_face_rule():
    """planar_groups finds each face's plane-mates through a k-d tree; the groups are those of
    testing every face against every other (the rule as first written): on a box, a faceted
    cylinder and a jittered scan-like box, where nearly every facet is a plane of its own."""

    def every_pair(mesh, angle_tol_deg=1.0, offset_tol=1e-3):
        n = mesh.face_normals
        d = np.einsum("ij,ij->i", n, mesh.triangles[:, 0])
        lead = n[np.arange(len(n)), np.argmax(np.abs(n) > 1e-6, axis=1)]
        sign = np.where(lead < 0, -1.0, 1.0)
        n, d = n * sign[:, None], d * sign
        cos_tol, tol = np.cos(np.radians(angle_tol_deg)), offset_tol * mesh.extent
        groups, next_id = np.full(len(n), -1), 0
        for i in range(len(n)):
            if groups[i] < 0:
                groups[(groups < 0) & (n @ n[i] >= cos_tol) & (np.abs(d - d[i]) <= tol)] = next_id
                next_id += 1
        return groups

    for mesh in (box_mesh(), dense_cylinder(sections=64), noisy_box(subdivisions=2, noise=0.0003)):
        np.testing.assert_array_equal(planar_groups(mesh), every_pair(mesh))


def test_make_mesh_refuses_arrays_of_other_shapes_naming_them():
    # 2-D vertices (6 × 2 = 12 numbers) were reshaped into 4 other 3-D vertices without a word, a
    # Trimesh for the vertices was float()'s TypeError
    import trimesh

    from quatrack.viewsets.errors import SpecError

    tm = trimesh.creation.box(extents=(0.1, 0.2, 0.05))
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [2, 0], [2, 1.0]])
    with pytest.raises(SpecError, match=r"vertices must be an \(n, 3\) array of numbers, got shape \(6, 2\)"):
        make_mesh(square, np.array([[0, 1, 2], [0, 2, 3]]))
    with pytest.raises(SpecError, match=r"vertices must be .*a trimesh's .vertices"):
        make_mesh(tm, tm.faces)
    with pytest.raises(SpecError, match=r"faces must be an \(m, 3\) array"):
        make_mesh(tm.vertices, np.array([[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4]]))
    assert len(make_mesh(tm.vertices, tm.faces).faces) == 12

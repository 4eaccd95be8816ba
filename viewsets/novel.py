"""Novel (synthetic) views of a registered object: new poses, textured by plane-induced homographies.

Each planar face group seen well in the registered photo is warped into the novel view by the
homography that its plane induces between the two cameras, so recognition can learn viewpoints
the photo does not show head-on. Faces the photo shows badly (or not at all) stay untextured and
get no keypoints.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.jit import lazily_compiled

from .features import RUN_TIME_STRETCH
from .mesh import Mesh
from .render import RenderBuffers, footprint, pixel_rays, render
from .viewset import Viewset, ViewsetParams, build_viewset
from quatrack.tracking.pose import Pose

BACKGROUND = 127  # neutral grey: keypoints are taken only well inside the textured mask anyway


@dataclass(frozen=True)
class NovelViewParams:
    """Viewpoints around each registered view: rotations (degrees) about the object's own axes
    through its centre, and scale changes (apparent size ×s, i.e. distance ÷s)."""

    angles_deg: tuple[float, ...] = (20.0, 40.0)
    axes: str = "xyz"
    scales: tuple[float, ...] = (0.6, 1.4)
    min_source_cos: float = 0.3


def rotate_about_centre(pose: Pose, centre: np.ndarray, rvec_obj: np.ndarray) -> Pose:
    """The pose of the object turned by ``rvec_obj`` (object frame) about its point ``centre``."""
    Rd = cv2.Rodrigues(np.asarray(rvec_obj, float).reshape(3, 1))[0]
    R = pose.R @ Rd
    t = pose.R @ centre - R @ centre + pose.t
    return Pose.from_matrix(R, t)


def scale_pose(pose: Pose, centre: np.ndarray, scale: float) -> Pose:
    """Move the object along its line of sight so it appears ``scale`` times larger."""
    p = pose.R @ centre + pose.t
    return Pose(pose.q_wxyz, pose.t + p / scale - p)


def novel_poses(mesh: Mesh, pose: Pose, params: NovelViewParams) -> list[tuple[str, Pose]]:
    """Labelled novel poses around ``pose`` (the registered pose itself is not included)."""
    c = mesh.centre
    out = []
    for axis in params.axes:
        e = np.zeros(3)
        e["xyz".index(axis)] = 1.0
        for a in params.angles_deg:
            for sgn in (1, -1):
                out.append((f"rot{axis}{sgn * a:+g}", rotate_about_centre(pose, c, e * np.radians(sgn * a))))
    for s in params.scales:
        out.append((f"scale{s:g}", scale_pose(pose, c, s)))
    return out


def plane_homography(
    plane_n: np.ndarray, plane_d: float, pose_from: Pose, pose_to: Pose
) -> np.ndarray:
    """3×3 map of normalised rays (x, y, 1) of camera *from* to camera *to* for points on the object
    plane ``n·X = d`` (object frame): ``H = R_rel + t_rel n_cᵀ / d_c`` with the plane in *from*."""
    R_rel = pose_to.R @ pose_from.R.T
    t_rel = pose_to.t - R_rel @ pose_from.t
    n_c = pose_from.R @ plane_n
    d_c = plane_d + n_c @ pose_from.t
    return R_rel + np.outer(t_rel, n_c) / d_c


# a photo shows the same surface point when its z-buffer lies within this share of the mesh's
# extent of the point's own depth (render_textured_view, for faces that are planes of their own)
SAME_POINT_DEPTH = 0.01
SAME_SURFACE_COS = float(np.cos(np.radians(30.0)))  # ... and turns by less than this from the face
_FEW_GROUPS = 64  # plane groups in view up to which render_textured_view sets them up one by one


def plane_homographies(n: np.ndarray, d: np.ndarray, pose_from: Pose, pose_to: Pose) -> np.ndarray:
    """:func:`plane_homography` of many planes at once: (k, 3, 3) for normals ``n`` (k, 3) and
    offsets ``d`` (k,).

    >>> n, d = np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]]), np.array([0.5, -1.0])
    >>> a, b = Pose.from_rvec([0.1, 0.2, 0.3], [0.0, 0.0, 5.0]), Pose.from_rvec([-0.2, 0.1, 0.0], [0.1, 0.0, 6.0])
    >>> bool(np.allclose(plane_homographies(n, d, a, b), [plane_homography(n[i], d[i], a, b) for i in range(2)]))
    True
    """
    R_rel = pose_to.R @ pose_from.R.T
    t_rel = pose_to.t - R_rel @ pose_from.t
    n_c = np.asarray(n, float) @ pose_from.R.T
    d_c = np.asarray(d, float) + n_c @ pose_from.t
    return R_rel[None] + np.einsum("i,kj->kij", t_rel, n_c) / d_c[:, None, None]


def _first_faces(groups: np.ndarray) -> np.ndarray:
    """Per plane group, its first (lowest) face, whose plane stands for the group's."""
    first = np.full(int(groups.max()) + 1 if len(groups) else 0, -1, np.int64)
    first[groups[::-1]] = np.arange(len(groups))[::-1]  # (the last write wins: the lowest face)
    return first


def _group_centroids(mesh: Mesh, groups: np.ndarray) -> np.ndarray:
    """Per plane group, the centroid of its faces' corners (each corner counted once per face)."""
    n_groups = int(groups.max()) + 1 if len(groups) else 0
    corners = mesh.vertices[mesh.faces].sum(axis=1)  # (m, 3): each face's three corners
    centroid = np.column_stack([np.bincount(groups, corners[:, k], n_groups) for k in range(3)])
    return centroid / np.maximum(3 * np.bincount(groups, minlength=n_groups), 1)[:, None]


def render_textured_view(
    mesh: Mesh,
    groups: np.ndarray,
    src_image: np.ndarray,
    src_camera: PinholeCamera,
    src_pose: Pose,
    src_buffers: RenderBuffers,
    camera: PinholeCamera,
    pose: Pose,
    min_source_cos: float = 0.3,
    src_mask: np.ndarray | None = None,
    buffers: RenderBuffers | None = None,
) -> tuple[np.ndarray, np.ndarray, RenderBuffers]:
    """Render the object at ``pose`` in ``camera``, textured from the registered photo.

    Returns the image (background grey), the mask of textured pixels, and the z-buffer of the
    novel view. A pixel is textured only if its face is seen at |cos| ≥ ``min_source_cos`` in
    the photo and the photo shows that same plane there (not occluded by the object itself, nor
    masked out by ``src_mask``, the user's mask of the photo: non-zero = the object is seen).
    ``buffers``: the z-buffer of ``pose`` in ``camera`` if already rendered (several photos
    rendered at one pose share it).

    The per-pixel lookup runs compiled (:func:`_lookup`, numba): ``locate`` renders the photos
    at every pose it verifies (:mod:`quatrack.recognition.appearance`), and the numpy version,
    a dozen whole-array operations per plane, cost 15 ms of that check's 17 (p50, the cookie
    box's rendered scenes); compiled the check takes 6 ms, with the same bits
    (tests/test_viewsets_render.py).
    """
    buf = render(mesh, camera, pose) if buffers is None else buffers
    h, w = buf.face.shape
    normals = mesh.face_normals
    offsets = np.einsum("ij,ij->i", normals, mesh.vertices[mesh.faces[:, 0]])
    src_centre = -src_pose.R.T @ src_pose.t
    # per plane group: whether the photo sees it well (the cosine between its normal and the ray
    # to its centroid) and the homography from this view's rays to the photo's
    n_groups = int(groups.max()) + 1 if len(groups) else 0
    use = np.zeros(n_groups, bool)
    Hs = np.zeros((n_groups, 3, 3))
    first = _first_faces(groups)
    gs = np.unique(groups[buf.drawn])  # (the groups in view)
    if len(gs) <= _FEW_GROUPS:  # (a planar model: plane by plane, as ever, the same bits)
        for g in gs:
            members = groups == g
            n, d = normals[first[g]], offsets[first[g]]  # (the group's first face: its plane)
            ray = mesh.vertices[mesh.faces[members]].reshape(-1, 3).mean(axis=0) - src_centre
            if abs(n @ ray) / np.linalg.norm(ray) >= min_source_cos:
                use[g], Hs[g] = True, plane_homography(n, d, pose, src_pose)
    else:  # (a curved or scanned surface of many facets: all at once)
        n, d = normals[first[gs]], offsets[first[gs]]
        ray = _group_centroids(mesh, groups)[gs] - src_centre
        seen = np.abs(np.einsum("ij,ij->i", n, ray)) / np.linalg.norm(ray, axis=1) >= min_source_cos
        gs, n, d = gs[seen], n[seen], d[seen]
        use[gs], Hs[gs] = True, plane_homographies(n, d, pose, src_pose)
    # a pixel left untextured maps far outside the photo: remap gives it the background colour
    map_x = np.full((h, w), -1000.0, np.float32)
    map_y = np.full((h, w), -1000.0, np.float32)
    textured = np.zeros((h, w), bool)
    dist = np.zeros(8)
    dist[: src_camera.dist_coeffs.size] = src_camera.dist_coeffs
    mask = np.zeros((1, 1), np.uint8) if src_mask is None else np.ascontiguousarray(src_mask)
    _compiled_lookup()(buf.face, groups, use, Hs, pixel_rays(camera), src_camera.fx, src_camera.fy, src_camera.cx,
                       src_camera.cy, dist, bool(src_camera.has_distortion), src_buffers.face, mask, src_mask is not None,
                       map_x, map_y, textured, normals, buf.depth, src_buffers.depth, SAME_POINT_DEPTH * mesh.extent,
                       SAME_SURFACE_COS)
    img = cv2.remap(src_image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=(BACKGROUND,) * 3)
    return img, textured.astype(np.uint8) * 255, buf


def turned_about_view(pose: Pose, centre: np.ndarray, angles_deg: tuple[float, ...]) -> list[tuple[str, Pose]]:
    """Labelled poses of the object turned by ``±a`` (each ``a`` in ``angles_deg``) about the
    *camera's* x and y axes through the object's centre ``c``: what a camera moving round the
    object (up, down, left, right) sees next. About camera axis ``e`` the rotation is
    ``R' = exp(a[e]×)·R``, i.e. the object-frame rotation vector ``a·Rᵀe`` of
    :func:`rotate_about_centre`; the centre's camera position ``R c + t`` stays.

    >>> p = Pose.from_rvec([0.0, 0.0, 0.0], [0.0, 0.0, 5.0])
    >>> [(lab, np.round(np.degrees(q.rvec), 1).tolist()) for lab, q in turned_about_view(p, np.zeros(3), (20.0,))]
    [('camx+20', [20.0, 0.0, 0.0]), ('camx-20', [-20.0, 0.0, 0.0]), ('camy+20', [0.0, 20.0, 0.0]), ('camy-20', [0.0, -20.0, 0.0])]
    """
    c = np.asarray(centre, float)
    out = []
    for i, axis in enumerate("xy"):
        e = np.zeros(3)
        e[i] = 1.0
        for a in angles_deg:
            for sgn in (1, -1):
                out.append((f"cam{axis}{sgn * a:+g}", rotate_about_centre(pose, c, pose.R.T @ e * np.radians(sgn * a))))
    return out


def synthetic_viewset(label: str, mesh: Mesh, groups: np.ndarray, src_image: np.ndarray, src_camera: PinholeCamera,
                      src_pose: Pose, camera: PinholeCamera, pose: Pose, params: ViewsetParams,
                      min_source_cos: float = 0.3, margin_px: int = 16) -> Viewset | None:
    """The viewset of the object at ``pose`` in ``camera``, textured from ``src_image`` (seen by
    ``src_camera`` at ``src_pose``: any crop of a frame, :meth:`PinholeCamera.cropped`) as
    :func:`render_textured_view` does, but rendered and described only over the object's box
    (plus ``margin_px``) — the same rays, a fraction of the pixels: ~15 ms instead of ~100 ms
    for a 640×480 frame. Keypoints are returned in ``camera``'s pixels, the viewset flagged
    ``synthetic`` and ``learned`` (made at run time, not by training). None when the object is
    not in view or nothing of it is textured."""
    box = footprint(mesh, camera, pose, margin_px)
    if box is None:
        return None
    x0, y0, x1, y1 = box
    win = camera.cropped(x0, y0, x1, y1)
    src_buffers = render(mesh, src_camera, src_pose)
    img, textured, buf = render_textured_view(mesh, groups, src_image, src_camera, src_pose, src_buffers, win, pose,
                                              min_source_cos)
    if not textured.any():
        return None
    vs = build_viewset(label, -1, True, img, textured, win, pose, mesh, buf, params, RUN_TIME_STRETCH)
    return replace(vs.uncropped(camera, x0, y0), learned=True)


def _lookup(face, groups, use, Hs, rays, fx, fy, cx, cy, dist, distorted, src_face, src_mask, masked,
            map_x, map_y, textured, normals, depth, src_depth, depth_tol, same_cos):  # pragma: no cover (compiled)
    """The per-pixel work of :func:`render_textured_view`, compiled: each pixel of a face whose
    plane group ``g`` the photo sees well (``use[g]``) maps its ray through the group's
    homography ``Hs[g]`` into the photo (projected as :meth:`PinholeCamera.project` does, lens
    distortion included, term for term) and takes the photo's pixel there if the photo shows the
    same plane there (its z-buffer ``src_face`` shows a face of group ``g``) and, when ``masked``, the user's mask marks the object.
    Another plane's face ``sf`` there shows the same surface when it turns from this pixel's
    face ``f`` by less than ~30° (``normals[f]·normals[sf] ≥ same_cos``) and the photo's z-buffer
    ``src_depth`` lies within ``depth_tol`` of the point's own depth in the photo, ``z·(H r)₃``
    (``z`` = ``depth`` here, ``r`` the pixel's ray): the neighbouring facet of a curved or scanned
    surface (whose facets are planes of their own, a few photo pixels wide), not another part of
    the object in front of it, nor the other face of a sharp edge (a box's: the same bits as the
    plane test alone).
    Fills ``map_x``/``map_y`` (the photo's coordinates, for ``cv2.remap``) and ``textured``."""
    k1, k2, p1, p2, k3, k4, k5, k6 = dist[0], dist[1], dist[2], dist[3], dist[4], dist[5], dist[6], dist[7]
    sh, sw = src_face.shape
    for y in range(face.shape[0]):
        for x in range(face.shape[1]):
            f = face[y, x]
            if f < 0:
                continue
            g = groups[f]
            if not use[g]:
                continue
            rx, ry = rays[y, x, 0], rays[y, x, 1]
            X2 = rx * Hs[g, 2, 0] + ry * Hs[g, 2, 1] + Hs[g, 2, 2]
            if not X2 > 0.0:
                continue
            X0 = rx * Hs[g, 0, 0] + ry * Hs[g, 0, 1] + Hs[g, 0, 2]
            X1 = rx * Hs[g, 1, 0] + ry * Hs[g, 1, 1] + Hs[g, 1, 2]
            iz = 1.0 / X2
            xn = X0 * iz
            yn = X1 * iz
            if distorted:
                r2 = xn * xn + yn * yn
                num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
                radial = num / den
                xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
                yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
                u = fx * xd + cx
                v = fy * yd + cy
            else:
                u = fx * xn + cx
                v = fy * yn + cy
            ui = np.rint(u)
            vi = np.rint(v)
            if not (ui >= 0 and vi >= 0 and ui < sw and vi < sh):
                continue
            iu, iv = int(ui), int(vi)
            sf = src_face[iv, iu]
            if sf < 0 or (masked and not src_mask[iv, iu] > 0):
                continue
            if groups[sf] != g and not (
                    normals[f, 0] * normals[sf, 0] + normals[f, 1] * normals[sf, 1] + normals[f, 2] * normals[sf, 2]
                    >= same_cos and abs(src_depth[iv, iu] - depth[y, x] * X2) <= depth_tol):
                continue
            map_x[y, x] = u
            map_y[y, x] = v
            textured[y, x] = True


_compiled_lookup = lazily_compiled(_lookup)  # compiled on first use, cached on disk (tracking/jit.py)

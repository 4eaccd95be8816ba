"""Which model points a camera sees at a pose: the trackable points of the object model.

The viewsets repeat the same physical points (synthetic views of one photo), so their 3-D points
are merged first. Visibility is a z-buffer test at reduced resolution (a box renders in ~1 ms at
1/4 scale): a point is seen if it projects inside the image, its depth matches the z-buffer
there (not hidden by another part of the object, not on a back face) and its face is not seen
at a grazing angle, where KLT windows straddle two faces.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.mesh import Mesh
from quatrack.viewsets.render import face_normals, render
from quatrack.tracking.pose import Pose


def merge_points(points: np.ndarray, tol: float) -> np.ndarray:
    """Points (n, 3) merged on a grid of cell ``tol`` (one representative per cell)."""
    P = np.asarray(points, float).reshape(-1, 3)
    if len(P) == 0:
        return P
    cells = np.floor(P / tol).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return P[np.sort(first)]


_SCALED: dict[tuple[int, float], tuple[weakref.ref, PinholeCamera]] = {}  # (id(camera), s) -> (camera, scaled)


def scaled_camera(camera: PinholeCamera, s: float) -> PinholeCamera:
    """The camera of the image resized by ``s`` (pixel centres preserved); remembered per camera
    and scale (cameras are frozen; the tracker asks several times a frame)."""
    key = (id(camera), float(s))
    hit = _SCALED.get(key)
    if hit is not None and hit[0]() is camera:
        return hit[1]
    small = camera.scaled(s)
    if len(_SCALED) >= 64:
        _SCALED.clear()
    _SCALED[key] = (weakref.ref(camera), small)
    return small


@dataclass(frozen=True)
class VisibilityParams:
    scale: float = 0.25  # z-buffer resolution relative to the image
    depth_tol: float = 0.03  # × the mesh's extent
    min_cos: float = 0.25  # |cos| between the view ray and the face normal
    margin_px: float = 12.0  # points closer to the image border are not used (KLT window)


def visibility_buffers(mesh: Mesh, camera: PinholeCamera, pose: Pose, params: VisibilityParams = VisibilityParams()):
    """The reduced-resolution z-buffer :func:`visible_points` tests against (one per frame and
    pose serves every measurement source)."""
    return render(mesh, scaled_camera(camera, params.scale), pose)


def visible_points(
    mesh: Mesh, camera: PinholeCamera, pose: Pose, points: np.ndarray, params: VisibilityParams = VisibilityParams(),
    buffers=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mask (n,) of the ``points`` (object frame) visible at ``pose``, and their pixels (n, 2).
    ``buffers``: :func:`visibility_buffers` of the same mesh, camera, pose and params, if at hand."""
    P = np.asarray(points, float).reshape(-1, 3)
    Xc = pose.apply(P)
    n = len(P)
    ok = Xc[:, 2] > 1e-6
    uv = np.full((n, 2), -1.0)
    if not ok.any():
        return ok, uv
    uv[ok] = camera.project(Xc[ok])
    w, h = camera.width, camera.height
    m = params.margin_px
    ok &= (uv[:, 0] >= m) & (uv[:, 1] >= m) & (uv[:, 0] <= w - 1 - m) & (uv[:, 1] <= h - 1 - m)
    if not ok.any():
        return ok, uv
    small = scaled_camera(camera, params.scale)
    buf = buffers if buffers is not None else render(mesh, small, pose)
    sx, sy = small.width / w, small.height / h
    ui = np.clip(np.rint((uv[:, 0] + 0.5) * sx - 0.5).astype(int), 0, small.width - 1)
    vi = np.clip(np.rint((uv[:, 1] + 0.5) * sy - 0.5).astype(int), 0, small.height - 1)
    face = buf.face[vi, ui]
    depth = buf.depth[vi, ui]
    # away from the silhouette by a low-res pixel: a KLT window there straddles the background
    inner = cv2.erode((buf.face >= 0).astype(np.uint8), np.ones((3, 3), np.uint8))
    ok &= (face >= 0) & (inner[vi, ui] > 0)
    ok &= np.abs(depth - Xc[:, 2]) < params.depth_tol * mesh.extent
    normals = face_normals(mesh)[np.maximum(face, 0)] @ pose.R.T
    rays = Xc / np.linalg.norm(Xc, axis=1, keepdims=True)
    ok &= np.abs(np.einsum("ij,ij->i", normals, rays)) >= params.min_cos
    return ok, uv


def mesh_edges(mesh: Mesh, angle_deg: float = 1.0) -> np.ndarray:
    """Edges (k, 2, 3) between faces that are not coplanar, and boundary edges: the wireframe
    a viewer expects (a box's 12 edges, not its triangulation's diagonals). (An edge shared by
    other than two faces is always one; faces of opposite normals count as coplanar.)"""
    return sharp_edges(mesh, angle_deg)[0]


def sharp_edges(mesh: Mesh, angle_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mesh_edges` (k, 2, 3) and the two faces each one borders (k, 2; −1: none, on the
    mesh's boundary).

    >>> from quatrack.viewsets.mesh import make_mesh
    >>> tetra = make_mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
    ...                   np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    >>> E, F = sharp_edges(tetra)
    >>> E.shape, F.shape, bool((F >= 0).all())
    ((6, 2, 3), (6, 2), True)
    """
    edges, faces, counts = mesh.edge_faces
    normals = mesh.face_normals
    cos = np.abs(np.einsum("ij,ij->i", normals[faces[:, 0]], normals[np.maximum(faces[:, 1], 0)]))
    keep = (counts != 2) | (cos < np.cos(np.radians(angle_deg)))
    if not keep.any():
        return np.zeros((0, 2, 3)), np.zeros((0, 2), int)
    return mesh.vertices[edges[keep]], faces[keep]


def edge_samples_visible(zbuffer, uv: np.ndarray, z: np.ndarray, faces: np.ndarray, plane_ids: np.ndarray,
                         image_size: tuple[int, int], tol: float) -> np.ndarray:
    """Mask (n,) of the model-edge samples at pixels ``uv`` (n, 2) of a ``image_size`` = (w, h)
    image, at camera depths ``z`` (n,), that a reduced z-buffer ``zbuffer`` (its ``depth``, inf on
    the background, and ``face``, −1 there) shows: the plane of one of the two faces the
    sample's edge borders (``faces`` (n, 2), −1: none; ``plane_ids`` (m,) the planar group of
    each face, :attr:`~quatrack.viewsets.mesh.Mesh.plane_ids`) is rendered in its 3×3
    neighbourhood, or no surface there lies nearer than ``z − tol``.

    Why both: a sample lies on its faces' border, and the z-buffer is reduced, so it is judged
    by its neighbourhood. The depth test alone, against the nearest depth round it, fails on a
    face seen at a grazing angle, whose depth changes fast from pixel to pixel: the zoo flat
    box's far outline lay 15–17 mm behind the nearest depth round it, with a 6 mm tolerance, so
    only one face's outline was left, and the edges judged right poses to be 0.4–1.6 × the
    5 %/5° criterion off (bench/RESULTS.md, session 39). Its own face seen next to it says the
    edge is there whatever the slope; on a curved surface, whose thin facets the reduced buffer
    may not show, the depth test still holds.

    >>> class Z: pass
    >>> zb = Z()
    >>> zb.face = np.array([[0, 0, 1], [0, 0, 1], [-1, -1, -1]])
    >>> zb.depth = np.array([[10.0, 11.0, 30.0], [10.0, 11.0, 30.0], [np.inf] * 3], np.float32)
    >>> faces = np.array([[2, -1], [2, -1], [1, -1]])  # the first two border face 2, of plane 7: not shown
    >>> edge_samples_visible(zb, np.array([[1.0, 1.0]] * 3), np.array([10.5, 25.0, 25.0]), faces,
    ...                      np.array([0, 1, 7]), (3, 3), 1.0)
    array([ True, False,  True])
    """
    face, depth = np.asarray(zbuffer.face), np.asarray(zbuffer.depth, np.float32)
    dh, dw = depth.shape
    w, h = image_size
    ui = np.clip(np.rint((uv[:, 0] + 0.5) * dw / w - 0.5).astype(int), 0, dw - 1)
    vi = np.clip(np.rint((uv[:, 1] + 0.5) * dh / h - 0.5).astype(int), 0, dh - 1)
    # each sample's 3×3 neighbourhood (clipped at the border: the repeated pixels are inside it)
    dy, dx = np.divmod(np.arange(9), 3)
    rows, cols = np.clip(vi[:, None] + dy - 1, 0, dh - 1), np.clip(ui[:, None] + dx - 1, 0, dw - 1)  # (n, 9)
    flat = rows * dw + cols  # (np.take of flat indices: the pixels of [rows, cols], faster)
    d = np.take(depth, flat)
    near = np.where(np.isfinite(d), d, np.inf).min(axis=1)  # the nearest surface round it (NaN: none)
    ok = np.asarray(z) <= near + tol
    plane_ids = np.asarray(plane_ids)
    faces = np.asarray(faces)
    planes = np.where(faces >= 0, plane_ids[np.maximum(faces, 0)], -1)
    f = np.take(face, flat)
    seen = np.where(f >= 0, plane_ids[np.maximum(f, 0)], -2)  # (−2: no face, never an edge's)
    return ok | ((seen == planes[:, :1]) | (seen == planes[:, 1:])).any(axis=1)


def model_gap(uv: np.ndarray, normal: np.ndarray, edge: np.ndarray, reach: float, step: float) -> np.ndarray:
    """For each edge sample (pixels ``uv`` (n, 2), unit normals ``normal`` (n, 2), model edge
    ``edge`` (n,)), how far across it (px, along its normal) the nearest sample of *another*,
    parallel model edge lies (within ``step`` along it; ``|nᵢ·nⱼ| ≥ 0.9``); inf beyond ``reach``.

    Why: a face seen at a grazing angle projects to a thin strip whose two edges lie a few
    pixels apart, and a 1-D search for one that reaches further finds the other, with the
    same orientation: the pose is pulled by the strip's width. The model says where its own
    edges crowd, so a search stops halfway to the next one (zoo flat box, its side seen nearly
    edge-on, 5 px wide: a track pulled 5.9° off in three frames; bench/RESULTS.md, session 39).

    >>> uv = np.array([[10.0, 10.0], [10.0, 14.0], [30.0, 10.0], [16.0, 14.0]])
    >>> n = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0], [1.0, 0.0]])
    >>> model_gap(uv, n, np.array([0, 1, 0, 2]), reach=10.0, step=4.0).tolist()  # 0 and 1: 4 px apart
    [4.0, 4.0, inf, inf]
    """
    from scipy.spatial import cKDTree

    n = len(uv)
    gap = np.full(n, np.inf)
    if n < 2:
        return gap
    pairs = cKDTree(uv).query_pairs(float(np.hypot(reach, step)), output_type="ndarray")
    if len(pairs) == 0:
        return gap
    i, j = pairs[:, 0], pairs[:, 1]
    d = uv[j] - uv[i]
    ni = normal[i]
    across = np.abs(np.einsum("ij,ij->i", d, ni))
    along = np.abs(d[:, 0] * ni[:, 1] - d[:, 1] * ni[:, 0])
    ok = (edge[i] != edge[j]) & (np.abs(np.einsum("ij,ij->i", ni, normal[j])) >= 0.9) & (along <= step) & (across <= reach)
    np.minimum.at(gap, i[ok], across[ok])
    np.minimum.at(gap, j[ok], across[ok])
    return gap


def segment_samples(A: np.ndarray, B: np.ndarray, camera: PinholeCamera, step_px: float,
                    max_per_segment: int | None = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Samples along 3-D segments with camera-frame ends ``A``, ``B`` (k, 3), about every
    ``step_px`` pixels of their projections: each projected segment is cut into
    ``max(1, ⌈length / step_px⌉)`` equal parts (at most ``max_per_segment``: an end just in front
    of the camera projects millions of px away, and its segment would ask for millions of
    samples; None: no bound), sampled at the middle of each. Returns per sample
    its segment (n,), its camera-frame point (n, 3), pixel (n, 2) and the unit normal of its
    projected segment (n, 2), the direction turned by +90° (x right, y down: its right side).

    >>> cam = PinholeCamera(100.0, 100.0, 50.0, 50.0, width=100, height=100)
    >>> seg, P, uv, n = segment_samples(np.array([[0.0, 0, 1]]), np.array([[0.3, 0, 1]]), cam, 10.0)
    >>> seg.tolist(), uv[:, 0].tolist(), n[0].tolist()
    ([0, 0, 0], [55.0, 65.0, 75.0], [-0.0, 1.0])
    """
    if len(A) == 0:
        return np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2))
    ua, ub = camera.project(A), camera.project(B)
    n_s = np.maximum(1, np.ceil(np.linalg.norm(ub - ua, axis=1) / step_px))
    if max_per_segment is not None:
        n_s = np.minimum(n_s, max_per_segment)
    n_s = n_s.astype(int)
    seg = np.repeat(np.arange(len(A)), n_s)
    first = np.repeat(np.cumsum(n_s) - n_s, n_s)  # each sample's segment's first sample
    s = (np.arange(len(seg)) - first + 0.5) / np.repeat(n_s, n_s)  # (k-th of its segment + ½) / n
    P = A[seg] * (1 - s[:, None]) + B[seg] * s[:, None]
    d = ub[seg] - ua[seg]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    return seg, P, camera.project(P), np.column_stack([-d[:, 1], d[:, 0]])

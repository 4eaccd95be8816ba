"""Projecting a mesh into a camera: z-buffer (depth, face ids, mask), ray casting, keypoint lifting.

Pixels are tested by their *undistorted* ray, so lens distortion is handled exactly: straight
triangle edges stay straight in normalised coordinates, whatever the lens does to them.
Pixel centres are at integer coordinates, as in OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property, lru_cache

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.jit import lazily_compiled

from .mesh import Mesh
from quatrack.tracking.pose import Pose

_NEAR = 1e-6


@dataclass(frozen=True)
class RenderBuffers:
    """Per-pixel result of rendering: camera-frame depth z (inf = background), triangle id (-1)."""

    depth: np.ndarray
    face: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """uint8 mask, 255 where the object is visible."""
        return np.where(self.face >= 0, 255, 0).astype(np.uint8)

    @cached_property
    def drawn(self) -> np.ndarray:
        """The ids of the triangles drawn, ascending (a count over the pixels, not a sort),
        computed once: the texture checks render every reference at one pose over the same
        buffers (:func:`~.novel.render_textured_view`), ~5 of them a frame on a walk's tall box.
        (The arrays are never changed once rendered.)

        >>> RenderBuffers(np.zeros((2, 3)), np.array([[-1, 4, 4], [0, -1, 4]], np.int32)).drawn.tolist()
        [0, 4]
        """
        return np.flatnonzero(np.bincount(self.face.ravel() + 1)[1:])


def undistort_pixels(camera: PinholeCamera, uv: np.ndarray) -> np.ndarray:
    """Normalised image coordinates (n, 2) of pixels (n, 2): the direction (x, y, 1) of their rays
    — the rays ``camera.project`` takes back to the pixels. ``cv2.undistortPoints``' rays, but
    where they do not project back (:func:`_inverted`)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if not camera.has_distortion:
        return np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy], axis=1)
    pts = cv2.undistortPoints(
        uv.reshape(-1, 1, 2), camera.matrix, camera.dist_coeffs, None, None, None,
        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12),
    ).reshape(-1, 2)
    back = camera.project(np.column_stack([pts, np.ones(len(pts))]))
    bad = ~(np.abs(back - uv).max(axis=1, initial=0.0) <= _UNDISTORT_TOL_PX)  # (NaN too)
    if bad.any():
        pts[bad] = _inverted(camera, uv[bad])
    return pts


_UNDISTORT_TOL_PX = 1e-6  # a ray is taken from cv2.undistortPoints when it projects back this near


def _inverted(camera: PinholeCamera, uv: np.ndarray) -> np.ndarray:
    """Rays of pixels whose ``cv2.undistortPoints`` ray does not project back to them: OpenCV's
    fixed-point iteration stalls, or lands on the far side of the radius where the lens model
    turns back, for pixels near or beyond that radius (a strong lens's image corners: k1 = −0.45
    alone at 640 × 480, 56°, left the corners' rays 50 px off). The radius is inverted first on
    :meth:`PinholeCamera.project`'s radial model, which grows everywhere (bisection), then the
    ray refined by Newton's method on the whole model (tangential terms too); rays that still
    miss their pixel by more than 0.01 px are NaN (no ray: such a pixel is never drawn)."""
    d = np.zeros(8)
    d[: camera.dist_coeffs.size] = camera.dist_coeffs
    k1, k2, _, _, k3, k4, k5, k6 = d
    r2m = camera.valid_r2

    def radial_out(r):  # r_d of r on the radial model, continued outwards beyond the valid radius
        s = np.minimum(r * r, r2m)
        return r * (1.0 + s * (k1 + s * (k2 + s * k3))) / (1.0 + s * (k4 + s * (k5 + s * k6)))

    pd = np.column_stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy])
    rd = np.hypot(pd[:, 0], pd[:, 1])
    lo, hi = np.zeros_like(rd), np.full_like(rd, 1.0)
    while np.any(grow := radial_out(hi) < rd) and hi.max() < 1e6:
        hi = np.where(grow, 2.0 * hi, hi)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = radial_out(mid) < rd
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    scale = np.divide(lo, rd, out=np.ones_like(rd), where=rd > 0)
    xy = pd * scale[:, None]
    for _ in range(20):
        proj, J = camera.project_with_jacobian(np.column_stack([xy, np.ones(len(xy))]))
        res = uv - proj
        if np.all(np.abs(res) < 1e-9):
            break
        with np.errstate(all="ignore"):
            step = np.linalg.solve(J[:, :, :2], res[:, :, None])[:, :, 0] if np.all(np.isfinite(J)) else 0.0 * xy
        xy = np.where(np.isfinite(step), xy + step, xy)
    miss = ~(np.abs(camera.project(np.column_stack([xy, np.ones(len(xy))])) - uv).max(axis=1) <= 0.01)
    xy[miss] = np.nan
    return xy


@lru_cache(maxsize=8)
def _pixel_rays_cached(key: tuple) -> np.ndarray:
    fx, fy, cx, cy, dist, w, h = key
    if not np.any(np.asarray(dist) != 0.0):
        # x depends on the column only, y on the row: (u − cx)/fx per column, broadcast — the
        # same arithmetic per pixel as undistort_pixels' over a meshgrid, the same bits
        out = np.empty((h, w, 2))
        out[..., 0] = ((np.arange(w, dtype=np.float64) - cx) / fx)[None, :]
        out[..., 1] = ((np.arange(h, dtype=np.float64) - cy) / fy)[:, None]
    else:
        cam = PinholeCamera(fx, fy, cx, cy, np.asarray(dist), width=w, height=h)
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        out = undistort_pixels(cam, np.stack([u.ravel(), v.ravel()], axis=1)).reshape(h, w, 2)
    out.setflags(write=False)
    return out


def pixel_rays(camera: PinholeCamera) -> np.ndarray:
    """(H, W, 2) normalised ray coordinates of every pixel centre (cached per camera).

    A crop of a distorted camera (:meth:`PinholeCamera.cropped`) takes its rays from the whole
    image's, sliced (a read-only view): the texture checks and the keyframes' views crop a new
    window every frame, and undistorting each window's pixels (iteratively,
    ``cv2.undistortPoints``) cost ~28 ms for a 228 × 440 crop. The whole image's rays are those
    of the same pixels to ~1e-15 (the principal point moved by whole pixels, added back;
    tests/test_viewsets_render.py). Without distortion a crop's rays cost ~0.1 ms and are
    computed for the crop itself."""
    if camera.width is None or camera.height is None:
        raise ValueError("the camera needs an image size to render")
    if camera.has_distortion and camera.crop_of is not None:
        x0, y0, W, H = camera.crop_of
        w, h = int(camera.width), int(camera.height)
        if 0 <= x0 and 0 <= y0 and x0 + w <= W and y0 + h <= H:
            whole = replace(camera, cx=camera.cx + x0, cy=camera.cy + y0, width=W, height=H, crop_of=None)
            return pixel_rays(whole)[y0:y0 + h, x0:x0 + w]
    key = (camera.fx, camera.fy, camera.cx, camera.cy, tuple(float(x) for x in camera.dist_coeffs),
           int(camera.width), int(camera.height))
    return _pixel_rays_cached(key)


def face_normals(mesh: Mesh) -> np.ndarray:
    """``mesh.face_normals`` (computed once per mesh and kept on it: :class:`~.mesh.Mesh`)."""
    return mesh.face_normals


@lru_cache(maxsize=8)
def _unit_rays_cached(key: tuple) -> np.ndarray:
    xy = _pixel_rays_cached(key)
    h, w = xy.shape[:2]
    rays = np.dstack([*np.moveaxis(xy, -1, 0), np.ones((h, w))])
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    rays.setflags(write=False)
    return rays


def unit_pixel_rays(camera: PinholeCamera) -> np.ndarray:
    """(H, W, 3) unit directions (camera frame) of every pixel centre's ray (cached per camera)."""
    pixel_rays(camera)  # (checks the image size)
    key = (camera.fx, camera.fy, camera.cx, camera.cy, tuple(float(x) for x in camera.dist_coeffs),
           int(camera.width), int(camera.height))
    return _unit_rays_cached(key)


def _pixel_bboxes(camera: PinholeCamera, tris: np.ndarray, w: int, h: int) -> np.ndarray:
    """Pixel bounding boxes ``(m, 4)`` ``[x0, y0, x1, y1]`` (inclusive, clipped to the image; empty
    when ``x0 > x1`` or ``y0 > y1``) of camera-frame triangles ``(m, 3, 3)``, one pixel of margin.
    With distortion the edges are sampled (9 points each), so their bending is covered."""
    if camera.has_distortion:
        s = np.linspace(0.0, 1.0, 9)[None, :, None]
        pts = np.concatenate([tris[:, a, None] * (1 - s) + tris[:, b, None] * s for a, b in ((0, 1), (1, 2), (2, 0))], axis=1)
    else:
        pts = tris
    uv = camera.project(pts.reshape(-1, 3)).reshape(len(tris), -1, 2)
    lo, hi = uv.min(axis=1), uv.max(axis=1)
    if camera.has_distortion:
        lo, hi = _inside_the_view(camera, tris, lo, hi)
    lo = np.floor(lo) - 1
    hi = np.ceil(hi) + 1
    x0, y0 = np.clip(lo[:, 0], 0, w), np.clip(lo[:, 1], 0, h)
    x1, y1 = np.clip(hi[:, 0], -1, w - 1), np.clip(hi[:, 1], -1, h - 1)
    return np.column_stack([x0, y0, x1, y1]).astype(np.int64)


_CLIPPED_SAMPLES = 65  # per edge inside the view's ray box, and per side of the box


@lru_cache(maxsize=32)
def _ray_box(camera: PinholeCamera) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1): the box of the normalised rays of the image's border pixels (with a
    lens growing outwards, of all its pixels), per camera (cameras hash by their fields)."""
    rays = pixel_rays(camera)
    border = np.concatenate([rays[0], rays[-1], rays[:, 0], rays[:, -1]])
    (x0, y0), (x1, y1) = np.nanmin(border, axis=0), np.nanmax(border, axis=0)
    return float(x0), float(y0), float(x1), float(y1)


def _inside_the_view(camera: PinholeCamera, tris: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """``lo``, ``hi`` (m, 2) of the triangles' sampled edges, widened by what their parts inside
    the view project to, for the triangles reaching out of the box of the image's rays. Why:
    nine samples of an edge running far out of the view project far away, and the curve the
    lens makes of the edge between them inside the image was left out of the box (a triangle
    reaching 47 units off a depth of 1, through the rational lens of
    tests/test_distortion_lens_model.py, lost tens of thousands of its pixels). The
    boundary of (triangle ∩ ray box) bounds what the triangle shows in the image: its edges
    clipped to the box (Liang–Barsky), sampled densely, and the box's sides inside the triangle
    (whose pixels lie at or beyond the image's border)."""
    # (a corner outside the box projects outside the image: only triangles with a sample there are looked at)
    k = np.flatnonzero(~((lo >= 0).all(axis=1) & (hi[:, 0] <= camera.width - 1) & (hi[:, 1] <= camera.height - 1)))
    if not len(k):
        return lo, hi
    bx0, by0, bx1, by1 = _ray_box(camera)
    p = tris[k, :, :2] / tris[k, :, 2:3]  # normalised corners (every corner is in front)
    out = (p[..., 0] < bx0) | (p[..., 0] > bx1) | (p[..., 1] < by0) | (p[..., 1] > by1)
    k = k[out.any(axis=1)]
    if not len(k):
        return lo, hi
    p = tris[k, :, :2] / tris[k, :, 2:3]
    a, b = p, p[:, [1, 2, 0]]  # edges a → b, (n, 3, 2)
    d = b - a
    t0, t1 = np.zeros(d.shape[:2]), np.ones(d.shape[:2])
    with np.errstate(divide="ignore", invalid="ignore"):
        for dd, q in ((-d[..., 0], a[..., 0] - bx0), (d[..., 0], bx1 - a[..., 0]),
                      (-d[..., 1], a[..., 1] - by0), (d[..., 1], by1 - a[..., 1])):
            t = q / dd
            t0 = np.where(dd < 0, np.maximum(t0, t), t0)
            t1 = np.where(dd > 0, np.minimum(t1, t), t1)
            t1 = np.where((dd == 0) & (q < 0), -1.0, t1)  # parallel to this side and outside it
    s = np.linspace(0.0, 1.0, _CLIPPED_SAMPLES)
    t = t0[..., None] + (t1 - t0)[..., None] * s  # (n, 3, S)
    xy = a[:, :, None] + t[..., None] * d[:, :, None]
    xy[t0 > t1] = np.nan  # (an edge missing the box)
    uv = camera.project(np.concatenate([xy.reshape(-1, 2), np.ones((xy.size // 2, 1))], axis=1)).reshape(len(k), -1, 2)
    # the box's sides, sampled, where inside each triangle (the three edge functions of one sign)
    g = np.linspace(0.0, 1.0, _CLIPPED_SAMPLES)
    side = np.concatenate([np.column_stack([bx0 + (bx1 - bx0) * g, np.full_like(g, v)]) for v in (by0, by1)]
                          + [np.column_stack([np.full_like(g, v), by0 + (by1 - by0) * g]) for v in (bx0, bx1)])
    e = [(b[:, i, None, 0] - a[:, i, None, 0]) * (side[None, :, 1] - a[:, i, None, 1])
         - (b[:, i, None, 1] - a[:, i, None, 1]) * (side[None, :, 0] - a[:, i, None, 0]) for i in range(3)]
    inside = (np.minimum(np.minimum(e[0], e[1]), e[2]) >= 0) | (np.maximum(np.maximum(e[0], e[1]), e[2]) <= 0)
    uv_side = camera.project(np.column_stack([side, np.ones(len(side))]))
    lo, hi = lo.copy(), hi.copy()
    for pts in (uv, np.where(inside[..., None], uv_side[None], np.nan)):
        finite = np.isfinite(pts).all(axis=2, keepdims=True)
        lo[k] = np.fmin(lo[k], np.where(finite, pts, np.inf).min(axis=1))
        hi[k] = np.fmax(hi[k], np.where(finite, pts, -np.inf).max(axis=1))
    return lo, hi


def render(mesh: Mesh, camera: PinholeCamera, pose: Pose) -> RenderBuffers:
    """Z-buffer rendering of the mesh: exact ray/plane depth per pixel, nearest triangle wins
    (ties: the lower triangle index).

    A pixel is inside a triangle when the three edge functions ``(b − a) × (r − a)`` of the
    triangle's normalised corners agree in sign at the pixel's undistorted ray ``r = (x, y)``;
    its depth is the ray/plane intersection ``z = (n·V₀) / (n·(x, y, 1))``. Each triangle is
    tested over its pixel bounding box. The bounding boxes and normalised corners of all
    triangles are computed at once. Triangles with a corner at or behind the camera plane are
    skipped (callers check that the object lies in front of the camera). Faces a closed mesh
    turns away from the camera are not tested (:func:`_front_triangles`: they are hidden anyway).

    The per-pixel test runs compiled (:func:`_zbuffer`, numba): one triangle after another in
    index order, each over its box, the same arithmetic in the same order as the plain numpy
    loop over triangles (:func:`render_reference`), whose buffers it equals bit for bit
    (tests/test_viewsets_render.py). Why compiled: the tracker renders a z-buffer 2–4 times a
    frame, and the numpy loop's cost is per triangle (a dozen array operations each, over boxes
    of a few hundred pixels): a cylinder's 48 front triangles took 2.2 ms at 160×120, 0.4 ms
    compiled (bench/RESULTS.md, session 35).
    """
    return _rasterise(mesh, camera, pose)


def render_window(mesh: Mesh, camera: PinholeCamera, pose: Pose, window: tuple[int, int, int, int]) -> RenderBuffers:
    """:func:`render`'s buffers over the pixel box ``window`` = (x0, y0, x1, y1) of the image
    only (``x1``, ``y1`` exclusive, inside the image): ``render(...)[y0:y1, x0:x1]`` bit for bit
    — the same rays (the full image's, sliced), the same triangles' tests on the pixels of their
    boxes inside the window — without the cost of the rest of the image."""
    return _rasterise(mesh, camera, pose, window=window)


def footprint(mesh: Mesh, camera: PinholeCamera, pose: Pose, margin_px: int = 0) -> tuple[int, int, int, int] | None:
    """The pixel box (x0, y0, x1, y1; ends exclusive) holding every pixel :func:`render` may
    draw — the union of its triangles' boxes, grown by ``margin_px`` on every side (room for a
    filter's or a descriptor's neighbourhood), clipped to the image — or None when it draws none."""
    if camera.width is None or camera.height is None:
        raise ValueError("the camera needs an image size to render")
    w, h = int(camera.width), int(camera.height)
    tris, _, _, ids = _front_triangles(mesh, pose)
    if not len(ids):
        return None
    boxes = _pixel_bboxes(camera, tris[ids], w, h)
    boxes = boxes[(boxes[:, 2] >= boxes[:, 0]) & (boxes[:, 3] >= boxes[:, 1])]
    if not len(boxes):
        return None
    m = int(margin_px)
    return (max(int(boxes[:, 0].min()) - m, 0), max(int(boxes[:, 1].min()) - m, 0),
            min(int(boxes[:, 2].max()) + 1 + m, w), min(int(boxes[:, 3].max()) + 1 + m, h))


def _front_triangles(mesh: Mesh, pose: Pose, cull: bool = False):
    """Camera-frame triangles (m, 3, 3), their (unnormalised) normals and plane offsets, and the
    indices of those :func:`render` tests (in front of the camera, not seen edge-on).

    ``cull``: also leave out the faces turned away from the camera (``n·V₀ > 0``: the camera is
    on their inner side) when the mesh is closed with outward normals
    (:attr:`~.mesh.Mesh.closed_outward`) and the camera lies outside its bounding box. Such a
    face is then always behind a face turned towards the camera, so the buffers are the same
    but where a ray meets both exactly on the edge they share (a tie at the silhouette, where
    the last bit of the two depths decides); it halves a convex object's triangles."""
    tris = pose.apply(mesh.vertices)[mesh.faces]  # (m, 3, 3) camera frame
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    offsets = np.einsum("ij,ij->i", normals, tris[:, 0])
    tested = np.all(tris[:, :, 2] > _NEAR, axis=1) & (offsets != 0.0)  # else behind, or edge-on
    if cull and mesh.closed_outward:
        eye = -pose.R.T @ pose.t  # the camera centre in the object frame
        V = mesh.vertices
        if np.any(eye < V.min(axis=0)) or np.any(eye > V.max(axis=0)):
            tested &= offsets < 0.0
    return tris, normals, offsets, np.flatnonzero(tested)


def _rasterise(mesh: Mesh, camera: PinholeCamera, pose: Pose, window: tuple[int, int, int, int] | None = None,
               cull: bool = True, compiled: bool = True) -> RenderBuffers:
    """:func:`render`'s z-buffer; ``window``: only over that pixel box (:func:`render_window`);
    ``cull``: skip the faces a closed mesh turns away from the camera (:func:`_front_triangles`);
    ``compiled``: the per-pixel test by :func:`_zbuffer`, else by the numpy loop over triangles
    (:func:`render_reference`)."""
    W, H = int(camera.width), int(camera.height)
    wx0, wy0, wx1, wy1 = (0, 0, W, H) if window is None else (int(v) for v in window)
    if not (0 <= wx0 <= wx1 <= W and 0 <= wy0 <= wy1 <= H):
        raise ValueError(f"the window {window} is not inside the {W}×{H} image")
    w, h = wx1 - wx0, wy1 - wy0
    rays = pixel_rays(camera)[wy0:wy1, wx0:wx1]
    depth = np.full((h, w), np.inf, dtype=np.float64)
    face = np.full((h, w), -1, dtype=np.int32)
    tris, normals, offsets, ids = _front_triangles(mesh, pose, cull)
    if not len(ids) or not w or not h:
        return RenderBuffers(depth, face)
    boxes = _pixel_bboxes(camera, tris[ids], W, H)
    if window is not None:  # (the boxes in the window's pixels, clipped to it)
        boxes = np.column_stack([np.maximum(boxes[:, 0], wx0) - wx0, np.maximum(boxes[:, 1], wy0) - wy0,
                                 np.minimum(boxes[:, 2], wx1 - 1) - wx0, np.minimum(boxes[:, 3], wy1 - 1) - wy0])
    keep = (boxes[:, 2] >= boxes[:, 0]) & (boxes[:, 3] >= boxes[:, 1])
    ids, boxes = ids[keep], boxes[keep]
    corners = tris[ids, :, :2] / tris[ids, :, 2:3]  # normalised corners (x, y)
    if compiled:
        zbuffer = _compiled_zbuffer()
        zbuffer(ids.astype(np.int64), np.ascontiguousarray(boxes, dtype=np.int64), corners, normals, offsets,
                np.ascontiguousarray(rays), depth, face, _NEAR)
        return RenderBuffers(depth, face)
    distorted = camera.has_distortion
    if not distorted:
        rx_row, ry_col = rays[0, :, 0][None, :], rays[:, 0, 1][:, None]
    for i, (x0, y0, x1, y1), p in zip(ids.tolist(), boxes.tolist(), corners.tolist()):
        if not distorted:
            rx, ry = rx_row[:, x0 : x1 + 1], ry_col[y0 : y1 + 1]
        else:
            r = rays[y0 : y1 + 1, x0 : x1 + 1]
            rx, ry = r[..., 0], r[..., 1]
        e0 = (p[1][0] - p[0][0]) * (ry - p[0][1]) - (p[1][1] - p[0][1]) * (rx - p[0][0])
        e1 = (p[2][0] - p[1][0]) * (ry - p[1][1]) - (p[2][1] - p[1][1]) * (rx - p[1][0])
        e2 = (p[0][0] - p[2][0]) * (ry - p[2][1]) - (p[0][1] - p[2][1]) * (rx - p[2][0])
        lo, hi = np.minimum(np.minimum(e0, e1), e2), np.maximum(np.maximum(e0, e1), e2)
        inside = (lo >= 0) | (hi <= 0)  # all three of one sign (or on an edge)
        n = normals[i]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = offsets[i] / (n[0] * rx + n[1] * ry + n[2])
        dsub = depth[y0 : y1 + 1, x0 : x1 + 1]
        fsub = face[y0 : y1 + 1, x0 : x1 + 1]
        closer = inside & (z > _NEAR) & (z < dsub)
        np.copyto(dsub, z, where=closer)
        np.copyto(fsub, i, where=closer)
    return RenderBuffers(depth, face)


def _zbuffer(ids, boxes, corners, normals, offsets, rays, depth, face, near):  # pragma: no cover (compiled)
    """The per-pixel test of :func:`_rasterise`, compiled: triangles ``ids`` (ascending) over
    their ``boxes`` ((m, 4) inclusive pixel boxes of ``rays``/``depth``/``face``), with normalised
    ``corners`` (m, 3, 2), their planes' ``normals`` and ``offsets`` (indexed by id); a pixel
    takes a triangle strictly nearer than what it holds (ties: the earlier, lower id). The
    expressions are the numpy loop's, term for term, so the results are the same bits (numba
    does not contract ``a·b + c`` into fused multiply–adds without ``fastmath``)."""
    for j in range(ids.shape[0]):
        i = ids[j]
        p0x, p0y = corners[j, 0, 0], corners[j, 0, 1]
        p1x, p1y = corners[j, 1, 0], corners[j, 1, 1]
        p2x, p2y = corners[j, 2, 0], corners[j, 2, 1]
        n0, n1, n2 = normals[i, 0], normals[i, 1], normals[i, 2]
        off = offsets[i]
        for y in range(boxes[j, 1], boxes[j, 3] + 1):
            for x in range(boxes[j, 0], boxes[j, 2] + 1):
                rx, ry = rays[y, x, 0], rays[y, x, 1]
                e0 = (p1x - p0x) * (ry - p0y) - (p1y - p0y) * (rx - p0x)
                e1 = (p2x - p1x) * (ry - p1y) - (p2y - p1y) * (rx - p1x)
                e2 = (p0x - p2x) * (ry - p2y) - (p0y - p2y) * (rx - p2x)
                if not (min(min(e0, e1), e2) >= 0.0 or max(max(e0, e1), e2) <= 0.0):
                    continue  # the three edge functions disagree in sign: outside
                den = n0 * rx + n1 * ry + n2
                if den == 0.0:  # (the ray parallel to the plane: numpy's ±inf, never nearer)
                    continue
                z = off / den
                if z > near and z < depth[y, x]:
                    depth[y, x] = z
                    face[y, x] = i


# compiled on first use, cached on disk (tracking/jit.py); nogil: a background re-anchoring
# renders beside the frame's step
_compiled_zbuffer = lazily_compiled(_zbuffer)


def render_reference(mesh: Mesh, camera: PinholeCamera, pose: Pose) -> RenderBuffers:
    """:func:`render` with every triangle tested one at a time over its box by numpy (the plain
    loop, as before session 22): the reference the compiled test must equal bit for bit
    (tests/test_viewsets_render.py)."""
    return _rasterise(mesh, camera, pose, compiled=False)


# meshes with at least this many triangles are ray-cast through a grid of the rays' plane
# (_binned_hits); smaller ones test every ray against every triangle
BINNED_MIN_TRIANGLES = 512


def cast_rays(mesh: Mesh, pose: Pose, rays_xy: np.ndarray, chunk: int = 4096):
    """Nearest intersection of camera rays (x, y, 1) with the mesh (Möller–Trumbore).

    Returns ``(X_obj (n, 3), face (n,) or -1, cos_view (n,))``, where ``cos_view`` is the
    |cosine| between the ray and the hit triangle's normal (0 = grazing).

    A mesh of ``BINNED_MIN_TRIANGLES`` or more triangles (a scanned object: 10⁴–10⁶) is not
    tested ray by triangle: each ray meets only the triangles whose projection's box covers its
    cell of a grid laid over the rays (:func:`_binned_hits`), the same hits at a fraction of the
    cost (a 49 000-triangle box: ~1 000 keypoints lifted in 0.1 s instead of 16 s).
    """
    xy = np.asarray(rays_xy, dtype=float).reshape(-1, 2)
    n = len(xy)
    R, t = pose.R, pose.t
    origin = -R.T @ t  # camera centre in the object frame
    dirs = np.column_stack([xy, np.ones(n)]) @ R  # R^T d, row-wise
    tri = mesh.triangles
    normals = face_normals(mesh)
    if len(tri) >= BINNED_MIN_TRIANGLES and n:
        best_s, best_f = _binned_hits(mesh, tri, pose, xy, origin, dirs)
    else:
        best_s, best_f = _all_hits(tri, origin, dirs, chunk)
    found = np.isfinite(best_s)
    X = np.full((n, 3), np.nan)
    X[found] = origin + dirs[found] * best_s[found, None]
    cos = np.zeros(n)
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    cos[found] = np.abs(np.einsum("ij,ij->i", unit[found], normals[best_f[found]]))
    return X, np.where(found, best_f, -1), cos


def _ray_hits(d: np.ndarray, origin: np.ndarray, v0: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Möller–Trumbore: the ray parameter ``s`` at which each ray ``origin + s d`` meets the
    triangle ``(v0, v0 + e1, v0 + e2)`` (inf where it misses, runs parallel to it or meets it
    at ``s ≤ _NEAR``), over arrays that broadcast along their leading axes (the last is xyz):
    every ray against every triangle (:func:`_all_hits`: ``d`` (c, 1, 3) against (m, 3)) or
    listed pairs (:func:`_binned_hits`: (k, 3) against (k, 3)). With ``p = d × e2``,
    ``det = e1·p``, ``T = origin − v0``, ``Q = T × e1``:
    ``u = T·p / det``, ``v = d·Q / det``, ``s = e2·Q / det``; a hit needs ``u, v ≥ 0`` and
    ``u + v ≤ 1`` (within 1e-9, so a ray on a shared edge meets both triangles).

    >>> tri = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])  # v0 at z = 1, e1, e2 in the plane z = 1
    >>> _ray_hits(np.array([[0.2, 0.2, 1.0], [2.0, 0.0, 1.0]]), np.zeros(3), tri[0], tri[1], tri[2]).tolist()
    [1.0, inf]
    """
    dot = lambda a, b: np.einsum("...j,...j->...", a, b)  # noqa: E731 (the last axis, broadcast)
    pvec = np.cross(d, e2)
    det = dot(e1, pvec)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = origin - v0
    u = dot(tvec, pvec) * inv
    qvec = np.cross(tvec, e1)
    v = dot(d, qvec) * inv
    s = dot(e2, qvec) * inv
    tol = 1e-9
    hit = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (s > _NEAR)
    return np.where(hit, s, np.inf)


def _all_hits(tri: np.ndarray, origin: np.ndarray, dirs: np.ndarray, chunk: int = 4096):
    """Every ray (``origin`` + s ``dirs``, object frame) against every triangle ``tri`` (m, 3, 3):
    the nearest hit's ray parameter ``s`` (inf: none) and triangle (-1: none) per ray; ties go
    to the lower triangle."""
    n = len(dirs)
    v0 = tri[:, 0]
    e1 = tri[:, 1] - v0
    e2 = tri[:, 2] - v0
    best_s = np.full(n, np.inf)
    best_f = np.full(n, -1, dtype=np.int64)
    if len(tri) == 0:
        return best_s, best_f
    for s0 in range(0, n, max(1, chunk // max(1, len(tri) // 64 + 1))):
        s = _ray_hits(dirs[s0 : s0 + chunk][:, None, :], origin, v0, e1, e2)  # (c, m)
        j = np.argmin(s, axis=1)
        sj = s[np.arange(len(j)), j]
        sl = slice(s0, s0 + len(j))
        better = sj < best_s[sl]
        best_s[sl] = np.where(better, sj, best_s[sl])
        best_f[sl] = np.where(better, j, best_f[sl])
    return best_s, best_f


def _binned_hits(mesh: Mesh, tri: np.ndarray, pose: Pose, xy: np.ndarray, origin: np.ndarray, dirs: np.ndarray,
                 max_pairs: int = 2_000_000):
    """:func:`_all_hits` for a large mesh (its ``triangles``, ``tri``), through a grid over the
    rays' normalised plane.

    A triangle wholly in front of the camera (every vertex at depth > ``_NEAR``) is met by the
    ray ``(x, y, 1)`` only if ``(x, y)`` lies in its projection, so only in the grid cells its
    projection's box covers: each ray is tested (:func:`_ray_hits`, as in :func:`_all_hits`) against
    the triangles listed in its own cell, ``G × G`` cells with ``G ≈ √m / 2`` over the rays' box,
    in batches of at most ``max_pairs`` ray–triangle pairs. Triangles reaching behind the camera
    (none, for an object in front of it) are tested against every ray. Ties go to the lower
    triangle, as in :func:`_all_hits`."""
    n = len(xy)
    m = len(tri)
    zc = pose.apply(mesh.vertices)
    zf = zc[np.asarray(mesh.faces)]  # (m, 3, 3): the triangles in the camera frame
    front = np.all(zf[:, :, 2] > _NEAR, axis=1)
    best_s = np.full(n, np.inf)
    best_f = np.full(n, -1, dtype=np.int64)
    if not front.all():  # (reaching behind the camera: no projection to bin)
        rest = np.flatnonzero(~front)
        s_r, f_r = _all_hits(tri[rest], origin, dirs)
        hit = f_r >= 0
        best_s[hit], best_f[hit] = s_r[hit], rest[f_r[hit]]
    ids = np.flatnonzero(front)
    if len(ids) == 0:
        return best_s, best_f
    p = zf[ids, :, :2] / zf[ids, :, 2:3]  # projected vertices, normalised (k, 3, 2)
    lo_t, hi_t = p.min(axis=1), p.max(axis=1)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    G = int(np.clip(np.sqrt(m) / 2, 4, 256))
    size = np.maximum(hi - lo, 1e-12) / G
    keep = np.all(hi_t >= lo, axis=1) & np.all(lo_t <= hi, axis=1)  # (boxes that meet the rays' box)
    ids, lo_t, hi_t = ids[keep], lo_t[keep], hi_t[keep]
    pad = 1e-6 * size  # (a ray on a triangle's edge, within Möller–Trumbore's tolerance, still meets it)
    c0 = np.clip(np.floor((lo_t - pad - lo) / size).astype(np.int64), 0, G - 1)
    c1 = np.clip(np.floor((hi_t + pad - lo) / size).astype(np.int64), 0, G - 1)
    # (cell, triangle) pairs: every triangle in every cell its box covers, listed by cell
    nx, ny = c1[:, 0] - c0[:, 0] + 1, c1[:, 1] - c0[:, 1] + 1
    per = nx * ny
    tri_of = np.repeat(np.arange(len(ids)), per)
    k = np.arange(len(tri_of)) - np.repeat(np.cumsum(per) - per, per)
    cell = (c0[tri_of, 1] + k // nx[tri_of]) * G + c0[tri_of, 0] + k % nx[tri_of]
    order = np.argsort(cell, kind="stable")  # (stable: a cell lists its triangles in index order)
    cell_tris = ids[tri_of[order]]
    starts = np.searchsorted(cell[order], np.arange(G * G + 1))
    ray_cell = (np.clip(np.floor((xy[:, 1] - lo[1]) / size[1]).astype(np.int64), 0, G - 1) * G
                + np.clip(np.floor((xy[:, 0] - lo[0]) / size[0]).astype(np.int64), 0, G - 1))
    count = starts[ray_cell + 1] - starts[ray_cell]
    v0_all = tri[:, 0]
    e1_all, e2_all = tri[:, 1] - v0_all, tri[:, 2] - v0_all
    ray_ids = np.flatnonzero(count)
    cum = np.cumsum(count[ray_ids])
    r0 = 0
    while r0 < len(ray_ids):  # (batches of at most max_pairs pairs, at least one ray each)
        done = int(cum[r0 - 1]) if r0 else 0
        r1 = max(int(np.searchsorted(cum, done + max_pairs, side="right")), r0 + 1)
        rays = ray_ids[r0:r1]
        r0 = r1
        cnt = count[rays]
        ray = np.repeat(rays, cnt)
        j = np.arange(len(ray)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        f = cell_tris[starts[ray_cell[ray]] + j]
        s = _ray_hits(dirs[ray], origin, v0_all[f], e1_all[f], e2_all[f])
        hit = np.isfinite(s)
        if not hit.any():
            continue
        ray, f, s = ray[hit], f[hit], s[hit]
        first = np.lexsort((f, s, ray))  # per ray: the nearest, then the lowest triangle
        ray, f, s = ray[first], f[first], s[first]
        lead = np.r_[True, ray[1:] != ray[:-1]]
        ray, f, s = ray[lead], f[lead], s[lead]
        better = (s < best_s[ray]) | ((s == best_s[ray]) & (f < best_f[ray]))
        best_s[ray[better]], best_f[ray[better]] = s[better], f[better]
    return best_s, best_f


def depth_edges(buffers: RenderBuffers, rel_jump: float = 0.05) -> np.ndarray:
    """Boolean map of self-occlusion boundaries: the depth jumps by > ``rel_jump`` within 3×3."""
    d = np.where(np.isfinite(buffers.depth), buffers.depth, 0.0).astype(np.float32)
    obj = (buffers.face >= 0).astype(np.uint8)
    k = np.ones((3, 3), np.uint8)
    big = np.where(obj > 0, d, 0).astype(np.float32)
    small = np.where(obj > 0, d, np.float32(np.finfo(np.float32).max))
    hi = cv2.dilate(big, k)
    lo = cv2.erode(small, k)
    return (obj > 0) & (cv2.erode(obj, k) > 0) & ((hi - lo) > rel_jump * d)


def lift_keypoints(
    mesh: Mesh,
    camera: PinholeCamera,
    pose: Pose,
    uv: np.ndarray,
    min_cos: float = 0.2,
    buffers: RenderBuffers | None = None,
    edge_margin_px: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """3-D model points (n, 3) of 2-D keypoints (n, 2) and a keep mask (n,).

    Each keypoint is undistorted, its ray cast onto the mesh at ``pose``; points that miss,
    hit at a grazing angle (|cos| < ``min_cos``), or lie within ``edge_margin_px`` of a
    silhouette or self-occlusion boundary (when ``buffers`` are given) are dropped.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    X, f, cos = cast_rays(mesh, pose, undistort_pixels(camera, uv))
    keep = (f >= 0) & (cos >= min_cos)
    if buffers is not None and len(uv):
        obj = buffers.face >= 0
        bad = (~obj) | depth_edges(buffers)
        if edge_margin_px > 0:
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * edge_margin_px + 1,) * 2)
            bad = cv2.dilate(bad.astype(np.uint8), k) > 0
        h, w = bad.shape
        ui = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
        vi = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
        keep &= ~bad[vi, ui]
    return X, keep

"""Faster forms of the tracking step's routines equal the plain forms they replaced (issue 12's
step time, session 22). Each test computes the plain form here and compares exactly: a change
to the fast form that alters a result fails it. (Speed itself is measured by the benchmarks.)"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import closed_prism

from quatrack.recognition.tracker.mesh_points import birth_mask
from quatrack.recognition.tracker.params import TrackerParams
from quatrack.recognition.visibility import scaled_camera
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.viewsets.render import depth_edges, pixel_rays, render, unit_pixel_rays

CAM = PinholeCamera(520.0, 515.0, 318.0, 243.0, width=640, height=480)
CAM_DIST = PinholeCamera(520.0, 515.0, 318.0, 243.0, np.array([-0.2, 0.08, 0.001, -0.0015, 0.0]), width=640, height=480)


def _plain_birth_mask(mesh, cam, pose, params):
    """birth_mask as it was: the view-angle test on every pixel, the rays normalised per call."""
    small = scaled_camera(cam, 0.5)
    buf = render(mesh, small, pose)
    ok = buf.face >= 0
    if not ok.any():
        return np.zeros((cam.height, cam.width), np.uint8)
    normals = mesh.face_normals @ pose.R.T
    rays = np.dstack([*np.moveaxis(pixel_rays(small), -1, 0), np.ones((small.height, small.width))])
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    cosv = np.abs(np.einsum("hwk,hwk->hw", normals[np.maximum(buf.face, 0)], rays))
    ok &= cosv >= params.visibility.min_cos
    ok &= ~depth_edges(buf)
    r = max(1, int(round(0.5 * params.mesh_edge_margin_px)))
    ok = cv2.erode(ok.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2))
    return cv2.resize(ok * 255, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
@pytest.mark.parametrize("sides", [4, 6, 24])
def test_birth_mask_equals_the_per_pixel_form(camera, sides):
    """The birth mask tests the view angle on the object's pixels only, with cached unit rays,
    on the object's box only: the same mask as testing every pixel of the frame — grazing faces
    included (a prism turned edge-on), and the object at the image's border."""
    mesh = closed_prism(sides)
    params = TrackerParams()
    rng = np.random.default_rng(sides)
    grazing = 0
    for k in range(11):
        rvec = rng.normal(0, 1.2, 3) if k else np.array([np.pi / 2, 0.0, 0.0])
        t = np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(18, 40)])
        if k >= 8:  # at the image's border, partly outside it (the mask is worked out on the object's box)
            t[:2] = t[2] * np.array([[0.62, 0.0], [-0.55, 0.45], [0.1, -0.5]][k - 8])
        pose = Pose.from_rvec(rvec, t - Pose.from_rvec(rvec, [0, 0, 0]).R @ mesh.centre)
        fast, plain = birth_mask(mesh, camera, pose, params), _plain_birth_mask(mesh, camera, pose, params)
        np.testing.assert_array_equal(fast, plain)
        assert fast.any()
        grazing += int(((render(mesh, scaled_camera(camera, 0.5), pose).face >= 0).sum() > 0) and (fast == 0).any())
    assert grazing


def test_unit_pixel_rays_are_the_normalised_pixel_rays():
    for cam in (scaled_camera(CAM, 0.5), scaled_camera(CAM_DIST, 0.25)):
        xy = pixel_rays(cam)
        d = np.dstack([xy[..., 0], xy[..., 1], np.ones(xy.shape[:2])])
        d /= np.linalg.norm(d, axis=2, keepdims=True)
        u = unit_pixel_rays(cam)
        np.testing.assert_array_equal(u, d)
        assert not u.flags.writeable and unit_pixel_rays(cam) is u


def test_cached_scaled_cameras_and_face_normals_are_the_computed_ones():
    """``scaled_camera`` and ``face_normals`` remember their results per object: the same values
    as computed afresh, and a new object (even at a reused address) gets its own."""
    from quatrack.viewsets.render import face_normals

    for s in (0.25, 0.5, 1.0):
        a, b = scaled_camera(CAM_DIST, s), CAM_DIST.scaled(s)
        assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == (b.fx, b.fy, b.cx, b.cy, b.width, b.height)
        np.testing.assert_array_equal(a.dist_coeffs, b.dist_coeffs)
        assert scaled_camera(CAM_DIST, s) is a
    for k in range(5):  # cameras and meshes that come and go: never another one's result
        cam = PinholeCamera(400.0 + k, 400.0, 160.0, 120.0, width=320, height=240)
        assert scaled_camera(cam, 0.5).fx == 0.5 * (400.0 + k)
        mesh = closed_prism(4 + k)
        n = face_normals(mesh)
        tri = mesh.vertices[mesh.faces]
        fresh = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        np.testing.assert_array_equal(n, fresh / np.linalg.norm(fresh, axis=1, keepdims=True))
        assert face_normals(mesh) is n and mesh.face_normals is n and not n.flags.writeable
        del cam, mesh


@pytest.mark.parametrize("sides,scale", [(4, 1), (24, 1), (4, 2)])
def test_audit_fit_image_gives_measure_edges_refit(sides, scale):
    """The audit's edge refit on :func:`fit_image`'s smaller gradient crop equals the refit on
    measure_edges' EdgeImage exactly — object in the middle, at the image's border, partly
    outside it, and poses a few per cent / degrees off (the refit moves them); also on an image
    of twice the resolution, whose gradients are read with a wider blur (``gradient_scale``)."""
    from quatrack.recognition.evidence import edge_fit, measure_edges
    from quatrack.recognition.pose import PoseParams
    from quatrack.recognition.tracker.edges import fit_image

    cam = CAM if scale == 1 else CAM.scaled(float(scale))
    mesh = closed_prism(sides)
    pp = PoseParams()
    rng = np.random.default_rng(7 + sides)
    clutter = cv2.GaussianBlur(rng.uniform(0, 255, (480 * scale, 640 * scale)).astype(np.float32), (0, 0), 3.0 * scale)
    moved, compared = 0, 0
    for k in range(14):
        rvec = rng.normal(0, 0.8, 3)
        shift = [(0, 0), (260, 0), (-250, 120), (0, -215), (300, 200), (-290, -10), (30, 230)][k % 7]
        t = np.array([shift[0] / 520.0 * 25, shift[1] / 515.0 * 25, rng.uniform(20, 32)])
        truth = Pose.from_rvec(rvec, t - Pose.from_rvec(rvec, [0, 0, 0]).R @ mesh.centre)
        buf = render(mesh, cam, truth)
        img = np.where(buf.face >= 0, 60.0 + 150.0 * ((buf.face * 7919) % 13) / 12.0, clutter)
        gray = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
        off = Pose.from_rvec(rvec + rng.normal(0, 0.03, 3), t + rng.normal(0, 0.3, 3) - Pose.from_rvec(rvec, [0, 0, 0]).R @ mesh.centre)
        for pose in (truth, off):
            X = mesh.vertices[:: max(1, len(mesh.vertices) // 8)]
            uv = cam.project(truth.apply(X))
            _, image = measure_edges(gray, mesh, cam, pose, pp.edges)
            small = fit_image(gray, mesh, cam, pose, pp.edges, pp.edge_fit_reach)
            if image is None:
                assert small is None
                continue
            assert small.origin == image.origin and small.gx.shape == image.gx.shape
            a = edge_fit(image, mesh, cam, pose, X, uv, pp.edges, pp.edge_fit_reach)
            b = edge_fit(small, mesh, cam, pose, X, uv, pp.edges, pp.edge_fit_reach)
            assert a == b
            compared += 1
            moved += a.samples >= 6 and a.shift > 0.05
    assert compared >= 15 and moved >= 3


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_one_visibility_call_for_both_point_sources(camera):
    """follow_together tests the trained and the mesh-born tracks in one visible_points call:
    each source's visible indices and predicted pixels are those of a call of its own
    (visible_tracks) — sizes 0, 1 and the tracker's usual hundreds, points in front, behind
    faces and off the object."""
    from quatrack.recognition.tracker.points import Tracks
    from quatrack.recognition.tracker.sources import FrameContext, _visible_together, visible_tracks
    from quatrack.tracking.filter import PoseFilter
    from quatrack.tracking.motion import make_motion_model

    class Src:
        def __init__(self, mesh, params, X):
            self.mesh, self.params, self.tracks = mesh, params, Tracks(X, np.zeros((len(X), 2)))

    mesh = closed_prism(6)
    params = TrackerParams()
    rng = np.random.default_rng(3)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    seen = hidden = 0
    for k, (n1, n2) in enumerate([(150, 90), (0, 40), (1, 0), (200, 100), (37, 1)]):
        rvec = rng.normal(0, 1.0, 3)
        t = np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(15, 30)])
        pose = Pose.from_rvec(rvec, t - Pose.from_rvec(rvec, [0, 0, 0]).R @ mesh.centre)
        f = PoseFilter(make_motion_model("ude", **params.motion_noise_params(float(mesh.extent))), params.adjust)
        f.initialize(0.0, pose, np.eye(6) * 1e-4)
        state = f.state
        on = mesh.triangles[rng.integers(0, len(mesh.faces), n1 + n2)]
        w = rng.dirichlet(np.ones(3), n1 + n2)
        X = np.einsum("nk,nkj->nj", w, on)
        X[::7] = rng.uniform(lo, hi, (len(X[::7]), 3))  # inside the object: hidden
        srcs = [Src(mesh, params, X[:n1]), Src(mesh, params, X[n1:])]
        ctx = FrameContext(None, None, None, camera, state)
        together = _visible_together(ctx, srcs, {})
        ctx2 = FrameContext(None, None, None, camera, state)
        for (s, idx, uv), src in zip(together, srcs):
            idx2, uv2 = visible_tracks(mesh, ctx2, src.tracks, params, {})
            assert s is src
            np.testing.assert_array_equal(idx, idx2)
            np.testing.assert_array_equal(uv, uv2)
            seen += len(idx)
            hidden += len(src.tracks) - len(idx)
    assert seen > 100 and hidden > 50


def test_corners_in_the_masks_box_are_the_frames_corners():
    """Mesh points are born on goodFeaturesToTrack's corners of the mask's box only
    (corners_in_mask): the same corners, in the same order, as on the whole frame — masks in
    the middle, at the image's border, tiny and empty."""
    from quatrack.recognition.tracker.mesh_points import corners_in_mask

    rng = np.random.default_rng(11)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640)).astype(np.float32), (0, 0), 1.5)
    gray = np.clip(tex + rng.normal(0, 3, tex.shape), 0, 255).astype(np.uint8)
    found = 0
    for x0, y0, x1, y1 in ((200, 150, 420, 330), (11, 40, 150, 200), (500, 300, 629, 469), (300, 11, 310, 19),
                           (11, 11, 629, 469), (0, 0, 0, 0)):
        mask = np.zeros((480, 640), np.uint8)
        mask[y0:y1, x0:x1] = 255
        cv2.circle(mask, ((x0 + x1) // 2, (y0 + y1) // 2), 20, 0, -1)
        for n, q, d in ((100, 0.01, 10.0), (30, 0.05, 4.0)):
            ref = cv2.goodFeaturesToTrack(gray, n, q, d, mask=mask)
            got = corners_in_mask(gray, mask, n, q, d)
            if ref is None:
                assert got is None
                continue
            np.testing.assert_array_equal(got, ref.reshape(-1, 2).astype(float))
            found += len(got)
    assert found > 200

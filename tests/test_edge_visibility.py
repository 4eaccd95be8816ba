"""Which model edges are visible: recognition's edge evidence (``evidence._edge_samples``) and the
tracker's edge source (``tracker.edges.edge_points``) sample exactly the edges a camera sees.

The truth needs no renderer: on a convex mesh an edge is seen iff one of its two faces faces the
camera. Boxes of three proportions and a hexagonal prism, in mm, cm and m, are viewed from above at grazing to steep
elevations, where a face seen at a grazing angle changes depth fast from pixel to pixel (the
far outline of a flat box once fell to the z-buffer test: bench/RESULTS.md, session 39).
"""

from __future__ import annotations

import numpy as np
import pytest

from quatrack.recognition.evidence import EdgeParams, _edge_samples
from quatrack.recognition.tracker.edges import edge_points
from quatrack.recognition.tracker.params import TrackerParams
from quatrack.recognition.visibility import mesh_edges, sharp_edges, visibility_buffers
from quatrack.testing.zoo import look_at, zoo_camera
from quatrack.tracking.state import initial_state
from quatrack.viewsets.mesh import make_mesh

SHAPES = {  # (trimesh's maker, its arguments), in the unit of the name
    "flat box (mm)": ("box", dict(extents=(240.0, 160.0, 40.0))),
    "cube (m)": ("box", dict(extents=(0.1, 0.1, 0.1))),
    "tall box (cm)": ("box", dict(extents=(6.0, 6.0, 20.0))),
    "hex prism (m)": ("cylinder", dict(radius=0.05, height=0.12, sections=6)),
}


def _mesh(shape: str):
    import trimesh

    maker, kwargs = SHAPES[shape]
    tm = getattr(trimesh.creation, maker)(**kwargs)
    return make_mesh(np.asarray(tm.vertices), np.asarray(tm.faces), shape)


def _seen_edges(mesh, pose, margin: float = 0.05):
    """The mesh's sharp edges (k, 2, 3); whether each is seen (one of its faces faces the camera by
    more than ``margin`` in cosine with the view ray) and whether it is hidden (both face away
    by more than that); an edge with a face edge-on is neither."""
    E = mesh_edges(mesh)
    N = mesh.face_normals
    C = pose.apply(mesh.face_centroids)
    cos = np.einsum("ij,ij->i", N @ pose.R.T, C / np.linalg.norm(C, axis=1, keepdims=True))
    # the faces an edge borders: those whose plane holds both its ends
    on = [np.abs(np.einsum("fj,kfj->kf", N, E[:, i][:, None] - mesh.vertices[mesh.faces[:, 0]][None])) < 1e-6 * mesh.extent
          for i in (0, 1)]
    borders = on[0] & on[1]
    assert np.all(borders.sum(1) >= 2), "every edge lies on two faces' planes"
    seen = (borders & (cos < -margin)[None]).any(axis=1)
    hidden = ~(borders & (cos < margin)[None]).any(axis=1)
    return E, seen, hidden


def _edge_of(X, E):
    """The edge each object point of ``X`` (n, 3) lies on (the nearest segment)."""
    A, B = E[:, 0][None], E[:, 1][None]
    AB = B - A
    s = np.clip(np.einsum("nkj,nkj->nk", X[:, None] - A, AB) / np.einsum("nkj,nkj->nk", AB, AB), 0, 1)
    dist = np.linalg.norm(X[:, None] - (A + s[..., None] * AB), axis=2)
    return np.argmin(dist, axis=1), dist.min(axis=1)


def _views():
    for name in SHAPES:
        for elevation in (8.0, 20.0, 45.0, 70.0):
            for azimuth in (15.0, 50.0, 130.0):
                yield pytest.param(name, elevation, azimuth, id=f"{name}-el{elevation:g}-az{azimuth:g}")


@pytest.mark.parametrize("shape,elevation,azimuth", list(_views()))
def test_edges_are_sampled_where_the_camera_sees_them(shape, elevation, azimuth):
    mesh = _mesh(shape)
    camera = zoo_camera()
    diameter = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    d = camera.fx * diameter / (0.4 * camera.width)  # the box fills 40 % of the image's width
    a, e = np.radians(azimuth), np.radians(elevation)
    pose = look_at(d * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]), np.zeros(3))
    E, seen, hidden = _seen_edges(mesh, pose)
    uv_ends = camera.project(pose.apply(E.reshape(-1, 3))).reshape(-1, 2, 2)
    length = np.linalg.norm(uv_ends[:, 1] - uv_ends[:, 0], axis=1)

    ep = EdgeParams()
    _, _, _, X_rec = _edge_samples(mesh, camera, pose, ep, None, 0.5)
    state = initial_state(0.0, pose.t, pose.q_wxyz, np.eye(6) * 1e-6)
    tp = TrackerParams()
    E_trk, F_trk = sharp_edges(mesh, tp.edge_crease_deg)
    X_trk, _, _ = edge_points(mesh, E_trk, camera, state, tp, visibility_buffers(mesh, camera, pose, tp.visibility), F_trk)

    for X, step in ((X_rec, ep.step_px), (X_trk, tp.edge_step_px)):
        k, dist = _edge_of(X, E)
        assert np.all(dist < 1e-6 * diameter)
        # no sample on an edge nobody sees
        assert not hidden[k].any(), f"samples on hidden edges {sorted(set(k[hidden[k]].tolist()))}"
        # every edge seen, long enough to hold a few samples, holds most of them
        counts = np.bincount(k, minlength=len(E))
        long_ = seen & (length >= 4 * step)
        expected = np.ceil(length / step)
        assert np.all(counts[long_] >= 0.7 * expected[long_] - 1), (counts[long_], expected[long_])


def test_the_nearest_depth_round_a_sample_is_the_3x3_minimum_of_the_buffer():
    """``edge_samples_visible`` reads the nearest surface round each sample from its 3×3
    neighbourhood of the reduced z-buffer (session 41); it must equal the buffer eroded by a 3×3
    minimum, borders included, inf and NaN meaning no surface — what it computed before."""
    import cv2

    from quatrack.recognition.visibility import edge_samples_visible

    rng = np.random.default_rng(41)

    class Buffer:
        pass

    for trial in range(20):
        dh, dw = rng.integers(3, 30, size=2)
        depth = rng.uniform(1.0, 2.0, size=(dh, dw)).astype(np.float32)
        depth[rng.random((dh, dw)) < 0.3] = np.inf
        depth[rng.random((dh, dw)) < 0.05] = np.nan
        zb = Buffer()
        zb.depth, zb.face = depth, np.full((dh, dw), -1)  # no face shown: the depth test alone decides
        w, h = int(dw) * 4, int(dh) * 4
        n = 200
        uv = np.column_stack([rng.uniform(-1, w, n), rng.uniform(-1, h, n)])  # borders and beyond
        z = rng.uniform(0.9, 2.1, n)
        tol = 0.05
        got = edge_samples_visible(zb, uv, z, np.zeros((n, 2), int), np.zeros(1, int), (w, h), tol)
        near = cv2.erode(np.where(np.isfinite(depth), depth, np.inf).astype(np.float32), np.ones((3, 3), np.uint8))
        ui = np.clip(np.rint((uv[:, 0] + 0.5) * dw / w - 0.5).astype(int), 0, dw - 1)
        vi = np.clip(np.rint((uv[:, 1] + 0.5) * dh / h - 0.5).astype(int), 0, dh - 1)
        want = z <= near[vi, ui] + tol
        assert np.array_equal(got, want), trial
        assert 0 < want.sum() < n  # both outcomes occur

"""Simulated clicks on rendered photos: a user registering a photo clicks the mesh's corners it
shows (:mod:`quatrack.viewsets.register`); here their true pixels, perturbed by seeded noise."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import Mesh
from quatrack.viewsets.register import PointPairs
from quatrack.viewsets.render import render


def visible_vertices(mesh: Mesh, camera: PinholeCamera, pose: Pose, margin: int = 2) -> np.ndarray:
    """Indices of the mesh's vertices the photo shows: inside the image (``margin`` px from its
    border) and not hidden by the object (no nearer surface within 2 px of the vertex's pixel)."""
    rb = render(mesh, camera, pose)
    Xc = mesh.vertices @ pose.R.T + pose.t
    uv = camera.project(Xc)
    out = []
    for i, (p, z) in enumerate(zip(uv, Xc[:, 2])):
        x, y = int(round(p[0])), int(round(p[1]))
        if margin <= x < camera.width - margin and margin <= y < camera.height - margin:
            d = rb.depth[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3]
            if np.isfinite(d).any() and z <= d[np.isfinite(d)].min() * 1.01:
                out.append(i)
    return np.array(out, int)


def zoo_clicks(name: str, folder: str | Path, seed: int, noise_px: float = 2.0, most: int = 8, grey: bool = False):
    """A zoo object's training photo (:func:`quatrack.testing.zoo.write_spec`, one view, ``seed``)
    and up to ``most`` of its visible corners clicked with Gaussian noise of ``noise_px`` per axis
    (seeded by ``100 + seed``). Returns ``(spec, view, mesh, PointPairs)``; ``view.pose`` is the truth."""
    from quatrack.viewsets.mesh import load_mesh
    from quatrack.viewsets.spec import load_spec

    from . import zoo as Z

    spec = load_spec(Z.write_spec(name, Path(folder), n_views=1, seed=seed, grey=grey))
    view = spec.views[0]
    mesh = load_mesh(spec.mesh_path)
    rng = np.random.default_rng(100 + seed)
    vis = visible_vertices(mesh, view.camera, view.pose)
    if len(vis) > most:
        vis = rng.choice(vis, most, replace=False)
    uv = view.camera.project(mesh.vertices[vis] @ view.pose.R.T + view.pose.t)
    return spec, view, mesh, PointPairs(mesh.vertices[vis], uv + rng.normal(0, noise_px, uv.shape))

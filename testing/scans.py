"""A scan's mesh of a known object, made from its CAD mesh: finely subdivided, optionally jittered.

Scanners and photogrammetry give 10⁴–10⁶ triangles, each a plane of its own, their vertices a
little off the true surface; the zoo's and the example's meshes have 12–96 faces. The tests and
``quatrack bench scan-mesh`` (session 57) make one from a CAD mesh, so its true surface is known.
"""

from __future__ import annotations

import numpy as np

from quatrack.viewsets.mesh import Mesh, make_mesh


def scanned(mesh: Mesh, subdivisions: int, jitter: float = 0.0, seed: int = 0) -> Mesh:
    """``mesh`` with every triangle split into four ``subdivisions`` times (trimesh's
    ``subdivide``: 4^k × the faces, the same surface) and, with ``jitter`` > 0, every vertex moved
    by a Gaussian of σ = ``jitter`` × the mesh's extent per coordinate (seeded by ``seed``).

    >>> box = make_mesh(np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1.0)]),
    ...                 np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
    ...                           [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]))
    >>> fine, rough = scanned(box, 2), scanned(box, 2, jitter=0.001)
    >>> len(fine.faces), bool(np.all((fine.vertices == 0) | (fine.vertices == 1) | (fine.vertices == 0.5)
    ...                              | (fine.vertices == 0.25) | (fine.vertices == 0.75)))
    (192, True)
    >>> bool(0 < np.abs(rough.vertices - fine.vertices).max() < 0.01)
    True
    """
    import trimesh

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    for _ in range(subdivisions):
        tm = tm.subdivide()
    V = np.asarray(tm.vertices, float)
    if jitter > 0:
        V = V + np.random.default_rng(seed).normal(0.0, jitter * mesh.extent, V.shape)
    return make_mesh(V, np.asarray(tm.faces, np.int64))

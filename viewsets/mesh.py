"""Triangle meshes (PLY/OBJ via trimesh) and the planar groups used to texture novel views."""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from .errors import SpecError


@dataclass(frozen=True, eq=False)
class Mesh:
    """Vertices (n, 3) float64 in mesh units and triangles (m, 3) int32 (indices into vertices).

    Meshes compare by value (``==``: the same vertices and faces, number for number, in order)
    and hash alike when equal (by their arrays' shapes: a mesh's arrays are not changed after it
    is made). (The dataclass's own ``==`` raised "the truth value of an array ... is ambiguous",
    and ``hash`` "unhashable type: 'numpy.ndarray'".)

    >>> tri = make_mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2]]))
    >>> tri == make_mesh(tri.vertices.copy(), tri.faces.copy()), tri == make_mesh(tri.vertices, tri.faces[:, ::-1])
    (True, False)
    >>> len({tri, make_mesh(tri.vertices.copy(), tri.faces.copy())})
    1
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Mesh):
            return NotImplemented
        return self is other or (np.shape(self.vertices) == np.shape(other.vertices)
                                  and np.shape(self.faces) == np.shape(other.faces)
                                  and np.array_equal(self.faces, other.faces)
                                  and np.array_equal(self.vertices, other.vertices))

    def __hash__(self) -> int:
        return hash((np.shape(self.vertices), np.shape(self.faces)))

    @property
    def triangles(self) -> np.ndarray:
        """(m, 3, 3): the corners of each triangle."""
        return self.vertices[self.faces]

    @cached_property
    def face_normals(self) -> np.ndarray:
        """(m, 3) unit normals (right-hand order of the corners), read-only. Computed once per
        mesh and kept on it (the tracker asks for them several times a frame; 0.02–0.2 ms each
        afresh): a mesh's arrays are not changed after it is made (:func:`make_mesh`)."""
        tri = self.triangles
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        n.setflags(write=False)
        return n

    @cached_property
    def face_centroids(self) -> np.ndarray:
        """(m, 3) the mean of each triangle's corners, read-only, computed once per mesh (which
        faces a pose turns towards the camera is asked per reference and per frame:
        :mod:`quatrack.recognition.appearance`, :mod:`quatrack.recognition.evidence`).

        >>> tri = make_mesh(np.array([[0, 0, 0], [3, 0, 0], [0, 3, 0.0]]), np.array([[0, 1, 2]]))
        >>> tri.face_centroids.tolist(), tri.face_centroids.flags.writeable
        ([[1.0, 1.0, 0.0]], False)
        """
        c = self.triangles.mean(axis=1)
        c.setflags(write=False)
        return c

    @cached_property
    def run_time(self) -> "Mesh":
        """The mesh recognition and tracking work with: this one, or, when it has more than
        ``RUN_TIME_MAX_FACES`` faces (a scan, a fine CAD export), its quadric decimation to at
        most that many (:func:`simplified`), computed once per mesh. Why: the run time's geometry
        — renders for the checks, silhouettes and edges every frame — costs in proportion to the
        faces, and a scan's jitter makes every facet a crease: a 49 000-face scan of the cookie
        box took ~120 ms a tracking step (12 faces: 10 ms) and about a second a ``locate``.
        Training lifts the photos' keypoints onto the full mesh, which the stored model keeps, and
        renders its synthetic views on this one (viewsets/train.py: ``_run_task``).

        >>> box = make_mesh(np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1.0)]),
        ...                 np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
        ...                           [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]))
        >>> box.run_time is box
        True
        """
        if len(self.faces) <= RUN_TIME_MAX_FACES:
            return self
        return simplified(self, RUN_TIME_MAX_FACES)

    @cached_property
    def plane_ids(self) -> np.ndarray:
        """(m,) the planar group of each triangle (:func:`planar_groups`: triangles on one plane
        share an id), read-only, computed once per mesh (which faces an edge sample borders is
        asked per frame: :func:`quatrack.recognition.visibility.edge_samples_visible`).

        >>> square_and_wall = make_mesh(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1.0]]),
        ...                             np.array([[0, 1, 2], [0, 2, 3], [0, 4, 1]]))
        >>> square_and_wall.plane_ids.tolist()
        [0, 0, 1]
        """
        g = planar_groups(self)
        g.setflags(write=False)
        return g

    @cached_property
    def edge_faces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The mesh's unique edges (k, 2) (vertex indices, the smaller first), the faces on their
        two sides (k, 2) (−1 where an edge has one face, the mesh's boundary; an edge of more than
        two faces keeps its first two) and how many faces share each edge (k,); read-only,
        computed once per mesh (silhouettes, creases and wireframes are all read from it).

        Faces meet where their corners lie at the same position, whatever the vertices' indices
        (an edge names the first vertex at each of its ends): an STL file stores each triangle's
        corners apart, and a texture seam splits vertices; by index every edge of an STL box was
        the boundary, its faces' diagonals among them — 36 "sharp" edges for its 12, sampled by
        the edge evidence and the tracker where the image has no edge.

        >>> tetra = make_mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
        ...                   np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
        >>> edges, faces, counts = tetra.edge_faces
        >>> len(edges), bool((faces >= 0).all()), counts.tolist()
        (6, True, [2, 2, 2, 2, 2, 2])
        >>> apart = make_mesh(tetra.triangles.reshape(-1, 3), np.arange(12).reshape(4, 3))  # as in an STL file
        >>> apart.edge_faces[2].tolist()
        [2, 2, 2, 2, 2, 2]
        """
        F = first_at_position(self.vertices)[np.asarray(self.faces)].astype(np.asarray(self.faces).dtype, copy=False)
        e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
        owner = np.tile(np.arange(len(F)), 3)
        key = np.sort(e, axis=1)
        order = np.lexsort((key[:, 1], key[:, 0]))
        key, owner = key[order], owner[order]
        new = np.r_[True, np.any(key[1:] != key[:-1], axis=1)]
        starts = np.flatnonzero(new)
        counts = np.diff(np.r_[starts, len(key)])
        faces = np.full((len(starts), 2), -1)
        faces[:, 0] = owner[starts]
        two = counts >= 2
        faces[two, 1] = owner[starts[two] + 1]
        out = (key[starts], faces, counts)
        for a in out:
            a.setflags(write=False)
        return out

    @cached_property
    def closed_outward(self) -> bool:
        """Whether the surface is closed with every normal pointing out: each edge (vertices
        merged by position, so seams split for texture coordinates do not open it) is shared by
        exactly two faces that run along it in opposite directions, and the signed volume
        ``Σ V₀·(V₁ × V₂) / 6`` is positive. Then, seen from outside, a face turned away from the
        camera is always hidden behind one turned towards it, and a z-buffer need not test it
        (:func:`~.render.render`).

        >>> tetra = make_mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
        ...                   np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
        >>> tetra.closed_outward, make_mesh(tetra.vertices, tetra.faces[:, ::-1]).closed_outward
        (True, False)
        """
        _, same = np.unique(self.vertices, axis=0, return_inverse=True)
        F = same.reshape(-1)[self.faces]
        directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
        # closed and consistently wound: every directed edge once, and its reverse once
        once = np.unique(directed, axis=0)
        if len(once) != len(directed) or not np.array_equal(once, np.unique(directed[:, ::-1], axis=0)):
            return False
        tri = self.triangles
        volume = float(np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))) / 6.0
        return volume > 0.0

    @property
    def centre(self) -> np.ndarray:
        """Centre of the bounding box: novel views rotate about it."""
        return 0.5 * (self.vertices.min(axis=0) + self.vertices.max(axis=0))

    @property
    def extent(self) -> float:
        """Diagonal of the bounding box, the mesh's length scale."""
        return float(np.linalg.norm(self.vertices.max(axis=0) - self.vertices.min(axis=0)))


def make_mesh(vertices: np.ndarray, faces: np.ndarray, where: str = "mesh") -> Mesh:
    """Check and wrap arrays: finite vertices, valid indices, no zero-area triangles."""
    # (a Trimesh for vertices was float()'s TypeError; vertices or faces of other than 3 columns were
    # reshaped into other points and triangles when their size allowed, else numpy's reshape error)
    try:
        V = np.asarray(vertices, dtype=float)
    except (TypeError, ValueError):
        raise SpecError(f"{where}: vertices must be an (n, 3) array of numbers (a trimesh's .vertices), "
                        f"got {type(vertices).__name__}") from None
    try:
        F = np.asarray(faces)
    except ValueError:  # (rows of different lengths: numpy's "inhomogeneous shape")
        F = np.asarray(faces, dtype=object)
    if V.ndim != 2 or V.shape[1] != 3:
        raise SpecError(f"{where}: vertices must be an (n, 3) array of numbers, got shape {V.shape}")
    if F.size and (F.ndim != 2 or F.shape[1] != 3):
        raise SpecError(f"{where}: faces must be an (m, 3) array of vertex indices (triangles), got shape {F.shape}")
    # (whole numbers only: 1.5 was cut to 1, NaN became index -2147483648 (IndexError), strings
    # numpy's UFuncTypeError; integral floats, as a text file's loadtxt gives them, are taken)
    if F.size and F.dtype.kind not in "iu":
        whole = F.dtype.kind == "f" and np.isfinite(F) & (F == np.round(F))
        if F.dtype.kind != "f" or not whole.all():
            got = f"{float(F[~whole][0]):g}" if F.dtype.kind == "f" else {
                "U": "text", "S": "text", "b": "True/False values", "c": "complex numbers"}.get(F.dtype.kind, "objects")
            raise SpecError(f"{where}: faces must be whole vertex indices, got {got}")
    F = F.reshape(-1, 3)
    if F.size == 0:
        raise SpecError(f"{where}: the mesh has no faces (a point cloud cannot be rendered)")
    if not np.all(np.isfinite(V)):
        raise SpecError(f"{where}: the mesh has non-finite vertex coordinates")
    if F.min() < 0 or F.max() >= len(V):
        raise SpecError(f"{where}: face indices out of range")
    F = F.astype(np.int32)
    tri = V[F]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    scale = max(float(np.ptp(V, axis=0).max()), 1e-12)
    keep = area2 > 1e-12 * scale * scale
    if not np.any(keep):
        raise SpecError(f"{where}: every face of the mesh has zero area")
    return Mesh(V, F[keep])


# meshes with more faces are decimated to this many for recognition and tracking (Mesh.run_time)
RUN_TIME_MAX_FACES = 5000


def simplified(mesh: Mesh, faces: int) -> Mesh:
    """``mesh`` decimated to about ``faces`` triangles by quadric error metrics (Garland &
    Heckbert 1997, the fast-simplification package: each edge collapse places its vertex where
    the squared distances to the planes it merges are least, so flat and sharp parts keep their
    shape while a scan's jitter averages out), in the same frame and units, faces wound outwards;
    the same in any unit (a mesh scaled by s gives its decimation scaled by s).
    First every collapse that changes nothing (``lossless``: a finely tessellated flat face
    becomes two triangles again), then, if still more than ``faces``, the least costly ones.

    >>> import trimesh
    >>> tm = trimesh.creation.icosphere(subdivisions=4, radius=2.0)
    >>> s = simplified(make_mesh(tm.vertices, tm.faces), 500)
    >>> len(tm.faces), len(s.faces) <= 500, bool(np.allclose(np.linalg.norm(s.vertices, axis=1), 2.0, atol=0.05))
    (5120, True, True)
    """
    import fast_simplification

    V, F = joined(mesh.vertices, mesh.faces)
    # in a frame of unit size (the bounding box's centre at 0, its diagonal 1), scaled back after:
    # the package's thresholds are absolute, and one scan in mm, cm and m was decimated to other
    # facets, other planar groups, other locate results
    centre, size = mesh.centre, max(mesh.extent, 1e-300)
    V = (np.asarray(V, np.float64) - centre) / size
    V, F = fast_simplification.simplify(V, np.asarray(F, np.int32), lossless=True)
    if len(F) > faces:
        V, F = fast_simplification.simplify(np.asarray(V, np.float64), np.asarray(F, np.int32),
                                            target_reduction=1.0 - faces / len(F))
    V2, F2 = np.asarray(V, float) * size + centre, np.asarray(F)
    return make_mesh(V2, outward_faces(V2, np.asarray(F2, np.int64)), "simplified mesh")


def _trimesh():
    """The trimesh module, imported with Ctrl-C held until the import ends. trimesh wraps its
    optional imports (scipy, seconds on a cold disk) in ``except BaseException``: a Ctrl-C
    there was swallowed, and training went on to replace the model the user meant to keep. A
    process that ignores Ctrl-C (a script's ``quatrack train … &``, a training worker) keeps
    ignoring it: the held one ended such a run with exit 130 when it came during the import."""
    import signal
    import sys
    import threading

    if ("trimesh" in sys.modules or threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is signal.SIG_IGN):
        import trimesh

        return trimesh
    pressed = []
    previous = signal.signal(signal.SIGINT, lambda *_: pressed.append(True))
    try:
        import trimesh
    finally:
        signal.signal(signal.SIGINT, previous)
    if pressed:
        raise KeyboardInterrupt
    return trimesh


# the mesh files load_mesh reads (trimesh's formats with faces), as its messages name them
MESH_FORMATS = "PLY, OBJ, STL, OFF, GLB or glTF"


def first_at_position(vertices: np.ndarray) -> np.ndarray:
    """(n,) for each vertex the index of the first vertex at its position (itself where no
    earlier one shares it): faces joined by position, not by index.

    >>> first_at_position(np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0.0], [1, 0, 0]])).tolist()
    [0, 1, 0, 1]
    """
    V = np.asarray(vertices)
    order = np.lexsort(V.T[::-1])  # (stable: the first of equal rows keeps the smallest index)
    new = np.r_[True, np.any(V[order][1:] != V[order][:-1], axis=1)]
    first = np.empty(len(V), np.int64)
    first[order] = order[new][np.cumsum(new) - 1]
    return first


def joined(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with its vertices at one position made one (the first of them, in order; the
    arrays themselves where none share a position). Why: decimation (:func:`simplified`) collapses
    edges between faces that share vertices; an STL scan's triangles, stored apart, share none,
    and its run-time mesh was 5 000 of its triangles kept at random — a surface full of holes.

    >>> V, F = joined(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]),
    ...               np.array([[0, 1, 2], [3, 5, 4]]))
    >>> len(V), F.tolist()
    (4, [[0, 1, 2], [1, 3, 2]])
    """
    first = first_at_position(vertices)
    if np.array_equal(first, np.arange(len(first))):
        return vertices, faces
    used = np.unique(first)
    return np.asarray(vertices)[used], np.searchsorted(used, first[np.asarray(faces)]).astype(np.asarray(faces).dtype)


def repeated_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Mask (m,) of the faces that repeat an earlier face: the same three corners, in any order
    (reversed too), vertices joined by position (an STL file stores each triangle's corners apart),
    as in :attr:`Mesh.closed_outward`. All False for arrays that are no valid mesh (left to
    :func:`make_mesh` to refuse).

    Why they are dropped on load: an edge of a repeated triangle has three or four faces, so
    :attr:`Mesh.edge_faces` pairs a face with its own copy — the crease it shares with its
    neighbour is lost to the edge evidence (a copy wound the same way: no crease, no silhouette)
    or the triangle's diagonal across a flat side becomes an edge the image is asked to show (one
    wound the other way: a "silhouette" at every pose); the tracker's sharp edges and the
    wireframe gain the diagonal; and the surface is no longer closed (no back-face culling).

    >>> tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    >>> repeated_faces(tri, np.array([[0, 1, 2], [2, 1, 0], [1, 2, 0]])).tolist()
    [False, True, True]
    """
    V, F = np.asarray(vertices), np.asarray(faces)
    out = np.zeros(len(F) if F.ndim else 0, bool)
    if (V.ndim != 2 or V.shape[1:] != (3,) or F.ndim != 2 or F.shape[1:] != (3,) or not len(F)
            or not np.issubdtype(F.dtype, np.integer) or F.min() < 0 or F.max() >= len(V)):
        return out
    # (on sorted keys, not np.unique(axis=0): 0.35 s → 0.07 s for a 330 000-face mesh)
    corners = np.sort(first_at_position(V)[F], axis=1)
    n = len(V)
    if n < 2**21:  # one int64 per triangle
        _, first = np.unique((corners[:, 0] * n + corners[:, 1]) * n + corners[:, 2], return_index=True)
    else:
        _, first = np.unique(corners, axis=0, return_index=True)
    out[:] = True
    out[first] = False
    return out


def load_mesh(path: str | Path, warn=None) -> Mesh:
    """Load a PLY or OBJ mesh (polygons are triangulated by trimesh; also STL, OFF, GLB/glTF);
    faces are required. ``warn`` (optional) is told what of the file is not used or is combined:
    its texture or colours (training takes the object's look from the photos alone), and the
    meshes of a scene merged into one object (:func:`mesh_notes`).

    Faces that repeat another (:func:`repeated_faces`) and faces of zero area are dropped, with one
    warning that counts them (to ``warn``; without it, a :class:`UserWarning`)."""
    trimesh = _trimesh()

    path = Path(path)
    if path.is_dir():  # (was "mesh file not found" of a folder the user sees right there)
        raise SpecError(f"{path}: a folder, not a mesh file (name the mesh file in it)")
    if not path.is_file():
        raise SpecError(f"{path}: mesh file not found")
    _check_file(path)
    obj = _obj_text_resolved(path) if path.suffix.lower() == ".obj" else None

    def read(**kw):  # (an OBJ whose relative indices were resolved is read from its new text)
        if obj is None:
            return trimesh.load(str(path), process=False, **kw)
        return trimesh.load(io.BytesIO(obj), file_type="obj", process=False,
                            resolver=trimesh.resolvers.FilePathResolver(str(path)), **kw)

    try:
        loaded = read()
        notes = mesh_notes(loaded, path) if warn is not None else []
        bodies = 1
        if isinstance(loaded, trimesh.Scene):  # e.g. an OBJ with several objects: merge them
            bodies = sum(len(getattr(g, "faces", ())) > 0 for g in loaded.geometry.values())
            loaded = read(force="mesh")
    except NotImplementedError:  # (trimesh's "file_type 'png' not supported": a photo named as the mesh)
        raise SpecError(f"{path}: not a mesh file format quatrack reads ({path.suffix or 'no extension'}; "
                        f"use {MESH_FORMATS})") from None
    except Exception as exc:  # trimesh raises many types on malformed files
        if isinstance(exc, IndexError) and path.suffix.lower() == ".obj":
            _obj_text_resolved(path, check=True)  # (names the face and the vertex it misses)
        raise SpecError(f"{path}: cannot read mesh ({exc.__class__.__name__}: {exc})") from None
    faces = getattr(loaded, "faces", None)
    vertices = getattr(loaded, "vertices", None)
    if vertices is None or len(vertices) == 0:
        raise SpecError(f"{path}: the mesh has no vertices")
    if faces is None or len(faces) == 0:
        raise SpecError(f"{path}: the mesh has no faces (a point cloud cannot be rendered)")
    for note in notes:  # (told only of a mesh that is used: a refused point cloud's colours were warned of first)
        warn(note)
    vertices, faces = np.asarray(vertices), np.asarray(faces)
    repeated = repeated_faces(vertices, faces)
    if repeated.any():  # (before winding: a copy wound the other way makes the surface one-sided)
        faces = faces[~repeated]
    walls = inner_walls(vertices, faces) if bodies > 1 else np.zeros(len(faces), bool)
    if walls.any() and not walls.all():
        faces = faces[~walls]
    mesh = make_mesh(vertices, outward_faces(vertices, faces), str(path))
    r, z, w = int(repeated.sum()), len(faces) - len(mesh.faces), int(walls.sum()) if not walls.all() else 0
    split = (r or z) and _polygons_split(path, loaded, obj)
    dropped = [f"{r} repeated face{'s' if r != 1 else ''}"
               + ("" if split else " (a triangle given again, in any corner order)")] if r else []
    dropped += [f"{z} face{'s' if z != 1 else ''} of zero area"] if z else []
    dropped += [f"{w} face{'s' if w != 1 else ''} where its meshes touch (inside the object)"] if w else []
    if dropped:  # (of a file of polygons, what trimesh's triangulation made: not the file's own triangles)
        _tell(warn, f"{path}: dropped {' and '.join(dropped)}" + (" after triangulating its polygons" if split else ""))
    # vertices no face uses (an exporter's leftovers, a CAD file's origin point) are dropped: far
    # off, one moved the bounding box's centre, about which the synthetic views turn the object,
    # out of the object (each kept no keypoint) and its extent, the mesh's length scale
    used, faces = np.unique(mesh.faces, return_inverse=True)
    if len(used) == len(mesh.vertices):
        return mesh
    return Mesh(mesh.vertices[used], faces.reshape(mesh.faces.shape).astype(np.int32))


# an OBJ face line giving a negative (relative) index
_OBJ_RELATIVE = re.compile(rb"^[ \t]*f[ \t][^\n]*-", re.M)


def _obj_text_resolved(path: Path, check: bool = False) -> bytes | None:
    """The OBJ file's text with its relative face indices (``f -3 -2 -1``: the last three
    vertices given so far) made absolute, or None when it has none (and ``check`` is not asked).
    Why: trimesh 5.2 counts them back from the file's last vertex, not from the face's line; a
    file giving three vertices and then a face, again and again (valid OBJ, as some exporters
    write it), was read as one triangle repeated, and trained as a one-triangle model.

    A face naming a vertex the file does not give raises SpecError ``face N refers to vertex I
    of V`` (a relative index: of the V given before it); ``check`` reads every face for it (after
    trimesh's IndexError, ``index 98 is out of bounds``, which named neither)."""
    data = path.read_bytes()
    if not check and not _OBJ_RELATIVE.search(data):
        return None
    lines = data.split(b"\n")
    total = {b"v": 0, b"vt": 0, b"vn": 0}
    for line in lines:
        words = line.split(None, 1)
        if words and words[0] in total:
            total[words[0]] += 1
    given = dict.fromkeys(total, 0)
    face = 0
    for k, line in enumerate(lines):
        words = line.split()
        if not words:
            continue
        if words[0] in given:
            given[words[0]] += 1
        elif words[0] == b"f":
            face += 1
            corners = []
            for word in words[1:]:
                parts = word.split(b"/")
                for j, (part, kind) in enumerate(zip(parts, (b"v", b"vt", b"vn"))):
                    if not part.lstrip(b"-").isdigit():
                        continue
                    index = int(part)
                    if index < 0:
                        if -index > given[kind]:
                            raise SpecError(f"{path}: face {face} refers to vertex {index} of the {given[kind]} "
                                            f"given before it" if kind == b"v" else
                                            f"{path}: face {face} refers to {kind.decode()} {index} of the "
                                            f"{given[kind]} given before it")
                        parts[j] = b"%d" % (given[kind] + 1 + index)
                    elif not 0 < index <= total[kind]:
                        raise SpecError(f"{path}: face {face} refers to vertex {index} of {total[kind]}"
                                        if kind == b"v" else
                                        f"{path}: face {face} refers to {kind.decode()} {index} of {total[kind]}")
                corners.append(b"/".join(parts))
            lines[k] = b"f " + b" ".join(corners)
    return b"\n".join(lines)


# the mesh formats by extension, as the messages name them
_FORMAT_OF_SUFFIX = {".ply": "PLY", ".obj": "OBJ", ".stl": "STL", ".off": "OFF", ".glb": "GLB", ".gltf": "glTF"}
# an OBJ line's first word (the first such line after comments tells an OBJ file)
_OBJ_WORDS = {b"v", b"vt", b"vn", b"f", b"o", b"g", b"s", b"mtllib", b"usemtl", b"l", b"p"}


def _content_format(head: bytes, size: int) -> str | None:
    r"""The mesh format a file's first bytes (``head``) and its size show, or None: the magic of
    PLY (``ply``), GLB (``glTF``), OFF (``OFF``, ``COFF``, ...), an ASCII STL (``solid``), a
    binary STL's length (84 bytes and 50 a triangle, as its header counts them; checked first:
    some binary STL headers begin with ``solid``), a glTF's JSON, an OBJ's keywords.

    >>> obj = b"# made by hand\nv 0 0 0"
    >>> _content_format(b"ply\nformat ascii 1.0", 100), _content_format(obj, len(obj))
    ('PLY', 'OBJ')
    """
    if head.startswith(b"ply"):
        return "PLY"
    if head.startswith(b"glTF"):
        return "GLB"
    if size >= 84 and len(head) >= 84 and 84 + 50 * int.from_bytes(head[80:84], "little") == size:
        return "STL"
    text = head.lstrip()
    if text.startswith(b"solid"):
        return "STL"
    if re.match(rb"(ST)?C?N?4?n?OFF\s", text):
        return "OFF"
    if text.startswith(b"{"):
        return "glTF"
    lines = text.split(b"\n")
    for line in lines[:-1] if len(head) < size else lines:  # (whole lines only)
        words = line.split(None, 1)
        if words and not words[0].startswith(b"#"):
            return "OBJ" if words[0] in _OBJ_WORDS else None
    return None


def _check_file(path: Path) -> None:
    """Refuse, with its cause, a mesh file trimesh would misread or fail on with a message that
    names none (``the mesh has no vertices``, ``Not a ply file!``, ``gltf_buffer_0.bin``): an
    empty file, a file whose content is another format than its extension says, a binary STL cut
    short, a glTF whose buffer file is missing. Files of other extensions are left to trimesh."""
    said = _FORMAT_OF_SUFFIX.get(path.suffix.lower())
    size = path.stat().st_size
    if size == 0:
        raise SpecError(f"{path}: the file is empty (0 bytes)")
    if said is None:
        return
    with open(path, "rb") as fh:
        head = fh.read(4096)
    seen = _content_format(head, size)
    if seen is not None and seen != said:
        suffix = {v: k for k, v in _FORMAT_OF_SUFFIX.items()}[seen]
        raise SpecError(f"{path}: its content looks like {seen}, not {said} as its extension says "
                        f"(rename it to {suffix})")
    if said == "STL" and seen is None:
        if size < 84:
            raise SpecError(f"{path}: too short for an STL file ({size} bytes; a binary STL's header alone is 84)")
        n = int.from_bytes(head[80:84], "little")
        raise SpecError(f"{path}: not a whole binary STL file: its header counts {n} triangles, "
                        f"{84 + 50 * n} bytes, the file has {size} (cut short?)")
    if said == "glTF":
        import json
        from urllib.parse import unquote

        try:
            buffers = json.loads(path.read_bytes()).get("buffers", [])
            uris = [b.get("uri") for b in buffers if isinstance(b, dict)]
        except (ValueError, AttributeError):
            return  # (not JSON: trimesh's message)
        for uri in uris:
            if isinstance(uri, str) and not uri.startswith("data:") and not (path.parent / unquote(uri)).is_file():
                raise SpecError(f"{path}: the glTF's buffer file {uri} is missing beside it")


def inner_walls(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Mask (m,) of the faces inside an object made of several bodies that touch: on one plane,
    faces turned one way and faces turned the other covering the same region (the same area and
    the same outline, corners joined by position) — where two halves of a box meet, each half's
    side. Why they are dropped: the seam round them had four faces on each edge, a sharp edge of
    the model that the photo does not show (lowering the edge agreement), and the surface was not
    closed. Planes whose two sides do not match exactly (bodies that only partly touch) are kept.

    >>> half = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    >>> inner_walls(np.r_[half, half], np.array([[0, 1, 2], [3, 5, 4]])).tolist()
    [True, True]
    """
    V, F = np.asarray(vertices, float), np.asarray(faces)
    out = np.zeros(len(F), bool)
    if len(F) < 2:
        return out
    tri = V[F]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    n = cross / np.maximum(area, 1e-300)[:, None]
    lead = n[np.arange(len(n)), np.argmax(np.abs(n) > 1e-6, axis=1)]
    sign = np.where(lead < 0, -1, 1)
    size = max(float(np.ptp(V, axis=0).max()), 1e-300)
    key = np.round(np.column_stack([n * sign[:, None], np.einsum("ij,ij->i", n, tri[:, 0]) * sign / size]), 6)
    _, plane = np.unique(key, axis=0, return_inverse=True)
    plane = plane.reshape(-1)
    both = np.intersect1d(plane[sign > 0], plane[sign < 0])
    at = first_at_position(V)[F]

    def outline(mask):  # the edges of these faces that only one of them has, by position
        e = np.sort(np.concatenate([at[mask][:, [0, 1]], at[mask][:, [1, 2]], at[mask][:, [2, 0]]]), axis=1)
        edges, count = np.unique(e, axis=0, return_counts=True)
        return edges[count == 1]

    for p in both:
        up, down = (plane == p) & (sign > 0), (plane == p) & (sign < 0)
        if (np.isclose(area[up].sum(), area[down].sum(), rtol=1e-9, atol=0)
                and np.array_equal(outline(up), outline(down))):
            out |= up | down
    return out


def _polygons_split(path: Path, loaded, obj: bytes | None) -> bool:
    """Whether trimesh split polygons of the file into triangles: it gave more faces than the file
    has (PLY: its face element's count; OBJ: its ``f`` lines; OFF: its header's count). Why: its
    triangulation fans a polygon out from one corner, and a polygon with corners on its sides (an
    8-corner face of a box with its edges' midpoints) gives triangles of zero area and repeated
    ones; the warning that dropped them blamed the file for triangles it does not hold."""
    suffix = path.suffix.lower()
    given = None
    try:
        if suffix == ".ply":
            given = loaded.metadata["_ply_raw"]["face"]["length"]
        elif suffix == ".obj":
            given = len(re.findall(rb"^[ \t]*f[ \t]", obj if obj is not None else path.read_bytes(), re.M))
        elif suffix == ".off":
            words = [w for line in path.read_bytes()[:4096].split(b"\n") if not line.lstrip().startswith(b"#")
                     for w in line.split()]
            given = int(words[2]) if words and words[0].endswith(b"OFF") else int(words[1])
    except (KeyError, TypeError, AttributeError, IndexError, ValueError, OSError):
        return False
    return given is not None and len(loaded.faces) > int(given)


def _tell(warn, message: str) -> None:
    """``message`` to ``warn`` when given, else as a :class:`UserWarning` (a library caller's)."""
    if warn is not None:
        warn(message)
    else:
        import warnings

        warnings.warn(message, UserWarning, stacklevel=3)


def mesh_notes(loaded, path) -> list[str]:
    """What a user may expect of the loaded file (a trimesh Trimesh or Scene) that training does
    not do: a texture or vertex colours are not used (the synthetic views are textured from the
    registered photos), and a scene's several meshes become one object (each placed by its
    node's transform). Without a word, a textured OBJ or a GLB of parts trained as if the
    texture or the split meant something."""
    import trimesh

    parts = list(loaded.geometry.items()) if isinstance(loaded, trimesh.Scene) else [(None, loaded)]
    out = []
    kinds = {getattr(getattr(g, "visual", None), "kind", None) for _, g in parts}
    if "texture" in kinds:
        out.append(f"{path}: the mesh's texture is not used: training takes the object's look from the registered "
                   f"photos alone")
    elif kinds & {"vertex", "face"}:
        out.append(f"{path}: the mesh's colours are not used: training takes the object's look from the registered "
                   f"photos alone")
    meshes = [name for name, g in parts if len(getattr(g, "faces", ()))]
    if isinstance(loaded, trimesh.Scene) and len(meshes) > 1:
        named = ", ".join(map(repr, meshes[:5])) + (", ..." if len(meshes) > 5 else "")
        out.append(f"{path}: its {len(meshes)} meshes ({named}) are trained as one object, each placed by the "
                   f"file's scene transforms")
    return out


def outward_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The faces (same order) re-wound so that every normal points out of a closed mesh.

    Exported meshes often mix windings (the bundled box.ply does); visibility tests need to know
    which side of a face is outside. An open mesh is only made consistent, not turned inside out.
    Faces are joined through vertices at the same position (an STL file stores each triangle's
    corners apart; texture seams split vertices), as in :attr:`Mesh.closed_outward`.
    """
    trimesh = _trimesh()

    F = np.asarray(faces)
    _, same = np.unique(np.asarray(vertices, float), axis=0, return_inverse=True)
    merged = same.reshape(-1)[F]
    tm = trimesh.Trimesh(np.unique(np.asarray(vertices, float), axis=0), merged, process=False)
    rewound = _rewound(tm) if len(F) > FAST_WINDING_FACES and not tm.is_winding_consistent else None
    if rewound is not None:
        tm.faces = rewound
    else:
        trimesh.repair.fix_winding(tm)
    if tm.is_watertight and tm.volume < 0:
        tm.invert()
    flipped = np.any(np.asarray(tm.faces) != merged, axis=1)  # (fix_winding and invert reverse a face's corners)
    return np.where(flipped[:, None], F[:, ::-1], F)


# above this many faces a mesh wound inconsistently is re-wound by _rewound, not trimesh's
# fix_winding (a Python loop over the faces: 27 s of a 590 000-face scan's 47 s of training)
FAST_WINDING_FACES = 20_000


def _rewound(tm) -> np.ndarray | None:
    """The faces of the trimesh ``tm`` re-wound as ``trimesh.repair.fix_winding`` re-winds them,
    computed on arrays; None where the answer could differ from its (faces joined by their edges
    in more than one part, whose starting faces it picks by set order, or a surface that cannot be
    wound consistently, where it depends on its traversal) — the caller then uses it.

    fix_winding walks the faces breadth first from the first face of its adjacency list and turns
    each face to run its shared edge against its neighbour's: on one orientable part every face's
    winding relative to that first face is fixed by any path to it, found here at once from the
    parity graph's components (each face twice, as kept and as turned: an edge run the same way
    by both faces joins one's kept to the other's turned)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(tm.faces)
    pairs, edges = np.asarray(tm.face_adjacency), np.asarray(tm.face_adjacency_edges)
    m = len(F)
    if len(pairs) == 0:
        return None

    def forward(f, u, v):  # whether face f runs u → v
        row = F[f]
        at = np.argmax(row == u[:, None], axis=1)
        return row[np.arange(len(f)), (at + 1) % 3] == v

    u, v = edges[:, 0], edges[:, 1]
    same = forward(pairs[:, 0], u, v) == forward(pairs[:, 1], u, v)  # (then one face must turn)
    a, b = pairs[:, 0], pairs[:, 1]
    one = np.ones(len(pairs))
    plain = coo_matrix((one, (a, b)), shape=(m, m))
    n_plain, plain_label = connected_components(plain, directed=False)
    linked = np.zeros(m, bool)
    linked[pairs.ravel()] = True
    if len(np.unique(plain_label[linked])) != 1:
        return None
    # the double cover: face f kept is node f, turned is node f + m
    rows = np.concatenate([a, a + m])
    cols = np.concatenate([np.where(same, b + m, b), np.where(same, b, b + m)])
    _, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * m, 2 * m)),
                                    directed=False)
    if np.any(label[:m][linked] == label[m:][linked]):  # (not orientable)
        return None
    root = pairs[0, 0]
    turn = linked & (label[:m] != label[root])
    return np.where(turn[:, None], F[:, ::-1], F)


def planar_groups(mesh: Mesh, angle_tol_deg: float = 1.0, offset_tol: float = 1e-3) -> np.ndarray:
    """Group id (m,) per triangle: triangles on one plane (normal and offset agree) share an id.

    A planar group is textured in a novel view by one plane-induced homography. ``offset_tol``
    is relative to the mesh's extent.
    """
    n = mesh.face_normals
    d = np.einsum("ij,ij->i", n, mesh.triangles[:, 0])
    # a plane is (n, d) or (−n, −d): pick the sign with the first non-zero normal component positive
    lead = n[np.arange(len(n)), np.argmax(np.abs(n) > 1e-6, axis=1)]
    sign = np.where(lead < 0, -1.0, 1.0)
    n, d = n * sign[:, None], d * sign
    cos_tol = np.cos(np.radians(angle_tol_deg))
    tol = offset_tol * mesh.extent
    groups = np.full(len(n), -1, dtype=np.int32)
    next_id = 0
    # the faces that may share face i's plane, from a k-d tree of (n, d·c/tol): within the chord
    # c = 2 sin(angle/2) in normal and tol in offset, so within √2·c in that space (a superset,
    # tested exactly below). Every face against every other cost O(m²): 5 s for a scanned mesh
    # of 49 000 triangles, whose faces are nearly all planes of their own
    from scipy.spatial import cKDTree

    chord = 2.0 * np.sin(np.radians(angle_tol_deg) / 2.0)
    scale = chord / tol if tol > 0 else 0.0
    space = np.column_stack([n, d * scale]) if tol > 0 else n
    tree = cKDTree(space)
    reach = chord * np.sqrt(2.0) * (1 + 1e-9) + 1e-12
    for i in range(len(n)):
        if groups[i] >= 0:
            continue
        near = np.asarray(tree.query_ball_point(space[i], reach), dtype=np.int64)
        near = near[(groups[near] < 0) & (n[near] @ n[i] >= cos_tol) & (np.abs(d[near] - d[i]) <= tol)]
        groups[near] = next_id
        next_id += 1
    return groups


def surface_normals(mesh: Mesh, points: np.ndarray, candidates: int = 16) -> np.ndarray:
    """Outward unit normal (n, 3) of the surface at points lying on the mesh (e.g. lifted
    keypoints): among the triangles with the nearest centroids, the one whose plane passes
    closest to the point. Coplanar neighbours share the normal, so ties do not matter."""
    from scipy.spatial import cKDTree

    P = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(P) == 0:
        return np.zeros((0, 3))
    oriented = make_mesh(mesh.vertices, outward_faces(mesh.vertices, mesh.faces))  # models stored before winding was fixed
    tris = oriented.triangles
    normals = oriented.face_normals
    k = min(candidates, len(tris))
    _, cand = cKDTree(tris.mean(axis=1)).query(P, k=k)
    cand = np.asarray(cand).reshape(len(P), k)
    plane = np.abs(np.einsum("pkj,pkj->pk", normals[cand], P[:, None, :] - tris[cand, 0]))
    return normals[cand[np.arange(len(P)), np.argmin(plane, axis=1)]]

"""Matching query SIFT features to the viewsets (Kragic & Kyrki, Sec. 2).

All viewsets' descriptors share one FLANN k-d forest, built once per loaded model and shared
read-only. One search per query feature replaces one per viewset (15× fewer). The synthetic
viewsets repeat the same physical points, so Lowe's ratio test compares the nearest neighbour
with the nearest one that belongs to a *different 3-D point* — otherwise two renderings of one
point would reject each other. Every surviving match votes for the viewset of its neighbour;
the viewset with the most votes is the paper's choice, and its matches go to PnP.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial.distance import cdist

from quatrack.viewsets.features import Features
from quatrack.viewsets.mesh import surface_normals
from quatrack.viewsets.store import ObjectModel
from quatrack.viewsets.viewset import extract_query_features, params_from_manifest

_FLANN_KDTREE = 1


@dataclass(frozen=True)
class MatchParams:
    ratio: float = 0.8  # Lowe's ratio test
    k: int = 4  # neighbours searched, to find one of another 3-D point
    checks: int = 32  # FLANN leaves visited per query (32 and 64 gave the same accuracy, bench locate)
    trees: int = 4
    same_point_tol: float = 0.01  # × the mesh's extent: closer 3-D points count as one point
    max_query_features: int = 1500


@dataclass(frozen=True)
class Matches:
    """Ratio-tested matches: query feature ``query_idx[i]`` ↔ model row ``model_row[i]``, which
    lies in viewset ``viewset[i]`` and is the 3-D point ``points3d[i]`` on a surface of normal ``normals[i]``."""

    query_idx: np.ndarray
    model_row: np.ndarray
    viewset: np.ndarray
    points3d: np.ndarray
    normals: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.query_idx)

    def subset(self, keep: np.ndarray) -> "Matches":
        return Matches(self.query_idx[keep], self.model_row[keep], self.viewset[keep], self.points3d[keep],
                       self.normals[keep], self.distance[keep])

    def votes(self, n_viewsets: int) -> np.ndarray:
        """Good matches per viewset."""
        return np.bincount(self.viewset, minlength=n_viewsets)


def _seeded_forest(descriptors: np.ndarray, trees: int) -> cv2.flann_Index:
    """FLANN's k-d forest over ``descriptors``, the same in every thread and every run, built
    without touching the caller's random numbers.

    The forest's random splits come from OpenCV's RNG, which is per thread: seeded (0), every
    thread and every run builds the same forest, so the same image gives the same matches (an
    unseeded forest turned a benchmark's wrong-pose count with what ran before it). FLANN takes
    no seed of its own, and OpenCV's Python API can set its RNG but not read it back (no
    ``theRNG``), so the seed cannot be restored afterwards: the forest is built in a thread of
    its own, whose RNG is seeded and then discarded. (It was seeded in the caller's thread: a
    ``cv2.setRNGSeed`` of the caller's, for its own ``cv2.kmeans`` or RANSAC, was silently reset by
    the first match.) The forest is then queried only by the thread that asked for it."""
    out: dict = {}

    def build() -> None:
        try:
            cv2.setRNGSeed(0)
            out["forest"] = cv2.flann_Index(descriptors, {"algorithm": _FLANN_KDTREE, "trees": trees})
        except BaseException as exc:  # (raised in the caller's thread, below)
            out["error"] = exc

    worker = threading.Thread(target=build, name="quatrack-flann-build", daemon=True)
    worker.start()
    worker.join()
    if "error" in out:
        raise out["error"]
    return out["forest"]


class ModelIndex:
    """One FLANN index over every viewset of an object; thread-safe to query."""

    def __init__(self, model: ObjectModel, params: MatchParams = MatchParams()) -> None:
        # no reference to the model itself: a cached index must not keep a model alive
        self.viewsets = model.viewsets
        self.params = params
        self.viewset_params = replace(params_from_manifest(model.manifest), max_features=params.max_query_features)
        nonempty = [vs for vs in model.viewsets if len(vs)]
        self.descriptors = np.ascontiguousarray(
            np.concatenate([vs.descriptors for vs in nonempty]) if nonempty else np.zeros((0, 128)), np.float32
        )
        self.points3d = np.concatenate([vs.points3d for vs in nonempty]) if nonempty else np.zeros((0, 3))
        self.row_viewset = np.concatenate(
            [np.full(len(vs), i) for i, vs in enumerate(model.viewsets) if len(vs)]
        ).astype(int) if nonempty else np.zeros(0, int)
        self.point_tol = params.same_point_tol * float(model.mesh.extent)
        self.normals = surface_normals(model.mesh, self.points3d)
        self._local = threading.local()  # cv2 matchers are not safe to share across threads
        self._views: dict[int, tuple] = {}  # match_view's per-view arrays (a dict's item set is atomic)
        # the model's photos with their z-buffers and the mesh's planes (recognition/appearance.py),
        # rendered once per model, not per pose judged
        # (on the mesh recognition checks poses with: a scan's decimation, Mesh.run_time)
        self.appearance = [r.rendered(model.mesh.run_time) for r in model.appearance]
        self.planes = model.mesh.run_time.plane_ids if self.appearance else None

    def _matcher(self) -> cv2.flann_Index:
        """This thread's FLANN k-d forest over all descriptors (built on first use)."""
        m = getattr(self._local, "matcher", None)
        if m is None:
            m = _seeded_forest(self.descriptors, self.params.trees)
            self._local.matcher = m
        return m

    def describe(self, image: np.ndarray, box: tuple[int, int, int, int] | None = None, max_side: int | None = None,
                 max_features: int | None = None, scale: float | None = None) -> Features:
        """SIFT features of ``image`` (or of its crop ``box`` = x0, y0, x1, y1, in image pixels),
        extracted exactly as the viewsets' were. Cropping, not masking, saves the pyramid.
        ``max_side``: shrink the crop to at most this many pixels on its longer side first
        (SIFT's cost grows with the area; the viewsets hold the object at several scales);
        ``max_features``: keep only the strongest (fewer descriptors to compute and to search);
        ``scale`` (< 1): shrink the crop by this factor (the smaller of the two shrinks wins);
        keypoints are returned in the image's pixels either way.

        SIFT (OpenCV) doubles its input before the first octave, so its cost is ≈ 4 × the crop's
        area × the pyramid: a crop shrunk by ½ costs ¼."""
        x0, y0 = 0, 0
        if box is not None:
            x0, y0, x1, y1 = box
            image = image[y0:y1, x0:x1]
        s = 1.0 if scale is None else min(1.0, float(scale))
        if max_side is not None and max(image.shape[:2]) > max_side:
            s = min(s, max_side / max(image.shape[:2]))
        if s < 1.0:
            image = cv2.resize(image, (max(1, round(image.shape[1] * s)), max(1, round(image.shape[0] * s))),
                               interpolation=cv2.INTER_AREA)
        params = self.viewset_params if max_features is None else replace(self.viewset_params, max_features=max_features)
        f = extract_query_features(image, None, params)
        if (box is None and s == 1.0) or len(f) == 0:
            return f
        # pixel centres: u = (u_small + ½)/s − ½
        kp = (f.keypoints + 0.5) / s - 0.5 + np.array([x0, y0], np.float32)
        return Features(kp.astype(np.float32), f.descriptors, f.sizes / s, f.angles)

    def match(self, features: Features) -> Matches:
        """Ratio-tested matches of ``features`` to the model, one per query feature at most."""
        empty = Matches(np.zeros(0, int), np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        if len(features) == 0 or len(self.descriptors) < 2:
            return empty
        k = min(self.params.k, len(self.descriptors))
        # one vectorised search (arrays, not k DMatch objects per query); FLANN's k-d tree
        # returns squared L2 distances, and -1 rows where it found fewer than k neighbours
        rows, dist = self._matcher().knnSearch(np.ascontiguousarray(features.descriptors, np.float32), k,
                                                params={"checks": self.params.checks})
        rows = np.asarray(rows, int).reshape(len(features), k)
        dist = np.sqrt(np.maximum(np.asarray(dist, np.float32).reshape(len(features), k), 0.0))
        dist[rows < 0] = np.inf
        ok = rows[:, 0] >= 0
        # the nearest neighbour of another 3-D point: the ratio test's second
        P = self.points3d[np.maximum(rows, 0)]
        other = (np.linalg.norm(P - P[:, :1], axis=-1) > self.point_tol) & (rows >= 0)
        other[:, 0] = False
        has_other = other.any(axis=1)
        second = np.where(has_other, dist[np.arange(len(rows)), np.argmax(other, axis=1)], np.inf)
        good = ok & (dist[:, 0] < self.params.ratio * second)
        q = np.flatnonzero(good)
        return self._closest_per_row(q, rows[q, 0], dist[q, 0])

    def match_view(self, features: Features, v: int) -> Matches:
        """Ratio-tested matches of ``features`` to viewset ``v`` alone (exhaustive: a view holds
        a few hundred descriptors).

        Why: in the shared index one physical point is described by every view that sees it,
        and each query feature votes only for the view of its nearest neighbour, so a point
        seen by ten near-identical views (a keyframe's synthetic views) lends the right view a
        tenth of its vote and its matches. :meth:`match` still ranks the views; re-matched
        alone, the chosen view gets back all the matches it can give (a turned cube: 10 → 35).
        The ratio test's second neighbour is the nearest of *another* 3-D point of that view,
        as in :meth:`match`."""
        view = self._views.get(v)
        if view is None:  # (per view, once: its rows, descriptors, their norms, which points differ)
            rows = np.flatnonzero(self.row_viewset == v)
            P = self.points3d[rows]
            D = self.descriptors[rows]
            view = self._views[v] = (rows, D, (D * D).sum(1), cdist(P, P) > self.point_tol)
        rows, D, DD, differ = view
        empty = Matches(np.zeros(0, int), np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        if len(features) == 0 or len(rows) < 2:
            return empty
        Q = np.asarray(features.descriptors, np.float32)
        # squared L2 by ‖q‖² − 2 q·d + ‖d‖² (one matrix product)
        d2 = np.maximum((Q * Q).sum(1)[:, None] - 2.0 * Q @ D.T + DD[None, :], 0.0)
        nearest = np.argmin(d2, axis=1)
        other = differ[nearest]  # (query, view point): another 3-D point
        second = np.where(other, d2, np.inf).min(axis=1)
        d1 = d2[np.arange(len(Q)), nearest]
        good = d1 < (self.params.ratio**2) * second
        q = np.flatnonzero(good)
        return self._closest_per_row(q, rows[nearest[q]], np.sqrt(d1[q]))

    def _closest_per_row(self, q: np.ndarray, r: np.ndarray, d: np.ndarray) -> Matches:
        """The matches query ``q`` ↔ model row ``r`` at distance ``d``: one model point may be the
        nearest of several query features, and keeps the closest."""
        order = np.argsort(d, kind="stable")
        q, r, d = q[order], r[order], d[order]
        _, first = np.unique(r, return_index=True)
        q, r, d = q[first], r[first], d[first]
        return Matches(q, r, self.row_viewset[r], self.points3d[r], self.normals[r], d)


_INDEX_CACHE: dict[int, ModelIndex] = {}  # by id(model); an entry leaves with its model
_CACHE_LOCK = threading.Lock()


def index_for(model: ObjectModel) -> ModelIndex:
    """The (cached) index of a loaded model."""
    key = id(model)
    with _CACHE_LOCK:
        idx = _INDEX_CACHE.get(key)
        if idx is None or idx.viewsets is not model.viewsets:
            idx = _INDEX_CACHE[key] = ModelIndex(model)
            weakref.finalize(model, _INDEX_CACHE.pop, key, None)
        return idx


def rank_viewsets(matches: Matches, n_viewsets: int) -> list[int]:
    """Viewsets with at least one match, by decreasing votes (the first is the paper's choice)."""
    v = matches.votes(n_viewsets)
    return [int(i) for i in np.argsort(-v, kind="stable") if v[i] > 0]

"""Measurement sources: each turns the current frame into a residual block for the filter.

A source keeps its own tracks between frames. Per frame the machine calls

- :meth:`measure` with the :class:`FrameContext` (the frame, the previous one, the prediction):
  the source returns a :class:`~.points.PointBlock` of gated correspondences;
- :meth:`settle` after the adjustment with the inlier mask of that block and the posterior:
  the source keeps what agreed (and may grow, retire or re-anchor).

The sources (issue 12): :class:`TrainedPoints` (the viewsets' 3-D points followed by KLT,
re-anchored by SIFT: :mod:`.anchor`), :class:`~.mesh_points.MeshPoints` (corners born on the
mesh at the current pose), :class:`~.edges.ModelEdges` (the mesh's sharp edges found by their
gradients) and :class:`~.contour.Contour` (the object's outline found by its colours).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.state import FilterState
from quatrack.viewsets.mesh import Mesh

from ..klt import Frame, track_points
from ..visibility import visibility_buffers, visible_points
from .params import TrackerParams
from .points import PointBlock, Tracks, VarianceFactor, gate, posterior_m2, unless_off


@dataclass
class FrameContext:
    """What a source may look at in one step."""

    image: np.ndarray  # BGR 8-bit
    frame: Frame  # grey, for KLT
    prev: Frame | None  # the previous frame (None right after initialisation)
    camera: PinholeCamera
    prior: FilterState  # the prediction for this frame
    _zbuffer: object = None
    # per source name: (its tracks, visible indices, new pixels, KLT ok) from follow_together
    followed: dict = field(default_factory=dict)
    # the trained points measured in this frame give the pose absolute evidence (at least
    # min_inliers of them): set by the tracker after measuring them, read by the mesh points
    # (mesh_points.MeshPoints.measure: whether their birth error is shared with the state's)
    anchored: bool = True
    # the tracker reports this frame's pose: not one withheld while the edges doubt the track
    # (Tracker._doubt); sources learn only from such frames (births on the mesh, the outline's colours)
    vouched: bool = True

    def zbuffer(self, mesh: Mesh, params: TrackerParams):
        """The visibility z-buffer at the prediction, rendered once for every source."""
        if self._zbuffer is None:
            self._zbuffer = visibility_buffers(mesh, self.camera, self.prior.pose, params.visibility)
        return self._zbuffer


class MeasurementSource(Protocol):
    name: str

    def __len__(self) -> int: ...

    def reset(self) -> None: ...

    def measure(self, ctx: FrameContext, timings: dict) -> PointBlock: ...

    def settle(self, ctx: FrameContext, block: PointBlock, inliers: np.ndarray, state: FilterState) -> None: ...


def visible_tracks(mesh: Mesh, ctx: FrameContext, tracks: Tracks, params: TrackerParams,
                   timings: dict) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the ``tracks`` visible at the prediction (:func:`visible_points` on the frame's
    z-buffer) and their predicted pixels (n, 2)."""
    import time

    t0 = time.perf_counter()
    vis, uv_pred = visible_points(mesh, ctx.camera, ctx.prior.pose, tracks.X, params.visibility,
                                  ctx.zbuffer(mesh, params) if len(tracks) else None)
    idx = np.flatnonzero(vis)
    timings["visibility"] = timings.get("visibility", 0.0) + (time.perf_counter() - t0) * 1e3
    return idx, uv_pred[idx]


def _visible_together(ctx: FrameContext, group, timings: dict) -> list:
    """``[(source, *visible_tracks(source))]`` for the KLT sources ``group``, from ONE
    :func:`visible_points` call over all their tracks when they share the mesh and the
    visibility settings: it tests each point alone (its projection, the z-buffer's pixel, the
    face's angle), so one call over the concatenated points gives each source's answer
    (tests/test_step_speed_equivalence.py) and spares a call's fixed cost (the silhouette's
    erosion, the projections' set-up) per frame."""
    import time

    mesh, vp = group[0].mesh, group[0].params.visibility
    if any(s.mesh is not mesh or s.params.visibility != vp for s in group):
        return [(s, *visible_tracks(s.mesh, ctx, s.tracks, s.params, timings)) for s in group]
    t0 = time.perf_counter()
    X = np.concatenate([s.tracks.X for s in group])
    vis, uv_pred = visible_points(mesh, ctx.camera, ctx.prior.pose, X, vp,
                                  ctx.zbuffer(mesh, group[0].params) if len(X) else None)
    parts, start = [], 0
    for s in group:
        stop = start + len(s.tracks)
        idx = np.flatnonzero(vis[start:stop])
        parts.append((s, idx, uv_pred[start:stop][idx]))
        start = stop
    timings["visibility"] = timings.get("visibility", 0.0) + (time.perf_counter() - t0) * 1e3
    return parts


def follow_together(ctx: FrameContext, sources, timings: dict) -> None:
    """Follow the visible tracks of every KLT source (those with ``follows_klt``) in ONE
    pyramidal-LK call and leave each source's share in ``ctx`` for :func:`klt_block`.

    LK tracks every point alone on the two frames' pyramids, so one call gives exactly what one
    call per source gives, but builds the pyramids (both frames, forward and backward) once
    instead of once per source (OpenCV's Python binding takes no prebuilt pyramids)."""
    import time

    group = [s for s in sources if getattr(s, "follows_klt", False)]
    if len(group) < 2 or ctx.prev is None:
        return
    klt = group[0].params.klt
    if any(s.params.klt != klt for s in group):
        return  # (different KLT settings: one call each)
    parts = _visible_together(ctx, group, timings)
    t0 = time.perf_counter()
    uv0 = np.concatenate([s.tracks.uv[idx] for s, idx, _ in parts])
    guess = np.concatenate([uv for _, _, uv in parts])
    new_uv, ok, _ = track_points(ctx.prev, ctx.frame, uv0, guess, klt)
    timings["klt"] = timings.get("klt", 0.0) + (time.perf_counter() - t0) * 1e3
    start = 0
    for s, idx, _ in parts:
        stop = start + len(idx)
        ctx.followed[s.name] = (s.tracks, idx, new_uv[start:stop], ok[start:stop])
        start = stop


def klt_block(name: str, mesh: Mesh, ctx: FrameContext, tracks: Tracks, params: TrackerParams,
              timings: dict) -> tuple[PointBlock, np.ndarray]:
    """Tracks visible at the prediction, followed by KLT from the previous frame starting at
    their predicted pixels (fast but predictable motion stays within reach). Returns the block
    (isotropic ``sigma_px``) and the indices of ``tracks`` it holds. Uses the tracks' share of
    :func:`follow_together` when it followed these very tracks in this frame."""
    import time

    done = ctx.followed.get(name)
    if done is not None and done[0] is tracks:
        _, idx, new_uv, ok = done
    else:
        idx, uv_pred = visible_tracks(mesh, ctx, tracks, params, timings)
        t0 = time.perf_counter()
        new_uv, ok, _ = track_points(ctx.prev, ctx.frame, tracks.uv[idx], uv_pred, params.klt)
        timings["klt"] = timings.get("klt", 0.0) + (time.perf_counter() - t0) * 1e3
    idx = idx[ok]
    return PointBlock.isotropic(name, Tracks(tracks.X[idx], new_uv[ok]), params.sigma_px), idx


class TrainedPoints:
    """The viewsets' 3-D points, followed by KLT: exact model points, the anchors against drift.
    Their supply is :class:`~.anchor.Anchor` (SIFT matches), which the machine schedules."""

    name = "trained"
    follows_klt = True  # its tracks join follow_together's one KLT call

    def __init__(self, mesh: Mesh, params: TrackerParams) -> None:
        self.mesh, self.params = mesh, params
        self.tracks = Tracks.empty()
        self.factor = VarianceFactor(2)

    def __len__(self) -> int:
        return len(self.tracks)

    def reset(self) -> None:
        self.tracks = Tracks.empty()
        self.factor.reset()

    def measure(self, ctx: FrameContext, timings: dict) -> PointBlock:
        p = self.params
        block, _ = klt_block(self.name, self.mesh, ctx, self.tracks, p, timings)
        block.C = block.C * self.factor.value
        return block.keep(unless_off(gate(ctx.camera, block, ctx.prior, p.gate_chi2), p.min_inliers))

    def settle(self, ctx: FrameContext, block: PointBlock, inliers: np.ndarray, state: FilterState) -> None:
        self.factor.update(posterior_m2(ctx.camera, block.keep(inliers), state))
        self.tracks = block.tracks.keep(inliers)

"""Measurement sources: each turns the current frame into a residual block for the filter.

A source keeps its own tracks between frames. Per frame the machine calls

- :meth:`measure` with the :class:`FrameContext` (the frame, the previous one, the prediction):
  the source returns a :class:`~.points.PointBlock` of gated correspondences;
- :meth:`settle` after the adjustment with the inlier mask of that block and the posterior:
  the source keeps what agreed (and may grow, retire or re-anchor).

The sources (issue 12): :class:`TrainedPoints` (the viewsets' 3-D points followed by KLT,
re-anchored by SIFT: :mod:`.anchor`), :class:`~.mesh_points.MeshPoints` (corners born on the
mesh at the current pose).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.state import FilterState
from quatrack.viewsets.mesh import Mesh

from ..klt import Frame, track_points
from ..visibility import visibility_buffers, visible_points
from .params import TrackerParams
from .points import PointBlock, Tracks, VarianceFactor, gate, posterior_m2


@dataclass
class FrameContext:
    """What a source may look at in one step."""

    image: np.ndarray  # BGR 8-bit
    frame: Frame  # grey, for KLT
    prev: Frame | None  # the previous frame (None right after initialisation)
    camera: PinholeCamera
    prior: FilterState  # the prediction for this frame
    _zbuffer: object = None

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


def klt_block(name: str, mesh: Mesh, ctx: FrameContext, tracks: Tracks, params: TrackerParams,
              timings: dict) -> tuple[PointBlock, np.ndarray]:
    """Tracks visible at the prediction, followed by KLT from the previous frame starting at
    their predicted pixels (fast but predictable motion stays within reach). Returns the block
    (isotropic ``sigma_px``) and the indices of ``tracks`` it holds."""
    import time

    t0 = time.perf_counter()
    vis, uv_pred = visible_points(mesh, ctx.camera, ctx.prior.pose, tracks.X, params.visibility,
                                  ctx.zbuffer(mesh, params) if len(tracks) else None)
    idx = np.flatnonzero(vis)
    timings["visibility"] = timings.get("visibility", 0.0) + (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    new_uv, ok, _ = track_points(ctx.prev, ctx.frame, tracks.uv[idx], uv_pred[idx], params.klt)
    timings["klt"] = timings.get("klt", 0.0) + (time.perf_counter() - t0) * 1e3
    idx = idx[ok]
    return PointBlock.isotropic(name, Tracks(tracks.X[idx], new_uv[ok]), params.sigma_px), idx


class TrainedPoints:
    """The viewsets' 3-D points, followed by KLT: exact model points, the anchors against drift.
    Their supply is :class:`~.anchor.Anchor` (SIFT matches), which the machine schedules."""

    name = "trained"

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
        g = gate(ctx.camera, block, ctx.prior, p.gate_chi2)
        if g.sum() >= p.min_inliers:  # (too few pass: the prediction is off, let the adjustment judge)
            block = block.keep(g)
        return block

    def settle(self, ctx: FrameContext, block: PointBlock, inliers: np.ndarray, state: FilterState) -> None:
        self.factor.update(posterior_m2(ctx.camera, block.keep(inliers), state))
        self.tracks = block.tracks.keep(inliers)

"""Point correspondences as the filter sees them: tracks, residual blocks, the innovation gate.

A source's measurements for one frame are a :class:`PointBlock`: object points ``X`` (n, 3),
their measured pixels ``uv`` (n, 2) and pixel covariances ``C`` (n, 2, 2). Sources differ only
in ``C``: a trained model point is exact (``C = σ² I``); a point born on the mesh at an uncertain
pose carries that pose's uncertainty too (recognition/tracker/mesh_points.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.measurements import PointMeasurements, project_model_points
from quatrack.tracking.state import FilterState


@dataclass
class Tracks:
    """Tracked object points: object-frame points (n, 3) and their pixels in the last frame (n, 2)."""

    X: np.ndarray
    uv: np.ndarray

    @classmethod
    def empty(cls) -> "Tracks":
        return cls(np.zeros((0, 3)), np.zeros((0, 2)))

    def __len__(self) -> int:
        return len(self.X)

    def keep(self, mask: np.ndarray) -> "Tracks":
        return Tracks(self.X[mask], self.uv[mask])

    def __add__(self, other: "Tracks") -> "Tracks":
        return Tracks(np.concatenate([self.X, other.X]), np.concatenate([self.uv, other.uv]))


@dataclass
class PointBlock:
    """One source's correspondences in this frame, with pixel covariances ``C`` (n, 2, 2)."""

    source: str
    X: np.ndarray
    uv: np.ndarray
    C: np.ndarray

    @classmethod
    def isotropic(cls, source: str, tracks: Tracks, sigma_px: float) -> "PointBlock":
        return cls(source, tracks.X, tracks.uv, np.broadcast_to(sigma_px**2 * np.eye(2), (len(tracks), 2, 2)).copy())

    def __len__(self) -> int:
        return len(self.X)

    @property
    def tracks(self) -> Tracks:
        return Tracks(self.X, self.uv)

    def keep(self, mask: np.ndarray) -> "PointBlock":
        return PointBlock(self.source, self.X[mask], self.uv[mask], self.C[mask])

    @staticmethod
    def stack(blocks: list["PointBlock"]) -> "PointBlock":
        if not blocks:
            return PointBlock("", np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2, 2)))
        return PointBlock("+".join(b.source for b in blocks), np.concatenate([b.X for b in blocks]),
                          np.concatenate([b.uv for b in blocks]), np.concatenate([b.C for b in blocks]))

    @staticmethod
    def split(blocks: list["PointBlock"], rows: np.ndarray) -> list[np.ndarray]:
        """``rows`` — one per measurement of :meth:`stack` (``blocks``) — cut into each block's
        part (the inverse of the stacking, for per-source masks and counts).

        >>> a = PointBlock("a", np.zeros((2, 3)), np.zeros((2, 2)), np.zeros((2, 2, 2)))
        >>> b = PointBlock("b", np.zeros((3, 3)), np.zeros((3, 2)), np.zeros((3, 2, 2)))
        >>> [m.tolist() for m in PointBlock.split([a, b], np.array([1, 0, 0, 1, 1], bool))]
        [[True, False], [False, True, True]]
        """
        return np.split(np.asarray(rows), np.cumsum([len(b) for b in blocks])[:-1])

    def measurements(self, camera: PinholeCamera) -> PointMeasurements:
        """The residual block of eq. 24 for :meth:`PoseFilter.update`."""
        return PointMeasurements.create(camera, self.X, self.uv, self.C)


def mahalanobis2(r: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``rᵀ S⁻¹ r`` for residuals (n, 2) and 2×2 covariances (n, 2, 2), in closed form."""
    a, b, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
    det = a * d - b * b
    return (d * r[:, 0] ** 2 - 2 * b * r[:, 0] * r[:, 1] + a * r[:, 1] ** 2) / det


def gate(camera: PinholeCamera, block: PointBlock, prior: FilterState, chi2: float) -> np.ndarray:
    """Innovation gate: ``rᵀ (J P Jᵀ + C)⁻¹ r < χ²`` per point, at the prediction."""
    if len(block) == 0:
        return np.zeros(0, bool)
    uv, J = project_model_points(camera, block.X, prior.p, prior.R, True)
    S = J @ prior.pose_covariance @ np.swapaxes(J, 1, 2) + block.C
    return mahalanobis2(block.uv - uv, S) < chi2


def unless_off(passed: np.ndarray, min_inliers: int) -> np.ndarray:
    """The gate's verdicts (:func:`gate`) as a source applies them: when fewer than
    ``min_inliers`` or fewer than half of its points pass, the prediction is what is off (a
    camera's jolt moves the whole image), not the points, and every point is kept for the
    adjustment's two passes to judge. Gated to a handful, the zoo's cubes and prisms were lost at
    the peak of their walks' shake with every point followed by KLT; gated to the third that the
    prediction still expected, they dwindled until the track was lost again (bench/RESULTS.md,
    session 42).

    >>> int(unless_off(np.array([True] * 12 + [False] * 4), 12).sum())  # 12 of 16 pass: gated
    12
    >>> int(unless_off(np.array([True] * 12 + [False] * 20), 12).sum())  # 12 of 32: all kept
    32
    """
    if passed.sum() >= max(min_inliers, 0.5 * len(passed)):
        return passed
    return np.ones_like(passed)


def pose_spread(camera: PinholeCamera, X: np.ndarray, state: FilterState) -> np.ndarray:
    """``J P Jᵀ`` (n, 2, 2): how the pose's uncertainty spreads the projections of ``X``."""
    _, J = project_model_points(camera, X, state.p, state.R, True)
    return J @ state.pose_covariance @ np.swapaxes(J, 1, 2)


# medians of χ² with 1 and 2 degrees of freedom: a point measures 2 pixel coordinates, an edge
# sample 1 (across the edge)
_CHI2_MEDIAN = {1: 0.4549, 2: 1.3863}


@dataclass
class VarianceFactor:
    """How much larger a source's errors are than its covariances say: a variance component
    (Helmert; Förstner's a-posteriori variance factor) estimated from its posterior residuals.

    After each adjustment, ``f = median(rᵢᵀ Cᵢ⁻¹ rᵢ) / median(χ²_dof)`` over the source's inliers
    (the median: outliers the robust adjustment ignored must not count), floored at 1 (a source
    is never trusted more than its nominal noise) and smoothed over frames (``keep``). The
    source's next covariances are multiplied by it. KLT tracks slide a little between SIFT
    re-anchorings, more on faces seen obliquely; a measured ``f`` of 3–6 on the trained points
    (rendered orbits) was the pose covariance's largest overconfidence."""

    dof: int
    keep: float = 0.7
    min_samples: int = 8
    value: float = field(default=1.0)

    def reset(self) -> None:
        self.value = 1.0

    def update(self, m2: np.ndarray) -> None:
        """``m2``: the inliers' posterior ``rᵀ C⁻¹ r`` under the covariances used (already × value)."""
        if len(m2) < self.min_samples:
            return
        f = max(float(np.median(m2)) * self.value / _CHI2_MEDIAN[self.dof], 1.0)
        self.value = self.keep * self.value + (1.0 - self.keep) * f


def posterior_m2(camera: PinholeCamera, block: PointBlock, state: FilterState) -> np.ndarray:
    """``rᵀ C⁻¹ r`` of the block's measurements at the posterior pose ``state``."""
    if len(block) == 0:
        return np.zeros(0)
    uv, _ = project_model_points(camera, block.X, state.p, state.R, False)
    return mahalanobis2(block.uv - uv, block.C)


def score_statistic(camera: PinholeCamera, block: PointBlock, state: FilterState) -> float:
    """Rao's score test: do the block's measurements, alone, prefer another pose than ``state``?

    At the pose of ``state`` (an adjustment that also used other measurements), with residuals
    ``rᵢ = π(Xᵢ) − uvᵢ``, Jacobians ``Jᵢ = ∂π/∂[p, δθ]`` and weights ``Wᵢ = Cᵢ⁻¹``:
    ``g = Σ Jᵢᵀ Wᵢ rᵢ``, ``H = Σ Jᵢᵀ Wᵢ Jᵢ``, ``T = gᵀ H⁻¹ g`` — the decrease of the block's own χ²
    by one Gauss–Newton step towards the pose it alone fits. If ``state`` is consistent with
    the block (and ``C`` honest), ``T ~ χ²₆``; a large ``T`` says the other measurements pulled
    the pose away from where this block puts it. 0 for fewer than 3 points or a singular ``H``.

    >>> from quatrack.tracking.camera import PinholeCamera
    >>> from quatrack.tracking.state import initial_state
    >>> cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, np.zeros(5), width=640, height=480)
    >>> s = initial_state(0.0, np.array([0.0, 0.0, 5.0]), np.array([1.0, 0, 0, 0]), np.eye(6) * 1e-4)
    >>> X = np.random.default_rng(0).uniform(-1, 1, (30, 3))
    >>> uv, _ = project_model_points(cam, X, s.p, s.R, False)
    >>> C = np.broadcast_to(np.eye(2), (30, 2, 2)).copy()
    >>> round(score_statistic(cam, PointBlock("a", X, uv, C), s), 6)  # at the pose they fit
    0.0
    >>> score_statistic(cam, PointBlock("a", X, uv + [3.0, 0.0], C), s) > 100  # they fit 3 px away
    True
    """
    if len(block) < 3:
        return 0.0
    g, H = _score_parts(*_weighted_rows(camera, block, state))
    try:
        return float(g @ np.linalg.solve(H, g))
    except np.linalg.LinAlgError:
        return 0.0


def _weighted_rows(camera: PinholeCamera, block: PointBlock, state: FilterState):
    """Per measurement at ``state``: the Jacobian ``Jᵢ = ∂π/∂[p, δθ]`` (n, 2, 6), ``Wᵢ Jᵢ`` with
    ``Wᵢ = Cᵢ⁻¹`` (n, 2, 6) and the residual ``rᵢ = π(Xᵢ) − uvᵢ`` (n, 2); a block's gradient and
    information are then ``g = Σ (Wᵢ Jᵢ)ᵀ rᵢ`` and ``H = Σ Jᵢᵀ Wᵢ Jᵢ``, two matrix products over the
    stacked rows (:func:`_score_parts`; a three-operand ``einsum`` took ten times as long)."""
    uv, J = project_model_points(camera, block.X, state.p, state.R, True)
    a, b, d = block.C[:, 0, 0], block.C[:, 0, 1], block.C[:, 1, 1]
    W = np.stack([np.stack([d, -b], -1), np.stack([-b, a], -1)], -2) / (a * d - b * b)[:, None, None]
    return J, W @ J, uv - block.uv


def _score_parts(J: np.ndarray, WJ: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(g, H)`` of rows of :func:`_weighted_rows`."""
    WJf = WJ.reshape(-1, 6)
    return WJf.T @ r.reshape(-1), J.reshape(-1, 6).T @ WJf


def disagreement_factor(camera: PinholeCamera, blocks, state: FilterState) -> float:
    """How much more the sources disagree about the pose than their covariances allow: the
    Birge ratio squared (Birge 1932; the Particle Data Group's scale factor ``S²``), ≥ 1.

    Each block ``b`` (a source's inliers of one frame, at least 3) alone would move the joint
    pose ``state`` by one Gauss–Newton step and lower its own χ² by ``T_b = g_bᵀ H_b⁺ g_b``
    (:func:`score_statistic`; ``H⁺`` the pseudo-inverse over the directions the block measures,
    ``rank_b`` of them: a cylinder's outline does not see its spin). When every block is
    consistent with the others and its covariances are honest, ``Σ T_b ~ χ²`` with
    ``Σ rank_b − 6`` degrees of freedom (``B`` estimates of one 6-vector); then

        S² = max(1, Σ T_b / (Σ rank_b − 6)),

    and 1 with fewer than two blocks or no degree of freedom left. A ``S²`` above 1 says an
    error that no block's covariance holds (an outline locked on the print beside it, points
    born at a pose that was off): the pose's covariance, made from those covariances, is too
    small by about that factor. ``H`` is Jacobi-scaled before its rank is taken, so that the
    answer does not depend on the mesh's unit.

    >>> from quatrack.tracking.camera import PinholeCamera
    >>> from quatrack.tracking.state import initial_state
    >>> cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, np.zeros(5), width=640, height=480)
    >>> s = initial_state(0.0, np.array([0.0, 0.0, 5.0]), np.array([1.0, 0, 0, 0]), np.eye(6) * 1e-4)
    >>> X = np.random.default_rng(0).uniform(-1, 1, (60, 3))
    >>> uv, _ = project_model_points(cam, X, s.p, s.R, False)
    >>> C = np.broadcast_to(np.eye(2), (30, 2, 2)).copy()
    >>> a, b = PointBlock("a", X[:30], uv[:30], C), PointBlock("b", X[30:], uv[30:], C)
    >>> disagreement_factor(cam, [a, b], s)  # both fit the pose exactly
    1.0
    >>> a5 = PointBlock("a", X[:30], uv[:30] + [5.0, 0.0], C)  # 5 px apart: far beyond 1 px noise
    >>> disagreement_factor(cam, [a5, b], s) > 10
    True
    """
    blocks = [b for b in blocks if len(b) >= 3]
    if len(blocks) < 2:
        return 1.0
    J, WJ, r = _weighted_rows(camera, PointBlock.stack(blocks), state)  # (one projection for all)
    total, dof, used, start = 0.0, -6, 0, 0
    for block in blocks:
        rows = slice(start, start + len(block))
        start += len(block)
        g, H = _score_parts(J[rows], WJ[rows], r[rows])
        d = np.sqrt(np.diagonal(H))
        if not np.all(np.isfinite(d)):
            continue
        d = np.where(d > 0, d, 1.0)  # (a parameter the block does not touch at all: left unscaled)
        w, V = np.linalg.eigh(H / np.outer(d, d))
        measured = w > 1e-10 * max(w[-1], 0.0)
        if not measured.any():
            continue
        proj = V[:, measured].T @ (g / d)
        total += float(np.sum(proj * proj / w[measured]))
        dof += int(measured.sum())
        used += 1
    if used < 2 or dof <= 0:
        return 1.0
    return max(1.0, total / dof)

"""M-estimator weights for iteratively reweighted Gauss–Newton.

A measurement whose whitened residual has squared norm ``s²`` (its squared Mahalanobis distance)
gets the weight ``w = ρ'(s²)`` of the robust cost ``½ Σ ρ(s²)``; scaling its residual rows and
Jacobian by ``√w`` makes the Gauss–Newton step and gradient those of the robust cost.
Scales are in Mahalanobis units; the default is the 95 % quantile of χ² with ``d`` degrees of
freedom (99.9 % for Tukey, which rejects outright beyond it).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Literal

import numpy as np

RobustLoss = Literal["none", "huber", "cauchy", "tukey"]
LOSSES: tuple[str, ...] = ("none", "huber", "cauchy", "tukey")


@lru_cache(maxsize=64)
def default_scale(loss: str, dim: int) -> float:
    """Threshold (Mahalanobis distance) for a residual of ``dim`` rows: a χ² quantile.

    ``scipy.special.chdtri`` (the inverse χ² survival function) rather than ``scipy.stats``,
    which takes a second to import on the first frame."""
    from scipy.special import chdtri

    return float(np.sqrt(chdtri(dim, 0.001 if loss == "tukey" else 0.05)))


def weights(s2: np.ndarray, loss: RobustLoss, scale: float) -> np.ndarray:
    """IRLS weights ``ρ'(s²)`` for squared Mahalanobis distances ``s2``."""
    s2 = np.asarray(s2, dtype=float)
    k2 = scale * scale
    if loss == "none":
        return np.ones_like(s2)
    if loss == "huber":
        return np.where(s2 <= k2, 1.0, scale / np.sqrt(np.maximum(s2, k2)))
    if loss == "cauchy":
        return 1.0 / (1.0 + s2 / k2)
    if loss == "tukey":
        return np.where(s2 < k2, (1.0 - s2 / k2) ** 2, 0.0)
    raise ValueError(f"unknown robust loss {loss!r}; expected one of {LOSSES}")


def rho(s2: np.ndarray, loss: RobustLoss, scale: float) -> np.ndarray:
    """Robust cost ``ρ(s²)`` (``ρ(s²) = s²`` for ``none``), with ``ρ' =`` :func:`weights`."""
    s2 = np.asarray(s2, dtype=float)
    k2 = scale * scale
    if loss == "none":
        return s2
    if loss == "huber":
        s = np.sqrt(s2)
        return np.where(s2 <= k2, s2, 2.0 * scale * s - k2)
    if loss == "cauchy":
        return k2 * np.log1p(s2 / k2)
    if loss == "tukey":
        return np.where(s2 < k2, k2 / 3.0 * (1.0 - (1.0 - s2 / k2) ** 3), k2 / 3.0)
    raise ValueError(f"unknown robust loss {loss!r}; expected one of {LOSSES}")

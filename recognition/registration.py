"""A registered photo's pose refitted to the mesh's edges in it, with the clicks holding it
(``quatrack register``). The clicks' PnP is :mod:`quatrack.viewsets.register`'s (geometry, a lower
layer); the edges' evidence is recognition's (:mod:`.evidence`), hence this module here.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.register import PointPairs, Registration, click_limit_px, click_sigma, registration_at

from .evidence import edge_fit, measure_edges

__all__ = ["AGREEMENT_SLACK", "CLICK_SIGMA_FLOOR", "DEFAULT_CLICK_SIGMA", "clicks_sigma", "refine_with_edges", "xyzw_fits",
           "xyzw_hint"]

AGREEMENT_SLACK = 0.02  # a refit may lose this much edge agreement (one sample in 50: a pose already on its edges)


CLICK_SIGMA_FLOOR = 0.3  # px per coordinate: clicks on whole pixels are off by 0.29 px RMS from rounding alone
DEFAULT_CLICK_SIGMA = 2.0  # px: a click's σ unless the clicks' residual rules it out (refine_with_edges)


def _sigma_bound(rms_px: float, n: int, confidence: float = 0.95) -> float:
    """The largest click σ the ``n`` clicks' PnP residual ``rms_px`` allows at ``confidence``:
    ``n · rms² / σ²`` is χ² with ``2n − 6`` degrees of freedom, so
    ``σ ≤ rms · √(n / χ²_{2n−6}(1 − confidence))``; inf with too few clicks to tell.

    >>> round(_sigma_bound(0.25, 8), 2), _sigma_bound(1.0, 3)
    (0.36, inf)
    """
    from scipy.stats import chi2

    if n <= 3 or not np.isfinite(rms_px):
        return float("inf")
    return float(rms_px * np.sqrt(n / chi2.ppf(1.0 - confidence, 2 * n - 6)))


def clicks_sigma(reg: Registration, n: int, click_sigma_px: float | None = None) -> float:
    """The ``n`` clicks' σ (px per coordinate) that weighs them against the edges: the one stated
    (``click_sigma_px``), or more where their PnP residual shows more
    (:func:`~quatrack.viewsets.register.click_sigma`); not stated (None): as if
    :data:`DEFAULT_CLICK_SIGMA` were, but less where the residual rules it out
    (:func:`_sigma_bound`), at least :data:`CLICK_SIGMA_FLOOR`."""
    if click_sigma_px is not None:
        return click_sigma(reg, n, click_sigma_px)
    return max(CLICK_SIGMA_FLOOR, min(click_sigma(reg, n, DEFAULT_CLICK_SIGMA), _sigma_bound(reg.rms_px, n)))


def refine_with_edges(grey: np.ndarray, mesh, camera: PinholeCamera, reg: Registration, pairs: PointPairs,
                      click_sigma_px: float | None = None, rounds: int = 3) -> Registration:
    """``reg``'s pose refitted to the mesh's visible edges in the photo and the clicks together
    (:func:`~quatrack.recognition.evidence.edge_fit`: each edge sample searches along its normal
    for the strongest aligned gradient; Gauss–Newton with Cauchy weights, the clicks at
    :func:`~quatrack.viewsets.register.click_sigma`'s σ, the edges at 1 px), measured again from
    each new pose (``rounds``: the search is centred on the pose, so a pose several pixels off is
    pulled in over two or three).

    The refit is kept only if it keeps the clicks (their RMS within :func:`click_limit_px`) and
    puts as much of the model's edges on the photo's edges as before (within
    :data:`AGREEMENT_SLACK`: a pose clicked well already has 95 % of them there); otherwise ``reg`` comes back
    with the agreement measured and ``moved`` None. Why the clicks must hold it: a printed box's
    decoration runs parallel to its edges a few pixels inside, and the strongest gradient the
    search finds can be the print's. On the bundled cookie box's photo the edges alone pulled a
    pose clicked to 1.4 px RMS by 29 % of the box's size onto its print's frame, leaving the
    clicks 19 px off; on the zoo's photos (flat print) they brought poses 3× nearer the truth.

    ``click_sigma_px``: how far the user says a click may be off; None (the default): 2 px, or
    less where the clicks' PnP residual rules that out (:func:`clicks_sigma`). Why not a fixed 2 px: clicks good to a third of a pixel
    were weighed as 2 px ones, and on a photo over gravel the edges' search took the clutter
    beside the outline — a box's pose moved 0.14 → 1.75 % of its diameter off the truth, the
    clicks left at 2.6 px RMS, within the 2 px gate (a user's report); careful clicks hold it."""
    sigma = clicks_sigma(reg, len(pairs), click_sigma_px)
    before, image = measure_edges(grey, mesh, camera, reg.pose)
    pose, after = reg.pose, before
    for _ in range(rounds):
        if image is None:
            break
        fit = edge_fit(image, mesh, camera, pose, pairs.model, pairs.pixel, point_sigma_px=sigma, iterations=10)
        if fit.pose is None:
            break
        pose = fit.pose
        after, image = measure_edges(grey, mesh, camera, pose)  # (the next round's edges, and the last's agreement)
    if pose is reg.pose:
        return replace(reg, edge_agreement=(before.agreement, before.agreement))
    refit = registration_at(pairs, camera, pose, edge_agreement=(before.agreement, after.agreement))
    if after.agreement < before.agreement - AGREEMENT_SLACK or refit.rms_px > click_limit_px(len(pairs), sigma):
        return replace(reg, edge_agreement=(before.agreement, after.agreement), refused=refit)
    c = mesh.centre
    dc = float(np.linalg.norm((pose.R @ c + pose.t) - (reg.pose.R @ c + reg.pose.t)))
    angle = float(np.degrees(quat.angle_between(pose.q_wxyz, reg.pose.q_wxyz)))
    return replace(refit, moved=(dc / float(mesh.extent), angle))


def xyzw_fits(grey, mesh, view):
    """The edge evidence (:func:`~quatrack.recognition.evidence.edge_agreement`) of the view's
    ``q_wxyz`` read ``[x, y, z, w]`` (``view.xyzw_pose``: scipy's and ROS's order) in its photo
    ``grey``, when that reading puts the object in front of the camera and its edges on the
    photo's as a pose ``locate`` finds must (``PoseParams``' bars); else None (another pose
    form, or the other reading fits no better). ``train`` and ``register`` both ask it of a
    pose whose edges miss the photo's."""
    from .evidence import edge_agreement
    from .pose import PoseParams, edges_agree

    alt = getattr(view, "xyzw_pose", None)
    if alt is None or not np.all(alt.apply(mesh.vertices)[:, 2] > 0):
        return None
    p = PoseParams()
    x = edge_agreement(grey, mesh, view.camera, alt)
    return x if edges_agree(x, p) else None


def xyzw_hint(grey, mesh, view) -> str:
    """``is the quaternion in [x, y, z, w] order? …`` with the edges of that reading and the
    quaternion to write, when it fits the photo (:func:`xyzw_fits`); else ""."""
    from quatrack.viewsets.train import XYZW_HINT

    x = xyzw_fits(grey, mesh, view)
    if x is None:
        return ""
    q = ", ".join(f"{c:.6g}" for c in view.xyzw_pose.q_wxyz)
    return f"{XYZW_HINT} (read so, {x.agreement:.0%} of its edges agree: \"q_wxyz\": [{q}])"

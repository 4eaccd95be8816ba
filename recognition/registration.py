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

__all__ = ["AGREEMENT_SLACK", "refine_with_edges"]

AGREEMENT_SLACK = 0.02  # a refit may lose this much edge agreement (one sample in 50: a pose already on its edges)


def refine_with_edges(grey: np.ndarray, mesh, camera: PinholeCamera, reg: Registration, pairs: PointPairs,
                      click_sigma_px: float = 2.0, rounds: int = 3) -> Registration:
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
    clicks 19 px off; on the zoo's photos (flat print) they brought poses 3× nearer the truth."""
    sigma = click_sigma(reg, len(pairs), click_sigma_px)
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

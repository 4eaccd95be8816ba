"""Keyframes: what the object looked like earlier in this run, to find it again after a loss.

Recognition (:func:`..locate.locate`) knows the object only from its trained views (and the
views learned into the stored model). A model trained from one photo cannot find it from a
side that photo does not show; so once the tracker had followed the object round to such a
side and then lost it (the object left the frame, a hand covered it), nothing could start the
track again although the object stood plainly in view (issue 12's report: the last 29 % of a
video lost). The tracker remembers instead: while it tracks with a confident pose, it keeps
*keyframes*, the frame's SIFT keypoints on the visible faces lifted onto the mesh at the pose
(the lifting of a learned view, :func:`quatrack.viewsets.learn.learned_viewset`):

- one per viewing direction: a frame whose direction (object frame, roll ignored, as SIFT is
  blind to it) lies at least ``keyframe_min_angle_deg`` from every keyframe's is added; one
  nearer than that *renews* the nearest keyframe when that is ``keyframe_renew_s`` old (the
  light may have changed since);
- at most ``keyframes_max``: the oldest goes.

After a loss the tracker's recognition searches the model's views and the keyframes together
(:meth:`Keyframes.search_model`: one FLANN index over all of them), with recognition's own
window search, pose search and verification: one search per frame, whichever view is nearest.

Keyframes live in memory for the run only; the stored model changes only through learned views
(``TrackerParams.learn``), whose rules are stricter because they outlive the run.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from quatrack.tracking.pose import Pose
from quatrack.viewsets.store import ObjectModel
from quatrack.viewsets.viewset import Viewset

from ..match import ModelIndex


@dataclass(frozen=True)
class Keyframe:
    """One remembered view: when (``time_s``), from where (``direction``: unit vector, object
    frame, from the centre towards the camera) and what it saw (``viewset``, lifted points)."""

    time_s: float
    direction: np.ndarray
    viewset: Viewset


class Keyframes:
    """The bounded set of a run's keyframes (see the module) and the index to search them."""

    def __init__(self, centre: np.ndarray, max_keyframes: int, min_angle_deg: float, renew_s: float) -> None:
        self.centre = np.asarray(centre, float)
        self.max = int(max_keyframes)
        self.min_angle_deg = float(min_angle_deg)
        self.renew_s = float(renew_s)
        self.items: list[Keyframe] = []
        self._search: tuple[ObjectModel, ModelIndex, ObjectModel] | None = None  # (base, index, model)

    def __len__(self) -> int:
        return len(self.items)

    def slot(self, pose: Pose, time_s: float) -> int | None:
        """Where a keyframe at ``pose`` would go: ``len(self)`` (a new direction: appended), the
        index of the nearest keyframe (to renew it, when ``renew_s`` old), or None (not wanted).

        >>> kf = Keyframes(np.zeros(3), 4, 15.0, 3.0)
        >>> front = Pose.from_rvec([0.0, 0.0, 0.0], [0.0, 0.0, 5.0])
        >>> kf.slot(front, 0.0)
        0
        >>> kf.add(Keyframe(0.0, front.viewing_direction(kf.centre), None), 0)
        >>> kf.slot(front, 1.0) is None, kf.slot(front, 3.5)  # too soon; then renewed
        (True, 0)
        >>> kf.slot(Pose.from_rvec([0.0, 0.5, 0.0], [0.0, 0.0, 5.0]), 1.0)  # 29° round: a new one
        1
        """
        if self.max <= 0:
            return None
        if not self.items:
            return 0
        d = pose.viewing_direction(self.centre)
        dirs = np.array([k.direction for k in self.items])
        ang = np.degrees(np.arccos(np.clip(dirs @ d, -1.0, 1.0)))
        j = int(np.argmin(ang))
        if ang[j] >= self.min_angle_deg:
            return len(self.items)
        if time_s - self.items[j].time_s >= self.renew_s:
            return j
        return None

    def add(self, keyframe: Keyframe, slot: int) -> None:
        """Put ``keyframe`` at ``slot`` (from :meth:`slot`); beyond ``max`` the oldest goes."""
        if slot < len(self.items):
            self.items[slot] = keyframe
        else:
            self.items.append(keyframe)
            if len(self.items) > self.max:
                self.items.pop(int(np.argmin([k.time_s for k in self.items])))
        self._search = None

    def search_model(self, base: ObjectModel) -> tuple[ObjectModel, ModelIndex]:
        """``base`` with the keyframes added to its viewsets (labelled ``keyframeK``), and its
        matching index (built once per change of the keyframes or of ``base``)."""
        cached = self._search
        if cached is None or cached[0] is not base:
            views = [replace(k.viewset, label=f"keyframe{i + 1}") for i, k in enumerate(self.items)]
            model = replace(base, viewsets=list(base.viewsets) + views)
            cached = self._search = (base, ModelIndex(model), model)
        return cached[2], cached[1]

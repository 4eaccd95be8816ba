"""Tracking an object through a video: the public path of the tracker.

    tracker = Tracker(model, camera, TrackerParams(motion_model="ude"))
    for image, t in frames:
        step = tracker.step(image, t)      # "init" | "tracking" | "lost"

The tracker lives in :mod:`quatrack.recognition.tracker`: a state machine (init / tracking /
lost, :mod:`~quatrack.recognition.tracker.machine`) over measurement sources that each return
residual blocks for Ude's quaternion filter (:mod:`~quatrack.recognition.tracker.sources`,
:mod:`~quatrack.recognition.tracker.anchor`). Every default is free of units
(:mod:`~quatrack.recognition.tracker.params`).
"""

from __future__ import annotations

from .tracker import DEFAULT_MOTION_NOISE, STATUSES, Tracker, TrackerParams, TrackStep, motion_noise

__all__ = ["Tracker", "TrackerParams", "TrackStep", "DEFAULT_MOTION_NOISE", "STATUSES", "motion_noise"]

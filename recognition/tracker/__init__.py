"""The video tracker (issue 12): a state machine (:mod:`.machine`) over measurement sources
(:mod:`.sources`: trained-point KLT; :mod:`.anchor`: SIFT re-anchoring), whose residual blocks
(:mod:`.points`) feed Ude's quaternion filter. Public path: :mod:`quatrack.recognition.video`."""

from .machine import Tracker
from .params import DEFAULT_MOTION_NOISE, STATUSES, TrackerParams, TrackStep, motion_noise

__all__ = ["Tracker", "TrackerParams", "TrackStep", "DEFAULT_MOTION_NOISE", "STATUSES", "motion_noise"]

"""The tracker behind a WebSocket session: ``quatrack.recognition.video.Tracker``.

(A locate-per-frame stand-in served here until the video tracker landed; it is gone now.)
One tracker per session, built on the session's first frame, when the image size is known.
"""

from __future__ import annotations

from dataclasses import replace

from quatrack.recognition.video import Tracker, TrackerParams

TRACKER_KIND = "recognition.video.Tracker"


def make_tracker(model, camera, index, max_pixels: int) -> Tracker:
    """A fresh tracker sharing the model and its index (both read-only)."""
    params = TrackerParams()
    params = replace(params, locate=replace(params.locate, max_pixels=max_pixels))
    return Tracker(model, camera, params, index=index)

"""The tracker behind a WebSocket session: ``quatrack.recognition.video.Tracker``.

(A locate-per-frame stand-in served here until the video tracker landed; it is gone now.)
One tracker per session, built on the session's first frame, when the image size is known.
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import replace

from quatrack.recognition.video import Tracker, TrackerParams

TRACKER_KIND = "recognition.video.Tracker"


def make_tracker(model, camera, index, max_pixels: int, executor: Executor | None = None, learn: bool = False,
                 sources: tuple[str, ...] | None = None, relocate_interval_s: float | None = None) -> Tracker:
    """A fresh tracker sharing the model and its index (both read-only), set for live streams:
    re-anchoring runs in the background on ``executor`` (the service's pool, owned by its
    lifespan) between frames (``pipelined_refresh``) on a smaller window with fewer features,
    so that no frame waits for SIFT (bench/RESULTS.md, service). Without an executor it runs
    in the step. (A thread of its own for re-anchoring, apart from the frames' pool, was
    measured in session 18 and gained nothing: bench/RESULTS.md.) ``learn``: keep views of unseen sides (service/learning.py stores them). ``sources``: the
    measurement sources (``QUATRACK_TRACKER_SOURCES``; None: the tracker's default).
    ``relocate_interval_s``: while lost, recognition at most once per that many seconds
    (``QUATRACK_RELOCATE_INTERVAL_S``; None or 0: every frame; ``TrackerParams.relocate_interval_s``)."""
    params = TrackerParams(learn=learn).for_live_streams()
    if sources is not None:
        params = replace(params, sources=tuple(sources))
    params = replace(params, locate=replace(params.locate, max_pixels=max_pixels),
                     relocate_interval_s=relocate_interval_s or None)
    return Tracker(model, camera, params, index=index, executor=executor)

"""quatrack.recognition — online work on a trained model: where is the object, in which pose, and
how does it move (Kragic & Kyrki's initialisation, Ude's filter in a video loop).

Entry points:
- ``locate.locate(image, camera, model) -> Located`` (``locate_all`` for every trained object):
  RFCH window search (:mod:`.window_search`) → SIFT matched to every viewset (:mod:`.match`) →
  RANSAC PnP, refinement and covariance (:mod:`.pose`) → verification on what lies inside the
  image (:mod:`.pose`, :mod:`.evidence`).
- ``video.Tracker(model, camera, TrackerParams())`` and ``tracker.step(image, time_s) ->
  TrackStep``: the video tracker, a state machine (:mod:`.tracker.machine`) over measurement
  sources (trained-point and mesh-born KLT, model edges, SIFT re-anchoring) feeding
  :class:`quatrack.tracking.filter.PoseFilter`.
- :mod:`.trackio`: frame sources (file, glob, camera index, URL) and the rows poses leave in
  (CSV, JSON lines, BOP, ROS); :mod:`.overlay`: the one wireframe/label drawer and the track plot.
- :mod:`.images`: decoding and checking user images; :mod:`.runtime`: ``tune_allocator()`` for
  long-running processes.
"""

"""Allocator tuning: applied on glibc, and never over the user's own MALLOC_* settings."""

import platform

import pytest

from quatrack.recognition.runtime import tune_allocator


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_applied_on_glibc(monkeypatch):
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    assert tune_allocator() is True
    with pytest.raises(ValueError):
        tune_allocator(trim_threshold=1 << 40)


def test_users_environment_wins(monkeypatch):
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "0")
    assert tune_allocator() is False


def test_the_warm_up_compiles_every_loop_for_the_types_real_work_uses():
    """``compile_hot_loops`` (the service runs it before it says ready) must compile each numba
    loop for the very argument types that recognition and tracking pass: numba compiles once per
    type signature, so a warm-up on other types (a writable array where the real one is
    read-only, int64 where it is int32) would leave the compilation to the first request.
    After it, locating and tracking the example object add no signature."""
    import cv2
    import numpy as np

    from quatrack.recognition.appearance import _compiled_tile_sums
    from quatrack.recognition.runtime import compile_hot_loops
    from quatrack.recognition.tracker.edges import _compiled_candidates
    from quatrack.recognition.video import Tracker, TrackerParams
    from quatrack.testing.scenes import EXAMPLE, example_model
    from quatrack.tracking.measurements import _compiled_linearize
    from quatrack.viewsets.camera import load_camera
    from quatrack.viewsets.novel import _compiled_lookup
    from quatrack.viewsets.render import _compiled_zbuffer

    from quatrack.tracking.camera import _compiled_distorted_pass

    loops = (_compiled_zbuffer, _compiled_lookup, _compiled_linearize, _compiled_candidates, _compiled_tile_sums,
             _compiled_distorted_pass)
    assert compile_hot_loops() >= 0.0
    before = [set(f().signatures) for f in loops]
    assert all(len(s) >= 1 for s in before)
    model, camera = example_model(), load_camera(EXAMPLE / "camera.json")
    assert not camera.has_distortion  # (the compiled linearisation is for such cameras)
    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    tracker = Tracker(model, camera, TrackerParams())
    statuses = []
    for k in range(4):  # a pose found (locate: the texture check), then tracked (the adjustment)
        ok, frame = cap.read()
        assert ok
        statuses.append(tracker.step(frame, k / 30.0).status)
    assert statuses[0] == "init" and "tracking" in statuses
    # the same through a lens (a calibrated webcam's): the distorted projection, a crop's rays
    from dataclasses import replace

    lens = replace(camera, dist_coeffs=np.array([-0.02, 0.0, 0.0, 0.0, 0.0]))
    tracker = Tracker(model, lens, TrackerParams())
    cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
    statuses = [tracker.step(cap.read()[1], k / 30.0).status for k in range(3)]
    assert statuses[0] == "init" and "tracking" in statuses
    assert [set(f().signatures) for f in loops] == before

"""Process-wide tuning for numpy-heavy, latency-bound work: the per-frame recognition and tracking
loops allocate frame-sized arrays (:func:`tune_allocator`) and run many small BLAS products
(:func:`limit_blas_threads`). Lives in the recognition layer so that both the command line
and the service (the layers above) import it downward."""

from __future__ import annotations

import ctypes
import ctypes.util
import os

_M_TRIM_THRESHOLD = -1  # glibc mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3
_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
_BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def tune_allocator(mmap_threshold: int = 16 << 20, trim_threshold: int = 64 << 20) -> bool:
    """Keep freed blocks up to ``mmap_threshold`` bytes in the heap, and up to
    ``trim_threshold`` free bytes at its top, instead of handing them back to the OS.

    Why: by default glibc returns large blocks (``munmap``, heap trimming), so the next
    frame's arrays of the same sizes fault all their pages in again. Measured on the 2-core
    machine: a 640×480 localisation took 13 ms warm but 18 ms right after a SIFT pass, and
    13 ms in both cases with this setting. The cost is up to ``trim_threshold`` of idle heap
    per allocator arena (one per busy thread, bounded by the service's worker count).

    Returns whether the setting was applied: not on a non-glibc system, and not when the
    user set ``MALLOC_MMAP_THRESHOLD_`` or ``MALLOC_TRIM_THRESHOLD_`` (theirs wins).
    """
    for v in (mmap_threshold, trim_threshold):
        if not 0 <= int(v) < 2**31:
            raise ValueError(f"allocator threshold {v} outside 0 … 2³¹ − 1 bytes")
    if any(v in os.environ for v in _ENV):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold)) and mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)))


def limit_blas_threads(threads: int = 1) -> bool:
    """Let the BLAS libraries behind numpy and scipy use at most ``threads`` threads.

    Why: recognition's BLAS products are small — the RFCH labelling multiplies a (32 × 10) by a
    (10 × 2048) matrix per block of pixels, 38 blocks per 640×480 frame — and OpenBLAS splits
    each across every core, whose threads then wait for each other. Measured on the 2-core
    machine with other jobs running (load 7): 1.7 ms per product with two threads, 0.14 ms with
    one, which made the window search 5× slower; the quiet machine's localisation went from
    ≈ 26 to ≈ 17 ms p50 with the other speed work (quiet reruns in bench/RESULTS.md). OpenCV and the service's workers use
    the cores instead.

    Libraries already loaded are limited now (threadpoolctl); ``OPENBLAS_NUM_THREADS`` is set
    for those loaded later (scipy's own OpenBLAS, say). Returns whether the limit was applied:
    not when the user set ``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS`` or
    ``BLIS_NUM_THREADS`` (theirs wins).
    """
    if int(threads) < 1:
        raise ValueError(f"BLAS threads {threads} < 1")
    if any(v in os.environ for v in _BLAS_ENV):
        return False
    from threadpoolctl import threadpool_limits

    os.environ["OPENBLAS_NUM_THREADS"] = str(int(threads))
    threadpool_limits(int(threads), user_api="blas")
    return True


def compile_hot_loops() -> float:
    """Run each loop that numba compiles (:mod:`quatrack.tracking.jit`: the z-buffer, the
    texture lookup, the point block's linearisation, the 1-D edge search, the texture evidence's
    block sums, the distorted projection) once on a small box, so that its
    compilation happens now and not in the first request's frame; returns the seconds taken.

    Why: numba compiles a loop at its first call and keeps the machine code on disk. Where no
    cache exists yet — a fresh container, a read-only install — the first call costs 0.5–2 s
    per loop (measured: the linearisation 1.6 s). In the service the first tracked frame of
    the first session would pay all of it. The service calls this while ``/readyz`` still
    says "not ready". With a cache it takes a few milliseconds per loop.
    """
    import time

    import numpy as np

    from quatrack.recognition.appearance import tile_correlations
    from quatrack.recognition.tracker.edges import edge_candidates
    from quatrack.tracking.camera import PinholeCamera
    from quatrack.tracking.measurements import PointMeasurements
    from quatrack.tracking.pose import Pose
    from quatrack.viewsets.mesh import make_mesh
    from quatrack.viewsets.novel import render_textured_view
    from quatrack.viewsets.render import render, render_window

    t0 = time.perf_counter()
    corners = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    faces = [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
             [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]]
    box = make_mesh(corners, np.array(faces), "warm-up box")
    camera = PinholeCamera(60.0, 60.0, 32.0, 24.0, width=64, height=48)
    pose = Pose.from_rvec([0.4, -0.5, 0.1], [-0.5, -0.5, 4.0])
    buffers = render(box, camera, pose)
    render_window(box, camera, pose, (8, 8, 40, 32))  # (a window's rays are a writable copy: another signature)
    photo = np.full((48, 64), 128, np.uint8)
    render_textured_view(box, box.plane_ids, photo, camera, pose, buffers, camera, pose)
    X = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    block = PointMeasurements.create(camera, X, np.array([[30.0, 20.0], [34.0, 28.0]]), 1.0)
    block.linearize(pose.t, pose.R)
    g = np.zeros((48, 64), np.float32)
    edge_candidates(g, g, np.array([[30.0, 20.0]]), np.array([[1.0, 0.0]]), np.array([4.0]), 6.0, 0.5)
    tile_correlations(g, g, g > 0, 8)
    # a camera with lens distortion: its projection, and a crop's rays (a read-only slice of the
    # whole image's: another signature of the texture lookup)
    lens = PinholeCamera(60.0, 60.0, 32.0, 24.0, np.array([-0.1, 0.01, 0.0, 0.0, 0.0]), width=64, height=48)
    lens.project_with_jacobian(X + [0.0, 0.0, 4.0])  # (project() calls the same pass, the same types)
    render_textured_view(box, box.plane_ids, photo, lens, pose, render(box, lens, pose), lens.cropped(4, 4, 60, 44), pose)
    return time.perf_counter() - t0

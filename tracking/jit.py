"""Loops compiled on first use (numba), for the few hot paths numpy cannot vectorise cheaply.

A compiled loop here repeats the numpy code it replaces expression for expression, so it gives
the same bits: numba, without ``fastmath``, neither reorders floating-point operations nor fuses
``a·b + c`` into one rounding. Each use keeps its numpy original beside it and a test compares
the two (tests/test_viewsets_render.py, tests/test_measurements.py,
tests/test_recognition_histograms.py). One exception: the block
sums of :func:`quatrack.recognition.appearance.tile_correlations` add the pixels in scan order,
not in numpy's, so they agree to ~1e-12 (tests/test_appearance.py).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Callable


def lazily_compiled(fn: Callable) -> Callable[[], Callable]:
    """A function returning ``fn`` compiled by numba (``njit``), compiled on the first call:
    numba is imported then (~0.5 s that commands which never need it do not pay). The machine
    code is cached on disk beside ``fn``'s module (``cache=True``: ~1 s to compile once, ~0.2 s
    to load afterwards), or compiled per process where no cache location is writable (a
    read-only install without a home directory). ``nogil``: a background job (re-anchoring, a
    keyframe's views) runs it beside the frame's step. ``.cache_clear()`` forgets the compiled
    function (tests).

    >>> def twice(x):
    ...     return 2 * x
    >>> lazily_compiled(twice)()(21)
    42
    """

    @lru_cache(maxsize=1)
    def compiled() -> Callable:
        import numba

        try:
            return numba.njit(cache=True, nogil=True)(fn)
        except RuntimeError:  # no writable cache location: compile in this process
            return numba.njit(nogil=True)(fn)

    return compiled

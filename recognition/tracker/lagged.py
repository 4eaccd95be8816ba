"""A deterministic stand-in for a live stream's background executor.

In a live stream (the service) the tracker's slow jobs — SIFT re-anchoring, lifting a keyframe
or a learned view, a keyframe's synthetic views — run on an executor beside the next frames'
steps (``TrackerParams.pipelined_refresh``), and a later step keeps their result. A thread pool
makes *which* later step depend on the machine's speed and load, so two runs of one video differ.
:class:`LaggedExecutor` runs each job between steps, exactly ``lag`` steps after the one that
submitted it, and times it: the tracker sees what a live stream with a free core sees (a job's
result a fixed number of frames late), the results are the same on every machine, and the
foreground step's time is measured apart from the background's (``quatrack bench track-zoo``).

The driver calls :meth:`LaggedExecutor.tick` once after each step:

>>> ex = LaggedExecutor(lag=2)
>>> f = ex.submit(sum, [1, 2, 3])
>>> f.done(), ex.tick(), f.done(), ex.tick() >= 0.0, f.result()
(False, 0.0, False, True, 6)

A job still queued can be cancelled, as with a thread pool:

>>> g = ex.submit(sum, [4])
>>> g.cancel(), ex.tick(), ex.tick()
(True, 0.0, 0.0)
"""
from __future__ import annotations

import math
import numbers
import time
from concurrent.futures import Executor, Future


class LaggedExecutor(Executor):
    """Runs each submitted job at the ``lag``-th :meth:`tick` after its submission, in the
    caller's thread; :meth:`tick` returns the CPU milliseconds that tick's jobs took.

    ``lag`` ≥ 1, a whole number of steps: with 1 a job's result is there at the very next step
    (a background core that keeps up with the frame rate); 2 (the default) is a ~45 ms job at
    30 fps (``2.0`` is 2). A fraction of a step has no meaning here (jobs run between steps) and
    is refused: ``lag=1.5`` was taken as 1 without a word."""

    def __init__(self, lag: int = 2) -> None:
        whole = isinstance(lag, numbers.Real) and not isinstance(lag, bool) and math.isfinite(lag) and float(lag).is_integer()
        if not whole or lag < 1:
            raise ValueError(f"lag must be a whole number of steps, at least 1, got {lag!r}")
        self.lag = int(lag)
        self._queue: list[tuple[int, Future, object, tuple, dict]] = []
        self._ticks = 0
        self.background_ms: list[float] = []  # per tick, the CPU its jobs took

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        self._queue.append((self._ticks + self.lag, future, fn, args, kwargs))
        return future

    def tick(self) -> float:
        """One step has passed: run the jobs that are due (in submission order)."""
        self._ticks += 1
        due = [job for job in self._queue if job[0] <= self._ticks]
        self._queue = [job for job in self._queue if job[0] > self._ticks]
        t0, ran = time.process_time(), False
        for _, future, fn, args, kwargs in due:
            if not future.set_running_or_notify_cancel():  # cancelled while queued
                continue
            ran = True
            try:
                future.set_result(fn(*args, **kwargs))
            except BaseException as exc:  # (delivered through the future, as a pool does)
                future.set_exception(exc)
        ms = (time.process_time() - t0) * 1e3 if ran else 0.0
        self.background_ms.append(ms)
        return ms

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Run (``wait``) or drop what is still queued."""
        while self._queue:
            if cancel_futures or not wait:
                for _, future, *_ in self._queue:
                    future.cancel()
                self._queue = []
            else:
                self.tick()

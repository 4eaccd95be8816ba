"""Pyramidal Lucas–Kanade point tracking with a forward–backward check (Kalal et al. 2010).

A point is kept only if tracking it forward and then back lands within ``fb_max_px`` of where it
started: that rejects points that slid along an edge, left the view, or changed appearance.
The backward pass starts at the point's origin (where a right forward track leads back), so it
needs no coarse pyramid levels (``fb_levels``); LK's cost is per point and per level.
(OpenCV 5's Python binding no longer takes prebuilt pyramids, so LK builds them per call.)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class KLTParams:
    # window side, pixels. LK's time is not monotonic in it (OpenCV 5, one thread, a call with
    # 285 points of box.mp4 forward and back: 21 px 8.0 ms, 17 px 4.4, 16 px 3.6, 15 px 6.0,
    # 13 px 4.5; rows seem to be done in vectors of 8 px plus a scalar tail). 21 until session
    # 43: on the 24 zoo walks 17 px lost as many frames (live: 10 % fewer), with 0 poses beyond
    # 5 %/5° (21 px: 2; live 2 against 3) and lower mean errors on most shapes (bench/RESULTS.md,
    # session 43; tried in session 33, it had let a doubted drift through, which the audits
    # added since catch)
    win: int = 17
    levels: int = 3  # pyramid levels above the image
    fb_max_px: float = 1.0  # forward–backward error tolerated
    # pyramid levels of the backward pass (None: ``levels``). It starts where the point came
    # from, so on a right forward track it has nothing to search: the image level alone gives
    # the same verdicts at ~60 % of the forward–backward cost (bench/RESULTS.md, step time)
    fb_levels: int | None = 0
    max_iterations: int = 20
    epsilon: float = 0.03


@dataclass(frozen=True)
class Frame:
    """A grey 8-bit frame and its size (w, h)."""

    gray: np.ndarray
    size: tuple[int, int]


def make_frame(gray: np.ndarray) -> Frame:
    return Frame(np.ascontiguousarray(gray), (gray.shape[1], gray.shape[0]))


def track_points(
    prev: Frame, cur: Frame, points: np.ndarray, guess: np.ndarray | None = None,
    params: KLTParams = KLTParams(),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track ``points`` (n, 2) from ``prev`` to ``cur``; ``guess`` (n, 2) is where they are expected
    (e.g. projected at the predicted pose), so fast but predictable motion stays within reach.

    Returns ``(new_points (n, 2), ok (n,), fb_error (n,))``.
    """
    n = len(points)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0)
    p0 = np.ascontiguousarray(points, np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.max_iterations, params.epsilon)
    win = (params.win, params.win)
    flags = 0
    p1 = None
    if guess is not None:
        p1 = np.ascontiguousarray(guess, np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev.gray, cur.gray, p0, p1, winSize=win,
                                          maxLevel=params.levels, criteria=crit, flags=flags)
    back = p0.copy()
    back_levels = params.levels if params.fb_levels is None else params.fb_levels
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur.gray, prev.gray, p1, back, winSize=win,
                                           maxLevel=back_levels, criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1 = p1.reshape(-1, 2).astype(float)
    fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    w, h = cur.size
    inside = (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < params.fb_max_px) & inside & np.isfinite(fb)
    return p1, ok, fb

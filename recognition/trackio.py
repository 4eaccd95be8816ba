"""Track input and output: where frames come from, and the rows and files poses leave in.

Every consumer of a track — ``quatrack track``, ``quatrack demo``, the Python client, the
benchmarks and the tests — reads frames and writes poses through this module, so the rules below
hold everywhere:

- **Frame sources** (:func:`open_frames`): a video file, a glob of images (sorted by name; or
  several globs or files, as a shell expands an unquoted glob), a camera index (``"0"``) or
  device (``/dev/video0``), a FIFO, or any URL ``cv2.VideoCapture`` opens (``rtsp://``,
  ``http://``, ...; its password masked in every message: :func:`masked`). An image of a sequence that
  cannot be read is skipped, listed with its index and time (:attr:`FrameSource.skipped`). A video
  file's frames are given as recorded: its rotation metadata is not applied (the camera file
  describes the sensor), and a :class:`SourceWarning` names it.
- **Frame rate and time**: ``rate`` is the user's ``--fps`` if given, else the rate the container
  reports if it is finite and in (0, 1000], else 30. An image sequence's ``time_s = index / rate``;
  so is a video file's when ``--fps`` is given (the user says the rate). Else a video file's frame
  is timed by its container timestamp (``CAP_PROP_POS_MSEC``) — a variable-frame-rate video keeps
  its gaps — when its first :data:`STAMP_CHECK_FRAMES` frames' timestamps increase (a file whose
  B-frames carry their decoding order's times does not: ``index / rate`` then), and up to the
  first that does not; a frame without one (not decoded, or after that) comes a period after the
  frame before. A URL of a recorded video (``http://host/box.mp4``, ``file:///...``: its capture
  states a frame count and its frames carry container timestamps) is timed and ends as a file
  (though read in a thread as a live source is). A live
  source (camera index or device, FIFO, other URL) without ``--fps`` is timed by the clock instead: ``time_s`` =
  monotonic seconds from the moment its first frame was grabbed (its read returned, in the
  capture thread) to the moment this one was, since a camera drops and delays frames — not when
  the tracker took it (the first frame is read as the source opens, before the tracker is built).
  Frames buffered by the driver or FFmpeg while the tracker was busy are read at once, so their
  times come out compressed (:class:`LiveCapture` reads no frame ahead).
- **Live sources** are read in a thread of their own (:class:`LiveCapture`), one frame at a time
  as the consumer asks: a read blocked in OpenCV (a stalled stream) no longer holds off Ctrl-C or
  SIGTERM, and a source that gives no frame for ``stall_timeout_s`` (default
  :data:`STALL_TIMEOUT_S`) ends, saying so (:attr:`FrameSource.ended`). A frame that fails to
  decode (a corrupt JPEG part of an MJPEG stream) followed by another is skipped, not the end.
- FFmpeg's decoder warnings (``[h264 @ ...] A non-intra slice ...``) are kept out of the user's
  terminal: ``OPENCV_FFMPEG_LOGLEVEL`` is set (unless the user set it) before the first capture.
- **Rows**: one in-memory record per frame, :class:`~recognition.video.TrackStep`; the service's
  per-frame JSON message converts to and from it (:func:`step_message`, :func:`step_from_message`).
  Rows out: the contract's CSV (:data:`CSV_COLUMNS`), JSON lines (the full message), BOP results
  (``scene_id,im_id,obj_id,score,R,t,time``) and ROS ``geometry_msgs/PoseWithCovarianceStamped``.
- **Files** are written atomically (:func:`atomic_path`): to a temporary file beside the target,
  renamed into place only when complete, so an error or Ctrl-C never leaves half a file.
  A target that exists and is not a regular file (``/dev/null``, ``/dev/stdout``, a FIFO) is
  written in place.
- A **progress line** (:class:`Progress`) on stderr when it is a terminal, silent otherwise.
"""

from __future__ import annotations

import collections
import contextlib
import glob as globlib
import itertools
import json
import math
import numbers
import os
import queue
import re
import sys
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.pose import Pose

CSV_COLUMNS = ("frame", "time_s", "status", "tx", "ty", "tz", "qw", "qx", "qy", "qz",
               "vx", "vy", "vz", "wx", "wy", "wz", "inliers")
CSV_HEADER = ",".join(CSV_COLUMNS)
BOP_COLUMNS = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")
FORMATS = ("csv", "jsonl", "bop")
DEFAULT_RATE = 30.0
MAX_RATE = 1000.0
MIN_RATE = 1e-6  # frames/s: one frame in 11.6 days
#: metres per mesh unit, for the outputs with fixed units (BOP: mm, ROS: m)
UNIT_METRES = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


class SourceError(ValueError):
    """A frame source that cannot be used; the message names it (one line for the user)."""


class SourceEnded(SourceError):
    """The last item of a live source's frames when it ended by itself: the message says why."""


class SourceWarning(UserWarning):
    """Something about a frame source the user should know, which does not stop the run (``quatrack``
    prints it as ``quatrack track: warning: ...``)."""


class SourceStalled(SourceError):
    """A live source gave no frame (or no answer to its opening) within its timeout."""


#: seconds a live source may give no frame before it is taken for stalled and the run ends
#: (``--stall-timeout``); FFmpeg's own network timeout is set a little above it, so the thread
#: left blocked in a read comes back and lets the capture go
STALL_TIMEOUT_S = 30.0
#: consecutive failed reads of a live source before it is taken for ended: one corrupt JPEG part
#: of an MJPEG stream fails one read and the next frame comes (the run ended there, silently);
#: a stream closed or dropped fails every read at once
LIVE_BAD_RUN = 5


# --- frame sources ------------------------------------------------------------------------------

def quiet_ffmpeg() -> None:
    """Keep FFmpeg's decoder chatter off stderr. OpenCV reads ``OPENCV_FFMPEG_LOGLEVEL`` once,
    when its FFmpeg backend starts (the first capture), so call this before opening one; a
    value the user set is kept."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET


def open_capture(target: int | str, timeout_s: float | None = None):
    """``cv2.VideoCapture(target)``: the one place captures are made (tests replace it to fake a
    camera). ``timeout_s``: for a URL, FFmpeg's network timeout for opening and for each read
    (its default is 30 s)."""
    import cv2

    quiet_ffmpeg()
    # (a camera index or URL it cannot open made OpenCV print "[ WARN:0@0.5] global cap_v4l.cpp:914
    # open VIDEOIO(V4L2:/dev/video7): can't open camera by index" and more above the one-line error)
    log = cv2.utils.logging
    previous = log.getLogLevel()
    log.setLogLevel(min(previous, log.LOG_LEVEL_ERROR))
    try:
        if timeout_s is not None and isinstance(target, str) and "://" in target:
            ms = int(min(timeout_s, 86400) * 1000)
            return cv2.VideoCapture(target, cv2.CAP_ANY,
                                    [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms])
        return cv2.VideoCapture(target)
    finally:
        log.setLogLevel(previous)


CAPTURE_THREAD = "capture"  # the first word of a live capture's thread name (the CLI's exit waits less for it)


class LiveCapture:
    """A live source's capture, every call of it (open, ``read``, ``get``, ``release``) run in one
    daemon thread of its own while the caller waits at most ``timeout_s`` for it.

    Why: a read of a stalled stream blocks inside OpenCV (FFmpeg gives up after 30 s), where
    Python runs no signal handler: Ctrl-C and SIGTERM took effect only when the read returned,
    and the stall itself ended the run without a word (and with OpenCV's "Stream timeout
    triggered" warning on stderr). Here the caller waits in Python, so a signal stops it at
    once, and a call that does not return in time raises :class:`SourceStalled`. Calls run one
    at a time, in order: :meth:`release` while a read is blocked is queued behind it (a capture
    released under a running read is a crash), so it happens when the read comes back. The
    frames are read as the caller asks, one at a time, as a capture of its own would be (no
    read-ahead: the same frames, and a stop after ``N`` frames reads no more). An exception of the
    call (a test's camera raising ``KeyboardInterrupt``) is raised in the caller.

    :attr:`grabbed_at` is the :attr:`clock` reading taken in the capture thread as the latest
    ``read`` returned. That is the frame's capture time only when no frame waited: the read is made
    when the caller asks, so frames the driver or FFmpeg buffered while the caller was busy (a
    camera's few V4L2 buffers, a stream's packets) come out of reads that return at once, their
    times closer together than they were captured (nothing read ahead, nothing dropped)."""

    clock: Callable[[], float] = staticmethod(time.monotonic)

    def __init__(self, target: int | str, timeout_s: float = STALL_TIMEOUT_S) -> None:
        self.target, self.timeout_s = target, timeout_s
        self._calls: queue.SimpleQueue = queue.SimpleQueue()
        self._released = False
        self.grabbed_at: float | None = None
        #: called (in the caller's thread) about every 0.1 s while it waits: a progress line's tick
        self.on_wait: Callable[[], None] | None = None
        threading.Thread(target=self._serve, name=f"{CAPTURE_THREAD} {masked(str(target))}", daemon=True).start()
        # FFmpeg's own timeout a little after ours: the thread left in a blocked read comes back
        self.cap = self._call(lambda: open_capture(target, timeout_s + 5.0), what="answer")

    def _serve(self) -> None:
        import cv2

        log = cv2.utils.logging  # ("[ WARN:0@31.8] global cap_ffmpeg_impl.hpp:453 ... Stream timeout triggered")
        previous = log.getLogLevel()
        log.setLogLevel(min(previous, log.LOG_LEVEL_ERROR))
        try:
            while True:
                fn, box = self._calls.get()
                if fn is None:
                    return
                try:
                    box.put((True, fn()))
                except BaseException as exc:  # (KeyboardInterrupt too: the caller's)
                    box.put((False, exc))
        finally:
            log.setLogLevel(previous)

    def _call(self, fn: Callable[[], Any], what: str = "a frame") -> Any:
        box: queue.SimpleQueue = queue.SimpleQueue()
        self._calls.put((fn, box))
        deadline = time.monotonic() + self.timeout_s
        while True:  # (in slices: a signal delivered to another thread is seen within 0.1 s)
            try:
                ok, value = box.get(timeout=max(0.0, min(0.1, deadline - time.monotonic())))
                break
            except queue.Empty:
                if time.monotonic() >= deadline:
                    raise SourceStalled(f"no {what} within {self.timeout_s:g} s") from None
                if self.on_wait is not None:
                    self.on_wait()
        if not ok:
            raise value
        return value

    def isOpened(self) -> bool:
        return bool(self._call(self.cap.isOpened))

    def read(self):
        return self._call(self._read)

    def _read(self):
        """(In the capture thread.) The capture's read, its time noted as it returns."""
        result = self.cap.read()
        self.grabbed_at = self.clock()
        return result

    def get(self, prop: int) -> float:
        return self._call(lambda: self.cap.get(prop))

    def release(self) -> None:
        """Let the capture go (after any call still running) and end the thread; waits for it only
        while nothing blocks it."""
        if self._released:
            return
        self._released = True
        box: queue.SimpleQueue = queue.SimpleQueue()
        cap = getattr(self, "cap", None)
        self._calls.put(((cap.release if cap is not None else (lambda: None)), box))
        self._calls.put((None, None))
        try:
            box.get(timeout=0.5)
        except queue.Empty:  # (a read still blocked: it releases when that read comes back)
            pass


def frame_rate(given: float | None, reported: float | None = None) -> float:
    """The module's rule: ``given`` (``--fps``) if set, else ``reported`` (the container's) if
    finite and in (0, 1000], else 30 frames/s.

    >>> frame_rate(None, 29.97), frame_rate(12.0, 29.97), frame_rate(None, 0.0), frame_rate(None, float("nan"))
    (29.97, 12.0, 30.0, 30.0)
    """
    if given is not None:
        return float(given)
    if reported is not None and math.isfinite(reported) and 0 < reported <= MAX_RATE:
        return float(reported)
    return DEFAULT_RATE


_USER_INFO = re.compile(r"^(\s*[A-Za-z][A-Za-z0-9+.-]*://)([^/?#]*)@")


def masked(video: str) -> str:
    """``video`` as shown to the user: a URL's user-info (``rtsp://user:pass@host/...``) masked as
    ``user:***@`` (a lone token as ``***@``), so no password is printed in a message, a progress
    line or a row's ``reason``; anything else as given.

    >>> masked("rtsp://admin:s3cret@10.0.0.2/live"), masked("http://tok@cam/x"), masked("0")
    ('rtsp://admin:***@10.0.0.2/live', 'http://***@cam/x', '0')
    """
    def hide(m: re.Match) -> str:  # (group 2: up to the host's "@", the last one: a password may hold "@")
        user, sep, _ = m.group(2).partition(":")
        return f"{m.group(1)}{user + ':' if sep else ''}***@"

    return _USER_INFO.sub(hide, video, count=1)


def _special(path: str) -> str | None:
    """``"camera"`` for a character device (``/dev/video0``), ``"stream"`` for a FIFO (a pipe
    another program writes a stream into), else None."""
    import stat

    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    return "camera" if stat.S_ISCHR(mode) else "stream" if stat.S_ISFIFO(mode) else None


def live_kind(target: int | str) -> str | None:
    """What live source ``target`` (:func:`capture_target`'s) is: ``"camera"`` (an index, a
    character device such as ``/dev/video0``), ``"stream"`` (a URL, a FIFO), or None for a file."""
    if not isinstance(target, str):
        return "camera"
    return "stream" if "://" in target else _special(target)


def capture_target(video: str) -> int | str:
    """What ``--video`` names: a camera index (all digits) or a URL (has ``://``) as given, a
    character device (``/dev/video0``: a camera) or a FIFO (a stream) as given; else a file, which
    must exist (a device or FIFO was refused as "no such file").

    >>> capture_target("0"), capture_target("rtsp://10.0.0.2/stream"), capture_target("/dev/null")
    (0, 'rtsp://10.0.0.2/stream', '/dev/null')
    """
    text = video.strip()
    if text.isdigit():
        return int(text)
    if "://" in text or _special(text) is not None:
        return text
    if os.path.isdir(text):  # (was "no such file": a folder of frames is --images)
        raise SourceError(f"--video {video}: is a folder; for its images give --images "
                          f"{os.path.join(video, '*.png')!r}")
    if not os.path.isfile(text):
        raise SourceError(f"--video {video}: no such file (give a file, a camera index such as 0, or a stream URL)")
    if os.path.getsize(text) == 0:  # (was "cannot be opened as a video": an interrupted copy or recording)
        raise SourceError(f"--video {video}: the file is empty (0 bytes)")
    return text


@dataclass
class FrameSource:
    """Frames ``(index, time_s, image)`` of one source; iterate once, then :meth:`close` (or use
    ``with``). ``names`` holds the file of each frame for an image sequence."""

    label: str  # how the user named it, for messages: "--video box.mp4"
    rate: float
    live: bool = False
    names: list[str] | None = None
    max_frames: int | None = None
    _frames: Iterator[np.ndarray | Exception] | None = None
    _close: Callable[[], None] = lambda: None
    _clock: Callable[[], float] = time.monotonic
    # a live source's: the time its latest frame was grabbed (LiveCapture.grabbed_at), which times
    # its frames in place of the clock read when the consumer takes each
    _stamp: Callable[[], float | None] | None = None
    # a video file's: the container's time (s) of the frame just decoded (CAP_PROP_POS_MSEC), which
    # times its frames where it is usable (see :meth:`_file_time`); None: index / rate
    _pos: Callable[[], float | None] | None = None
    # a live capture's: sets the function it calls while it waits for a frame (LiveCapture.on_wait)
    _watch: Callable[[Callable[[], None] | None], None] | None = None
    _anchor: tuple[int, float] = field(default=(0, 0.0), init=False)
    _last_stamp: float | None = field(default=None, init=False)
    count: int = field(default=0, init=False)
    # frames that could not be read (an image sequence's unreadable file), skipped with their
    # index and time: ``(index, time_s, why)``; the frames after them keep their own index and time
    skipped: list[tuple[int, float, str]] = field(default_factory=list, init=False)
    #: why a live source ended before it was stopped (it stalled, closed, dropped), else None
    ended: str | None = field(default=None, init=False)

    def __iter__(self) -> Iterator[tuple[int, float, np.ndarray]]:
        t0, t = None, 0.0
        try:
            while self.max_frames is None or self.count < self.max_frames:  # (checked before the next read:
                image = next(self._frames, None)  # a live source's frame N+1 was waited for, a stalled one's 30 s)
                if image is None:
                    break
                if isinstance(image, SourceEnded):
                    self.ended = str(image)
                    break
                i = self.count
                if self.live:  # (a failed read: the time it returned, noted by decoded_frames)
                    now = getattr(image, "grabbed_at", None) if isinstance(image, Exception) else None
                    now = self._stamp() if now is None and self._stamp is not None else now
                    now = self._clock() if now is None else now
                    t0 = now if t0 is None else t0
                    t = now - t0 if i == 0 else max(now - t0, t + 1e-6)  # strictly increasing for the filter
                else:
                    t = self._file_time(i, t, image)
                self.count += 1
                if isinstance(image, Exception):  # (the frame's source said why it cannot be read)
                    self.skipped.append((i, t, str(image)))
                    continue
                yield i, t, image
        finally:
            self.close()

    def _file_time(self, i: int, previous: float, image) -> float:
        """Frame ``i``'s ``time_s`` in a video file: its container timestamp (``_pos``) while the
        timestamps increase; from the first that does not (missing, 0, out of order) on, and for a
        frame that failed to decode (the capture has read past it), a frame period after the
        frame before (no timestamps at all: ``index / rate``).

        Why: a variable-frame-rate video (a phone's, as most are) has frames 0.5 s apart among
        frames 33 ms apart; ``index / rate`` lost the gap and put every later frame early."""
        stamp = None
        if self._pos is not None and not isinstance(image, Exception):
            with contextlib.suppress(TypeError, ValueError):
                stamp = float(self._pos())
            if stamp is None or not (math.isfinite(stamp) and stamp >= 0
                                     and (self._last_stamp is None or stamp > self._last_stamp)):
                self._pos = stamp = None  # (not trusted from here on: periods from the last good one)
        if stamp is None:
            at, anchored = self._anchor
            return anchored + (i - at) / self.rate
        self._last_stamp = stamp
        t = stamp if i == 0 or stamp > previous else previous + 1e-6  # (after a failed frame's guess)
        self._anchor = (i, t)
        return t

    def on_wait(self, fn: Callable[[], None] | None) -> None:
        """Have ``fn`` called about every 0.1 s while a live source waits for its next frame (a
        progress line's :meth:`Progress.tick`: a stall shows as it lasts); nothing for files."""
        if self._watch is not None:
            self._watch(fn)

    def where(self, index: int) -> str:
        """Name frame ``index`` for an error message."""
        return self.names[index] if self.names else f"frame {index} of {self.label}"

    def close(self) -> None:
        self._close()

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: an ``--images`` file with one of these endings lists the images, one per line
LIST_SUFFIXES = (".txt", ".lst")


def list_file(path: str) -> list[str]:
    """The images a list file names, one per line, in its order (``--images frames.txt``: it was
    read as an image, "no frame can be read"). Blank lines and lines starting with ``#`` are
    skipped; a relative path is relative to the list's folder (as a spec's paths are to the spec);
    ``~`` is expanded. A listed file that is missing stays: its row says ``lost``."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            lines = [line.strip() for line in f]
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"--images {path}: cannot read the list ({exc.__class__.__name__}: {exc})"[:300]) from None
    folder = os.path.dirname(path)
    return [os.path.join(folder, os.path.expanduser(line)) for line in lines if line and not line.startswith("#")]


def glob_files(pattern: str) -> list[str]:
    """The files (not folders) a glob matches, sorted by name: the order of ``--images`` (the
    contract's) and of ``locate``'s quoted globs. A pattern that matches nothing is tried again
    with its folder taken literally: ``/data/run[2]/*.png`` (a folder named with ``[ ] * ?``) gave
    "no file matches", ``[2]`` read as a character class."""
    found = sorted(p for p in globlib.glob(pattern) if os.path.isfile(p))
    folder, name = os.path.split(pattern)
    if not found and globlib.has_magic(folder):
        found = sorted(p for p in globlib.glob(os.path.join(globlib.escape(folder), name)) if os.path.isfile(p))
    return found


def image_paths(patterns: str | Sequence[str]) -> list[str]:
    """The files of ``--images``: each glob (``~`` expanded) sorted by name, in the order given, or
    a file as the shell gave it (``[1].png`` is no pattern then), or the files a list file names
    (``.txt``, ``.lst``: :func:`list_file`); each file once, first place kept. :func:`open_frames` reads these; ``track`` checks its outputs against them.
    A file named that is missing (no pattern, no folder) stays, as a list's missing line does: its
    frame is a ``lost`` row in its place (it was left out, and the frames after it came one index
    early). ``locate`` expands its IMAGE arguments with this too, one at a time."""
    paths: list[str] = []
    for path in _expanded(patterns):
        if os.path.isfile(path) and path.lower().endswith(LIST_SUFFIXES):
            paths += list_file(path)
        elif os.path.isfile(path) or not (globlib.has_magic(path) or os.path.isdir(path)):
            paths.append(path)
        else:
            paths += glob_files(path)
    return list(dict.fromkeys(paths))


def _expanded(patterns: str | Sequence[str]) -> list[str]:
    """``--images``' arguments (one string or several), each with ``~`` expanded."""
    return [os.path.expanduser(p) for p in ([patterns] if isinstance(patterns, str) else patterns)]


def _numbered(path: str) -> list:
    """A sort key reading the numbers in a path as numbers: ``frame_2`` before ``frame_10``."""
    return [(int(part), "") if part.isdigit() else (-1, part) for part in re.split(r"(\d+)", path)]


def _first_descent(files: Sequence[str]) -> tuple[str, str] | None:
    """The first two neighbours of ``files`` whose numbers (:func:`_numbered`) go down, or None."""
    return next(((a, b) for a, b in zip(files, files[1:]) if _numbered(b) < _numbered(a)), None)


def misordered(patterns: str | Sequence[str]) -> tuple[str, str] | None:
    """The first two files of a glob of ``--images`` that its order by name (the contract's
    order) puts otherwise than their numbers do — ``frame_10.png`` before ``frame_2.png``, as
    numbered without leading zeros — or None. The frames are read by name as the contract says;
    the caller warns, since such a sequence is tracked in a jumbled order.

    >>> import tempfile
    >>> d = tempfile.mkdtemp()
    >>> for n in (1, 2, 10):
    ...     _ = open(os.path.join(d, f"f{n}.png"), "w")
    >>> [os.path.basename(p) for p in misordered(os.path.join(d, "*.png"))]
    ['f10.png', 'f2.png']
    >>> import shutil; shutil.rmtree(d)
    """
    globs = (path for path in _expanded(patterns) if not os.path.isfile(path))
    return next((pair for path in globs if (pair := _first_descent(glob_files(path))) is not None), None)


def _jumbled(files: list[str]) -> tuple[str, str] | None:
    """The first two of ``files`` in the wrong order by their numbers, when ``files`` are one
    numbered sequence (at least 3, names alike but for their numbers) in neither ascending nor
    descending order — as a shell's or ``ls``'s sort by name leaves ``f_1 f_10 f_2`` — else None.

    >>> _jumbled(["f_1.png", "f_10.png", "f_2.png"]), _jumbled(["f_3.png", "f_2.png", "f_1.png"])
    (('f_10.png', 'f_2.png'), None)
    """
    if len(files) < 3 or len({re.sub(r"\d+", "#", f) for f in files}) != 1:
        return None
    pair = _first_descent(files)  # (None: ascending)
    return None if pair is None or _first_descent(files[::-1]) is None else pair  # (descending: None too)


def numbering_gap(files: Sequence[str]) -> tuple[str, str, int] | None:
    """The first two neighbours of a numbered sequence (names alike but for one number, which goes
    up) whose numbers step further than the sequence's usual step (the step of more than half its
    neighbours, at least two), with the count of numbers missing between them, or None.

    Why: an image's ``time_s`` is its index / rate, so ``frame_0004`` then ``frame_0007`` put every
    frame after the gap two frames early, without a word.

    >>> numbering_gap(["f_1.png", "f_2.png", "f_5.png", "f_6.png"]), numbering_gap(["f_0.png", "f_5.png", "f_10.png"])
    (('f_2.png', 'f_5.png', 2), None)
    """
    steps: list[tuple[int, str, str]] = []
    for a, b in zip(files, files[1:]):
        na, nb = ([int(x) for x in re.findall(r"\d+", f)] for f in (a, b))
        differ = [(x, y) for x, y in zip(na, nb) if x != y]
        if len(na) != len(nb) or re.sub(r"\d+", "#", a) != re.sub(r"\d+", "#", b) or len(differ) != 1 \
                or differ[0][1] <= differ[0][0]:
            return None  # (not one numbered sequence going up: misordered's business, or none)
        steps.append((differ[0][1] - differ[0][0], a, b))
    if not steps:
        return None
    usual, seen = collections.Counter(step for step, _, _ in steps).most_common(1)[0]
    if seen < 2 or 2 * seen <= len(steps):  # (no step is the usual one: 1, 2, 10 is no sequence to judge)
        return None
    return next(((a, b, max(1, round(step / usual) - 1)) for step, a, b in steps if step > usual), None)


def misordered_given(patterns: str | Sequence[str]) -> tuple[str, str] | None:
    """As :func:`misordered`, for the files of ``--images`` taken in the order given: files named
    one after another (an unquoted glob, which the shell expanded and sorted by name itself) and
    each list file's lines (often ``ls``'s output) — jumbled numbered sequences (:func:`_jumbled`),
    which were tracked without a word while the same glob quoted was warned of."""
    runs: list[list[str]] = [[]]
    for path in _expanded(patterns):
        if os.path.isfile(path) and path.lower().endswith(LIST_SUFFIXES):
            runs += [list_file(path), []]
        elif os.path.isfile(path):
            runs[-1].append(path)
        else:
            runs.append([])
    return next((pair for run in runs if (pair := _jumbled(run)) is not None), None)


def open_frames(video: str | None = None, images: str | Sequence[str] | None = None, fps: float | None = None,
                max_frames: int | None = None, stall_timeout_s: float | None = None) -> FrameSource:
    """A :class:`FrameSource` for ``--video`` (file, camera index, URL) or ``--images`` (a glob, or
    several globs or files — what a shell makes of an unquoted glob: each expanded and sorted by
    name, in the order given, each file once). Raises :class:`SourceError` when nothing can be
    read from it (a video's first frame is decoded here, so a bad file fails before any output
    is opened). An image of a sequence that cannot be decoded is skipped and listed in
    :attr:`FrameSource.skipped`: one bad file does not end a long sequence. ``stall_timeout_s``:
    how long a live source may give no frame (or no answer to its opening) before it is taken for
    stalled (default :data:`STALL_TIMEOUT_S`); it then ends, and :attr:`FrameSource.ended` says why.

    >>> import tempfile, cv2
    >>> d = tempfile.mkdtemp()
    >>> for name in ("b.png", "a.png"):
    ...     _ = cv2.imwrite(os.path.join(d, name), np.zeros((40, 40, 3), np.uint8))
    >>> _ = open(os.path.join(d, "c.png"), "w").write("not an image")
    >>> src = open_frames(images=[os.path.join(d, n) for n in ("b.png", "c.png", "a.png")])
    >>> [os.path.basename(src.names[i]) for i, _, _ in src], [(i, t) for i, t, _ in src.skipped]
    (['b.png', 'a.png'], [(1, 0.03333333333333333)])
    >>> import shutil; shutil.rmtree(d)
    """
    # (a string was math.isfinite's "must be real number, not str", naming neither option)
    # (a rate below MIN_RATE put frame 2 of --fps 1e-308 at an infinite time_s: the run ended at the tracker's error)
    if fps is not None and (isinstance(fps, (str, bytes, bool)) or not isinstance(fps, numbers.Real)
                            or not (math.isfinite(fps) and MIN_RATE <= fps <= MAX_RATE)):
        raise SourceError(f"--fps must be a positive number (from {MIN_RATE:g} to {MAX_RATE:g}), got {fps!r}"[:120])
    if max_frames is not None and (isinstance(max_frames, bool) or not isinstance(max_frames, numbers.Integral)
                                   or max_frames < 1):
        raise SourceError(f"--max-frames must be at least 1 (a whole number), got {max_frames!r}"[:120])
    if (video is None) == (images is None):
        raise SourceError("give one of --video or --images")
    if images is not None:
        from .images import ImageError, read_image

        patterns = [images] if isinstance(images, str) else list(images)
        paths = image_paths(patterns)
        label = " ".join(repr(p) for p in patterns[:2]) + (f" … ({len(patterns)} in all)" if len(patterns) > 2 else "")
        listed = any(os.path.expanduser(p).lower().endswith(LIST_SUFFIXES) and os.path.isfile(os.path.expanduser(p))
                     for p in patterns)  # (a list's missing files: "no frame can be read", naming the first)
        if not paths or not (listed or any(os.path.isfile(p) for p in paths)):  # (named files all missing: as a glob matching none)
            folder = next((p for p in patterns if os.path.isdir(os.path.expanduser(p))), None)
            if folder is not None:  # (was "no file matches" for a folder full of frames)
                raise SourceError(f"--images {folder}: is a folder; give a glob of its images, "
                                  f"e.g. {os.path.join(folder, '*.png')!r}")
            raise SourceError(f"--images {label}: no file matches")

        if (gap := numbering_gap(paths)) is not None:
            warnings.warn(f"--images: the numbering skips from {gap[0]} to {gap[1]} ({gap[2]} missing?); a frame's "
                          f"time_s is its index / rate, so the frames after it are timed early", SourceWarning,
                          stacklevel=2)

        def frames() -> Iterator[np.ndarray | ImageError]:
            for p in paths:
                try:
                    yield read_image(p)
                except ImageError as exc:  # (the message names the file)
                    yield exc

        return FrameSource(f"--images {label}", frame_rate(fps), names=paths, max_frames=max_frames,
                           _frames=frames())
    target = capture_target(video)
    shown = masked(video)  # (a camera URL's password: in every message and row, it was printed as given)
    kind = live_kind(target) or "video"
    live = kind != "video"
    if stall_timeout_s is not None and (isinstance(stall_timeout_s, (str, bytes, bool))
                                        or not isinstance(stall_timeout_s, numbers.Real)
                                        or not (math.isfinite(stall_timeout_s) and 0 < stall_timeout_s <= 86400)):
        raise SourceError(f"--stall-timeout must be a number of seconds above 0 (at most 86400), "
                          f"got {stall_timeout_s!r}"[:120])
    started = time.monotonic()
    try:  # (a live source in a thread of its own: a stalled read no longer holds off Ctrl-C)
        cap = LiveCapture(target, stall_timeout_s or STALL_TIMEOUT_S) if live else open_capture(target)
        opened = cap.isOpened()
    except SourceStalled as exc:
        raise SourceError(f"--video {shown}: cannot be opened as a {kind} ({exc})") from None
    if not opened:
        cap.release()
        waited = time.monotonic() - started  # (an address that takes connections and never answers: 30 s)
        raise SourceError(f"--video {shown}: cannot be opened as a {kind}"
                          + (f" (no answer within {waited:.0f} s)" if live and waited >= 5 else ""))
    import cv2

    turned = 0.0 if live else _as_recorded(cap)
    listed = cap.get(cv2.CAP_PROP_FRAME_COUNT)
    listed = int(listed) if math.isfinite(listed) and listed > 0 else 0  # (0: unknown; a stream's -1)
    # a URL of a recorded video (http://host/box.mp4, file:///...): its container counts its frames,
    # a camera's or a live stream's does not; it was timed by the clock (200 frames over 4.35 s, the
    # pace they were read at, for 6.64 s of video) and its end reported as a dropped stream
    recorded = live and isinstance(target, str) and listed > 0
    stamps: collections.deque = collections.deque()  # (a file's: each decoded frame's container time, s)
    frames = decoded_frames(cap, f"--video {shown}", live and not recorded, listed, kind)
    if not live or recorded:
        frames = _file_frames(frames, cap, listed, f"--video {shown}", stamps)
    head: list[np.ndarray | SourceError] = []  # up to the first frame that decodes (a bad file fails here)
    for item in frames:
        if isinstance(item, SourceEnded):  # (a live source that gives no frame at all: say why)
            cap.release()
            raise SourceError(f"--video {shown}: {item}, before its first frame")
        head.append(item)
        if not isinstance(item, Exception):
            break
    else:
        cap.release()
        raise SourceError(f"--video {shown}: no frame can be decoded")
    if turned:
        warnings.warn(f"--video {shown}: the video says rotate {turned:g}°; its frames are tracked as recorded, "
                      f"in the camera's own orientation (the camera file's width and height)", SourceWarning,
                      stacklevel=2)
    increasing = (not live or recorded) and (fps is None or recorded) and _increasing(stamps, frames, head)
    if recorded and not (increasing or _stamped(stamps)):  # (no container times at all: a live stream after all)
        recorded = False
    timed = increasing and fps is None
    live = live and not recorded
    rate = frame_rate(fps, cap.get(cv2.CAP_PROP_FPS))
    return FrameSource(f"--video {shown}", rate, live=live and fps is None, max_frames=max_frames,
                       _frames=itertools.chain(head, frames), _close=cap.release,
                       _stamp=(lambda: cap.grabbed_at) if live else None,
                       _watch=(lambda fn: setattr(cap, "on_wait", fn)) if isinstance(cap, LiveCapture) else None,
                       _pos=stamps.popleft if timed else None)


def _as_recorded(cap) -> float:
    """Turn off OpenCV's turning of a video file's frames by its rotation metadata (``rotate`` tag,
    display matrix) and return the rotation it states, clockwise degrees (0: none).

    Why: the camera file describes the sensor, whose pictures the video holds as recorded; turned
    for display, a 640×480 phone video tagged rotate 90 was refused as 480×640 px, and one tagged
    180 was tracked without a word with every pose turned 180°."""
    import cv2

    with contextlib.suppress(AttributeError, cv2.error):  # (an OpenCV without the property: as before)
        cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 0)
    try:
        turned = float(cap.get(cv2.CAP_PROP_ORIENTATION_META)) % 360
    except (AttributeError, TypeError, ValueError, cv2.error):
        return 0.0
    return turned if math.isfinite(turned) else 0.0


#: decoded frames of a video file whose timestamps must increase for them to time its frames: a
#: file whose B-frames were muxed with their decoding order's times (``examples/cookie-box/box.mp4``:
#: 0, 0.101, 0.067, 0.134, 0.034 s) shows it within its first few frames
STAMP_CHECK_FRAMES = 8


def _file_frames(items: Iterator[np.ndarray | SourceError], cap, listed: int, label: str,
                 stamps: collections.deque) -> Iterator[np.ndarray | SourceError]:
    """``items`` of a video file (:func:`decoded_frames`), each decoded frame's container time (s)
    appended to ``stamps`` as it comes (a frame is yielded right after its read: the failures
    before it come first). At the end, a file that gave fewer frames than its header counts
    (``listed``, 0: unknown) is warned of once (:class:`SourceWarning`): a copy or recording cut
    short ended early without a word. A count the container only estimates from its duration
    (Matroska: a variable-frame-rate video's is too high) is not taken for short when the last
    frame's time reaches that duration."""
    import cv2

    n, last = 0, None
    for item in items:
        n += 1
        if not isinstance(item, Exception):
            last = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            stamps.append(last)
        yield item
    rate = cap.get(cv2.CAP_PROP_FPS)
    timed = last is not None and math.isfinite(last) and last > 0 and math.isfinite(rate) and rate > 0
    # one frame short is no copy cut short: an H.264 header may count a frame the decoder drops (the
    # bundled box.mp4: 455 of 456, a damaged slice at its start) — a copy cut short misses many
    if last is not None and n < listed - 1 and not (timed and last + 1.5 / rate >= listed / rate):  # (none: an error)
        warnings.warn(f"{label}: the video ended after {n} of the {listed} frames its header counts "
                      f"(cut short or damaged?)", SourceWarning, stacklevel=2)


def _increasing(stamps: collections.deque, frames: Iterator, head: list) -> bool:
    """Whether a video file's first :data:`STAMP_CHECK_FRAMES` decoded frames (read ahead into
    ``head``) have increasing timestamps, so that they may time its frames."""
    while len(stamps) < STAMP_CHECK_FRAMES:
        item = next(frames, None)
        if item is None:
            break
        head.append(item)
    values = list(stamps)
    return all(math.isfinite(a) and a >= 0 for a in values) and all(b > a for a, b in zip(values, values[1:]))


def _stamped(stamps: collections.deque) -> bool:
    """Whether the decoded frames read so far carry container times (finite, from 0, not all 0),
    in order or not (a file's B-frames may carry their decoding order's): a recorded video's do."""
    values = list(stamps)
    return bool(values) and all(math.isfinite(a) and a >= 0 for a in values) and max(values) > 0


#: consecutive frames of a video file that may fail to decode beyond the count its container lists
#: before the failures are taken for its end (a count the container only estimates may be short)
BAD_RUN_PAST_COUNT = 2
#: ... and at most, whatever the count says (a duration in the header an hour too long)
MAX_BAD_RUN = 1000


def decoded_frames(cap, label: str, live: bool = False, listed: int = 0,
                   kind: str | None = None) -> Iterator[np.ndarray | SourceError]:
    """The frames of an open capture, in order; a frame of a file that fails to decode is a
    :class:`SourceError` in its place (a ``lost`` row), not the end of the video.

    Why: OpenCV's FFmpeg reader answers ``read() → False`` for a frame whose data cannot be
    decoded (an MJPG/AVI frame zeroed or cut by a failing disk or a dropped USB packet) and
    goes on with the next frame at the next call; ``track`` took the first ``False`` for the
    end, and the rest of the video was silently not tracked. Failures followed by a frame are
    frames that failed (one each: FFmpeg's AVI and MP4 readers keep each frame's place); failures
    not followed by one are the end. A live source (camera, stream) is alike — one corrupt JPEG
    part of an MJPEG stream fails one read, and the next frame comes (it ended the run) — and
    ends after :data:`LIVE_BAD_RUN` failures in a row, or when no frame came within its
    timeout (a :class:`LiveCapture` read that raised :class:`SourceStalled`): its last item is
    then a :class:`SourceEnded` saying why. ``listed``: the frame count the container states (0: unknown), which bounds how
    long a run of failures may be before it is the end.

    What OpenCV does not tell, and this cannot see: a frame whose data is damaged but decodes
    (FFmpeg conceals the damage: a garbled picture, and with inter-frame codecs such as H.264
    the frames after it until the next keyframe too), and a frame the container itself lost (an
    AVI chunk cut short swallows the next frame: the frames after it come one index early).
    Such frames are tracked as given; the tracker's own checks usually lose a garbled one.
    """
    n = 0
    # the run of reads failed since the last frame: when each returned (a live capture's clock)
    failed_at: list[float | None] = []
    what = kind or ("camera" if label.split()[-1].isdigit() else "stream")  # (kind: live_kind's)
    timeout = getattr(cap, "timeout_s", STALL_TIMEOUT_S)
    last = time.monotonic()
    while True:
        try:
            ok, frame = cap.read()
        except SourceStalled:  # (a live source's read that did not come back)
            yield SourceEnded(f"the {what} stalled: no frame within {timeout:g} s")
            return
        if ok and frame is not None:
            for at in failed_at:
                error = SourceError(f"{label}: its data cannot be decoded (a damaged "
                                    + ("frame?)" if live else "file?)"))
                error.grabbed_at = at  # (its own time: it was given the next frame's)
                yield error
            n, last = n + len(failed_at) + 1, time.monotonic()
            failed_at.clear()
            yield frame
            continue
        failed_at.append(getattr(cap, "grabbed_at", None))
        failed = len(failed_at)
        if live and time.monotonic() - last >= timeout:  # (reads that fail slowly, one after another)
            yield SourceEnded(f"the {what} stalled: no frame within {timeout:g} s")
            return
        if live and failed > LIVE_BAD_RUN:  # (a stream closed or dropped: every read fails at once)
            yield SourceEnded(f"the {what} ended: it gives no more frames"
                              + (" (closed or dropped by the source; not reconnected)" if what == "stream" else ""))
            return
        if not live and (failed > MAX_BAD_RUN or (failed > BAD_RUN_PAST_COUNT and n + failed >= listed)):
            return


def jpeg_frames(source: FrameSource, quality: int = 90) -> Iterator[tuple[int, float, bytes]]:
    """``(index, time_s, JPEG bytes)`` of a source: what a WebSocket client streams."""
    import cv2

    from .images import to_bgr8

    for i, t, image in source:
        yield i, t, cv2.imencode(".jpg", to_bgr8(image), [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()


# --- one record per frame: TrackStep <-> the service's JSON message ----------------------------

def _vec(x) -> list[float] | None:
    return None if x is None else [float(v) for v in np.asarray(x, float).ravel()]


def _covariance6(cov) -> np.ndarray:
    """The pose block (6×6) of a covariance, exactly symmetric: the filter's products leave it
    asymmetric by ~1e-17, which a consumer's ``C == C.T`` check (or ROS's) refused."""
    c = np.asarray(cov, float)[:6, :6]
    return (c + c.T) / 2


def step_message(step) -> dict:
    """The contract's per-frame JSON object (``"type": "pose"``) of a
    :class:`~recognition.video.TrackStep`: pose, velocity and 6×6 covariance are ``null`` when
    the status is ``lost``."""
    has_pose = step.status != "lost" and step.t is not None
    v, omega, cov = (getattr(step, k, None) for k in ("v", "omega", "covariance"))  # a tracker may have none
    has_vel = has_pose and v is not None and omega is not None
    return {
        "type": "pose",
        "frame": int(step.frame),
        "time_s": float(step.time_s),
        "status": step.status,
        "pose": {"t": _vec(step.t), "q_wxyz": _vec(step.q_wxyz)} if has_pose else None,
        "velocity": {"v": _vec(v), "omega": _vec(omega)} if has_vel else None,
        "covariance": [[float(x) for x in row] for row in _covariance6(cov)]
        if has_pose and cov is not None else None,
        "inliers": int(getattr(step, "inliers", 0) or 0),
        "reason": getattr(step, "reason", None),
        "timings_ms": {k: round(float(x), 3) for k, x in (getattr(step, "timings_ms", None) or {}).items()},
    }


def step_from_message(msg: dict | Any | None, frame: int | None = None, time_s: float | None = None):
    """A :class:`~recognition.video.TrackStep` from a server message (a dict or the client's
    pydantic ``TrackMessage``); ``None`` (no answer for that frame) is a ``lost`` step at
    ``frame``/``time_s``. ``frame``/``time_s`` override the message's (the caller's numbering)."""
    from .video import TrackStep

    if msg is not None and not isinstance(msg, dict):
        msg = msg.model_dump()
    if msg is None:
        return TrackStep(frame=int(frame or 0), time_s=float(time_s or 0.0), status="lost", reason="no answer")
    pose, vel, cov = msg.get("pose"), msg.get("velocity"), msg.get("covariance")
    timings = dict(msg.get("timings_ms") or {})
    if msg.get("latency_ms") is not None:
        timings["latency"] = float(msg["latency_ms"])
    return TrackStep(
        frame=int(msg["frame"] if frame is None else frame),
        time_s=float(msg["time_s"] if time_s is None else time_s),
        status=msg["status"],
        t=None if not pose else np.asarray(pose["t"], float),
        q_wxyz=None if not pose else np.asarray(pose["q_wxyz"], float),
        v=None if not vel else np.asarray(vel["v"], float),
        omega=None if not vel else np.asarray(vel["omega"], float),
        covariance=None if cov is None else np.asarray(cov, float),
        inliers=int(msg.get("inliers") or 0),
        timings_ms=timings,
        reason=msg.get("reason"),
    )


# --- rows ----------------------------------------------------------------------------------------

def _num(x) -> str:
    """A number as the shortest text that reads back as the same float (Python's ``repr``), a
    whole number without ``.0``, zero as ``0``: the CSV's and BOP's numbers are exactly the JSON
    lines' (BOP's ``t`` exactly the mesh's times the unit factor). They were rounded to 6
    significant digits (CSV: 10 µm of a pose at 12 m in a mesh in metres, ~1e-6 rad of
    rotation) and 9 (BOP).

    >>> [_num(x) for x in (0.1, 2.0, -0.0, 1 / 3, 1e-7, 653.9661009834390)]
    ['0.1', '2', '0', '0.3333333333333333', '1e-07', '653.966100983439']
    """
    x = float(x)
    if x == 0:
        return "0"
    text = repr(x)
    return text[:-2] if text.endswith(".0") else text


def csv_row(step) -> str:
    """One line of the contract's CSV (:data:`CSV_COLUMNS`, no newline); the pose and velocity
    columns are empty when the step has no pose (``lost``), velocity zero if unknown. Numbers
    read back as the very floats of the step (:func:`_num`); ``time_s`` to the microsecond."""
    head = f"{int(step.frame)},{float(step.time_s):.6f},{step.status}"
    if step.status == "lost" or step.t is None or step.q_wxyz is None:
        return head + "," * 14 + str(int(step.inliers or 0))
    v = np.zeros(3) if step.v is None else step.v
    w = np.zeros(3) if step.omega is None else step.omega
    nums = [*np.ravel(step.t), *np.ravel(step.q_wxyz), *np.ravel(v), *np.ravel(w)]
    return head + "," + ",".join(_num(x) for x in nums) + f",{int(step.inliers or 0)}"


def jsonl_row(step) -> str:
    """The full per-frame message (:func:`step_message`) as one JSON line (no newline), with the
    WebSocket message's other keys (the contract: "the WebSocket's pose message per line"):
    ``latency_ms`` (the step's own time: a file's frame waits for nothing else) and ``skipped`` (0:
    every frame of a file is tracked)."""
    msg = step_message(step)
    msg["latency_ms"] = round(float(msg["timings_ms"].get("total", 0.0)), 2)
    msg["skipped"] = 0
    return json.dumps(msg, separators=(",", ":"))


def _unit_scale(unit: str, to_metres: float) -> float:
    if unit not in UNIT_METRES:
        raise ValueError(f"mesh unit {unit!r}: use one of {', '.join(UNIT_METRES)}")
    return UNIT_METRES[unit] / to_metres


def bop_row(step, mesh_unit: str, obj_id: int = 1, scene_id: int = 0) -> str | None:
    """One line of a BOP results CSV (``scene_id,im_id,obj_id,score,R,t,time``): ``R`` row-major
    (9 numbers, space-separated), ``t`` in mm, ``im_id`` the frame index, ``score`` the inlier
    count, ``time`` the frame's processing time in seconds (-1 if unknown). ``None`` for a frame
    without a pose (BOP lists estimates only). ``mesh_unit``: the unit of the mesh (mm, cm, m).

    >>> from quatrack.recognition.video import TrackStep
    >>> step = TrackStep(frame=7, time_s=0.23, status="tracking", t=np.array([1.0, 2.0, 50.0]),
    ...                  q_wxyz=np.array([1.0, 0.0, 0.0, 0.0]), inliers=80, timings_ms={"total": 12.0})
    >>> bop_row(step, "cm")
    '0,7,1,80,1 0 0 0 1 0 0 0 1,10 20 500,0.012000'
    >>> pose_from_bop(bop_row(step, "cm"), "cm").t
    array([ 1.,  2., 50.])
    """
    if step.status == "lost" or step.t is None or step.q_wxyz is None:
        return None
    s = _unit_scale(mesh_unit, 1e-3)
    R = quat.to_matrix(np.asarray(step.q_wxyz, float))
    total = (step.timings_ms or {}).get("total")
    seconds = f"{total / 1e3:.6f}" if total is not None else "-1"
    return (f"{scene_id},{int(step.frame)},{obj_id},{float(step.inliers or 0):g},"
            + " ".join(_num(x) for x in R.ravel()) + ","
            + " ".join(_num(float(x) * s) for x in np.ravel(step.t)) + f",{seconds}")


def pose_from_bop(line: str, mesh_unit: str) -> Pose:
    """The :class:`~tracking.pose.Pose` (mesh units) of a :func:`bop_row` line."""
    parts = line.strip().split(",")
    R = np.array([float(x) for x in parts[4].split()]).reshape(3, 3)
    return Pose.from_matrix(R, np.array([float(x) for x in parts[5].split()]) / _unit_scale(mesh_unit, 1e-3))


def ros_stamp(time_s: float) -> tuple[int, int]:
    """``(sec, nanosec)`` of ROS's ``builtin_interfaces/Time`` for ``time_s``, to the nearest
    nanosecond, ``0 ≤ nanosec < 10⁹``. A fraction that rounds up to a whole second carries into
    ``sec`` (it was wrapped to 0 with ``sec`` kept: 2.9999999997 s was stamped 2 s, a second
    early and before the previous frame's stamp).

    >>> ros_stamp(12.25), ros_stamp(2.9999999997), ros_stamp(0.0)
    ((12, 250000000), (3, 0), (0, 0))
    """
    sec = int(math.floor(time_s))
    nanosec = int(round((time_s - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return sec, nanosec


def ros_pose_with_covariance(step_or_msg, mesh_unit: str, frame_id: str = "camera") -> dict | None:
    """``geometry_msgs/PoseWithCovarianceStamped`` as JSON (the field names of ROS 2's message):
    ``header.stamp`` from ``time_s``, position in metres, ``orientation`` in ROS order ``x, y,
    z, w``, ``covariance`` the 36 numbers of the 6×6 over ``[x, y, z, rot X, rot Y, rot Z]``,
    row-major, with position rows/columns scaled to metres. ROS's rotation covariance is about
    the parent frame's fixed axes, which is quatrack's ``δθ`` (``q_true = exp(δθ/2) ⊗ q``,
    camera frame), so it is copied as is. ``None`` for a frame without a pose."""
    step = step_or_msg if not isinstance(step_or_msg, dict) else step_from_message(step_or_msg)
    if step.status == "lost" or step.t is None or step.q_wxyz is None:
        return None
    s = _unit_scale(mesh_unit, 1.0)
    t = np.ravel(step.t) * s
    w, x, y, z = (float(v) for v in np.ravel(step.q_wxyz))
    if step.covariance is not None:
        scale = np.array([s, s, s, 1.0, 1.0, 1.0])
        cov = (_covariance6(step.covariance) * np.outer(scale, scale)).ravel()
    else:
        cov = np.zeros(36)  # unknown; ROS says -1 in [0] means "unknown"
        cov[0] = -1.0
    sec, nanosec = ros_stamp(step.time_s)
    return {
        "header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame_id},
        "pose": {"pose": {"position": {"x": float(t[0]), "y": float(t[1]), "z": float(t[2])},
                          "orientation": {"x": x, "y": y, "z": z, "w": w}},
                 "covariance": [float(c) for c in cov]},
    }


def pose_from_ros(msg: dict, mesh_unit: str) -> tuple[Pose, np.ndarray]:
    """``(pose, 6×6 covariance)`` in mesh units back from :func:`ros_pose_with_covariance`."""
    s = _unit_scale(mesh_unit, 1.0)
    p, o = msg["pose"]["pose"]["position"], msg["pose"]["pose"]["orientation"]
    scale = np.array([s, s, s, 1.0, 1.0, 1.0])
    cov = np.asarray(msg["pose"]["covariance"], float).reshape(6, 6) / np.outer(scale, scale)
    return Pose([o["w"], o["x"], o["y"], o["z"]], np.array([p["x"], p["y"], p["z"]]) / s), cov


class RowWriter:
    """Writes one format's header and rows to an open text file: ``csv`` (the contract's),
    ``jsonl`` (:func:`jsonl_row`) or ``bop`` (:func:`bop_row`; needs ``mesh_unit``)."""

    def __init__(self, f, fmt: str = "csv", mesh_unit: str | None = None, obj_id: int = 1, scene_id: int = 0) -> None:
        if fmt not in FORMATS:
            raise ValueError(f"--format {fmt}: use one of {', '.join(FORMATS)}")
        if fmt == "bop" and mesh_unit is None:
            raise ValueError("--format bop needs --mesh-unit (mm, cm or m): BOP's t is in millimetres")
        if mesh_unit is not None:
            _unit_scale(mesh_unit, 1.0)
        self.f, self.fmt, self.mesh_unit, self.obj_id, self.scene_id = f, fmt, mesh_unit, obj_id, scene_id
        if fmt == "csv":
            f.write(CSV_HEADER + "\n")
        elif fmt == "bop":
            f.write(",".join(BOP_COLUMNS) + "\n")

    def write(self, step) -> None:
        if self.fmt == "csv":
            line = csv_row(step)
        elif self.fmt == "jsonl":
            line = jsonl_row(step)
        else:
            line = bop_row(step, self.mesh_unit, self.obj_id, self.scene_id)
        if line is not None:
            self.f.write(line + "\n")


# --- files ---------------------------------------------------------------------------------------


def check_outputs(inputs: Sequence[tuple[str, str]], outputs: Sequence[tuple[str, str]]) -> None:
    """Raise :class:`SourceError` if an output (``(option, path)``) is an input file, another
    output, or a folder — before anything is read or written. Why: ``--out``/``--overlay``
    naming the input video replaced it with the poses, silently (``track``, ``demo``), and an
    output that is a folder was found only after the whole run. Paths compare resolved
    (``os.path.realpath``: links and ``..`` followed); inputs that are not files are ignored.

    >>> try:
    ...     check_outputs([("--video", __file__)], [("--out", __file__)])
    ... except SourceError as exc:
    ...     print(str(exc).split(": ", 1)[1])
    is the input; give another file name (it would be overwritten)
    """
    seen = {os.path.realpath(path): opt for opt, path in inputs if path and os.path.isfile(path)}
    for opt, path in outputs:
        if not path:
            continue
        if os.path.isdir(path):
            raise SourceError(f"{opt} {path}: is a folder; give a file name")
        real = os.path.realpath(path)
        if real in seen:
            what = "the input" if seen[real] in {o for o, _ in inputs} else f"also {seen[real]}"
            raise SourceError(f"{opt} {path}: is {what}; give another file name (it would be overwritten)")
        seen[real] = opt


SPECIAL_ROOTS = ("/dev/", "/proc/")  # devices, and /proc/self/fd/N: a process's open files


def written_where(target: str | os.PathLike) -> tuple[str, bool]:
    """Where an output named ``target`` goes: ``(path, in_place)``. In place (``path`` is
    ``target``) when it is under /dev/ or /proc/, reaches there through a link, or is a device or
    FIFO: ``--out /dev/stdout`` with stdout redirected to a file resolves to that regular file,
    and the rename of a temporary file onto /dev/stdout (a link to /proc/self/fd/1) replaced the
    link, for every process, and lost the poses. Otherwise ``path`` is the file the links lead to
    (``os.path.realpath``): the rename onto a link replaced the link, and its target was never
    written."""
    target = os.fspath(target)
    path = os.path.abspath(target)
    for _ in range(64):  # (each link of a chain, its folder resolved: a folder linked into /proc counts)
        path = os.path.join(os.path.realpath(os.path.dirname(path)), os.path.basename(path))
        if (path + os.sep).startswith(SPECIAL_ROOTS):
            return target, True
        if not os.path.islink(path):
            break
        path = os.path.join(os.path.dirname(path), os.readlink(path))
    real = os.path.realpath(target)
    if os.path.exists(real) and not os.path.isfile(real) and not os.path.isdir(real):
        return target, True
    return real, False


def _temp_affixes(name: str, folder: str) -> tuple[str, str]:
    """``mkstemp``'s prefix and suffix for a temporary ``.NAME.XXXXXXXX.ext`` beside ``NAME``,
    NAME cut short so that the whole fits the folder's longest name (255 bytes mostly): an output
    name of 240-255 bytes, one the filesystem takes, failed with "File name too long". The
    extension is kept when it fits (the video writer and ``imwrite`` go by it)."""
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    suffix = os.path.splitext(name)[1]
    room = limit - len(".." + "XXXXXXXX")  # (mkstemp's 8 random characters)
    if len(os.fsencode(suffix)) > room // 2:  # (an "extension" that is most of the name)
        suffix = ""
    stem = name
    while stem and len(os.fsencode(stem + suffix)) > room:  # (by characters: a UTF-8 name is not cut mid-character)
        stem = stem[:-1]
    return f".{stem}.", suffix


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, option: str = "") -> Iterator[str]:
    """A temporary path beside ``target`` (same folder, so the rename is atomic) that becomes
    ``target`` when the block ends normally, and is deleted if it raises. Permissions follow the
    umask (``mkstemp``'s 0600 would survive the rename). A device, FIFO or anything under /dev/
    or /proc/ (``/dev/null``, ``/dev/stdout``) is yielded as it is and written in place; a link
    to a file is written at the file the link leads to, the link kept (:func:`written_where`)."""
    target = os.fspath(target)
    name = f"{option} {target}" if option else target
    if not os.path.basename(target):  # ("" or "new/": the rename at the end failed, after the whole run)
        raise SourceError(f"{name}: give a file name, not a folder")
    final, in_place = written_where(target)
    if in_place:
        yield target
        return
    folder = os.path.dirname(final)
    if not os.path.isdir(folder):
        raise SourceError(f"{name}: the folder {folder} does not exist")
    prefix, suffix = _temp_affixes(os.path.basename(final), folder)
    try:
        fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=folder)
    except OSError as exc:  # (a read-only folder: the message named the temporary file, not the option)
        raise SourceError(f"{name}: cannot write in {folder} ({exc.strerror or exc})") from None
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield tmp
        if os.path.exists(tmp):  # (its writer removed it: nothing to write, the target is left as it was)
            try:
                os.replace(tmp, final)
            except OSError as exc:  # (the message named the temporary file and the target, not the option)
                raise SourceError(f"{name}: cannot put the finished file in place ({exc.strerror or exc}); "
                                  f"{final} is as it was") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


class VideoOut:
    """An MP4 (``mp4v``) written frame by frame to ``path``, opened at the first frame's size.

    MPEG-4 stores what OpenCV's writer cannot be asked for, and it said nothing: an odd width or
    height came out one pixel smaller (639×479 frames as a 638×478 video, rescaled), and a rate
    whose time base does not fit MPEG-4 (below ~0.0015 frames/s, or one such as 77.777 that needs
    a denominator over 65535) failed with OpenCV's error lines on stderr. Now an odd-sized frame
    is padded with one black column at the right and/or one black row at the bottom (its pixels
    and their coordinates unchanged; :attr:`padded` holds ``(w, h) → (W, H)``), and such a rate is
    written as the nearest one MPEG-4 stores (:attr:`written_rate`; the frames' own times are the
    caller's business). The caller can say so (:meth:`notes`).

    ``timed``: the frames are placed by their ``time_s`` (:meth:`write`), as a live source's are
    due: its frames come at the pace they are read and tracked, not at the rate the camera or
    stream claims (``CAP_PROP_FPS``, the video's rate), so written one per video frame the
    overlay played several times too fast. Each frame is shown from its time to the next one's:
    repeated while the source gave none, left out when two fall within one video frame (the
    later is shown); the video lasts as long as the run."""

    def __init__(self, path: str, rate: float, option: str = "--overlay", timed: bool = False,
                 target: str | None = None) -> None:
        self.path, self.rate, self.option, self.writer = path, rate, option, None
        self.target = path if target is None else target  # (the file named, when ``path`` is its temporary)
        self.size: tuple[int, int] | None = None  # (width, height) written
        self.padded: tuple[tuple[int, int], tuple[int, int]] | None = None
        self.written_rate: float | None = None
        self.timed = timed
        self.frames = 0  # video frames written
        self._held: np.ndarray | None = None  # (timed) the latest frame, written once the next one's time says how often

    def _open(self, size: tuple[int, int]):
        import cv2

        log = cv2.utils.logging  # (a refused rate printed "[ERROR:0@0.03] ... Could not open codec mpeg4")
        previous = log.getLogLevel()
        log.setLogLevel(log.LOG_LEVEL_SILENT)
        try:
            for rate in dict.fromkeys((self.rate, max(float(f"{self.rate:.3g}"), 0.002), DEFAULT_RATE)):
                writer = cv2.VideoWriter(self.path, cv2.VideoWriter_fourcc(*"mp4v"), rate, size)
                if writer.isOpened():
                    return writer, rate
                writer.release()
        finally:
            log.setLogLevel(previous)
        # (it said "cannot write ... here", naming neither the file nor where)
        raise SourceError(f"{self.option} {self.target}: cannot write a {size[0]}×{size[1]} MP4 video there "
                          f"(OpenCV's MP4 writer cannot open it)")

    def write(self, image: np.ndarray, time_s: float | None = None) -> None:
        """Add ``image``: the next video frame, or (``timed``) the one shown from ``time_s`` (seconds
        from the first frame's) on."""
        import cv2

        h, w = image.shape[:2]
        if self.writer is None:
            self.size = (w + w % 2, h + h % 2)
            if self.size != (w, h):
                self.padded = ((w, h), self.size)
            self.writer, self.written_rate = self._open(self.size)
        W, H = self.size
        if (w, h) != (W, H) and W - 1 <= w <= W and H - 1 <= h <= H:  # (an odd size: padded, not rescaled)
            image = cv2.copyMakeBorder(image, 0, H - h, 0, W - w, cv2.BORDER_CONSTANT, value=0)
        if not self.timed or time_s is None:
            self.writer.write(image)
            self.frames += 1
            return
        slot = math.floor(max(float(time_s), 0.0) * self.written_rate + 0.5)  # the video frame it starts at
        if self._held is not None:
            while self.frames < slot:
                self.writer.write(self._held)
                self.frames += 1
        self._held = image

    def notes(self) -> list[str]:
        """What the video is not as asked, one line each (none when it is): its size, its rate."""
        out = []
        if self.padded is not None:
            (w, h), (W, H) = self.padded
            out.append(f"{self.option} is {W}×{H}: MP4 stores even sizes only, so the {w}×{h} frames have a black "
                       f"{'column at the right' if W != w else ''}{' and a ' if W != w and H != h else ''}"
                       f"{'row at the bottom' if H != h else ''} (pixel coordinates unchanged)")
        if self.written_rate is not None and self.written_rate != self.rate:
            out.append(f"{self.option} plays at {self.written_rate:g} frames/s: MP4 cannot store {self.rate:g} "
                       f"(the poses' time_s is unchanged)")
        return out

    def check(self) -> None:
        """After :meth:`close`: raise :class:`SourceError` naming the output if the finished video
        cannot be read back whole. Why: OpenCV's writer fails in silence — on a full disk an
        ``--overlay`` cut off at 64 KiB, with no index (no player opens it), was put in place and
        the run said nothing (exit 0). A device or FIFO written in place is not read back."""
        import cv2

        if not self.frames or written_where(self.path)[1]:
            return
        quiet_ffmpeg()  # (FFmpeg's "moov atom not found" on stderr)
        cap = cv2.VideoCapture(self.path)
        whole = cap.isOpened() and cap.get(cv2.CAP_PROP_FRAME_COUNT) >= self.frames
        cap.release()
        if whole:
            return
        try:
            full = os.statvfs(os.path.dirname(os.path.abspath(self.path))).f_bavail == 0
        except (OSError, AttributeError):
            full = False
        raise SourceError(f"{self.option} {self.target}: the video could not be written whole "
                          f"({'the disk is full' if full else 'the written file cannot be read back'})")

    def close(self) -> None:
        """Finish the video; without a frame written (Ctrl-C before the first) there is no video:
        the file is removed (an empty .mp4 no player opens was left)."""
        if self.writer is not None:
            if self._held is not None:  # (timed: the last frame, once)
                self.writer.write(self._held)
                self.frames += 1
                self._held = None
            self.writer.release()
            self.writer = None
        elif os.path.isfile(self.path) and os.path.getsize(self.path) == 0 and not written_where(self.path)[1]:
            os.unlink(self.path)  # (not in place: an empty /dev/stdout was unlinked, the link itself)


# --- progress --------------------------------------------------------------------------------------

#: seconds of frames the progress line's rate is over
RATE_WINDOW_S = 2.0
#: seconds without a frame after which the progress line says it waits
WAIT_SHOWN_S = 1.0

class Progress:
    """One self-overwriting line on a terminal: frames, frames/s and status counts, at most
    ``every_s`` apart. Silent when ``stream`` is not a terminal (logs, pipes, CI).

    The rate is the recent one (the frames of the last :data:`RATE_WINDOW_S` s; it was the mean
    since the start, so a slowdown showed late). While a live source has waited
    :data:`WAIT_SHOWN_S` s for its next frame (counted from its first :meth:`tick`: the tracker's
    own time on a frame is no wait) the line says ``waiting for frames N s`` instead, kept fresh by :meth:`tick` (a live source
    calls it as it waits: :meth:`FrameSource.on_wait`); during a stall it showed the last rate,
    frozen, until the stall timeout ended the run."""

    def __init__(self, label: str, stream=None, every_s: float = 0.25, enabled: bool | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.label, self.stream = label, stream if stream is not None else sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)()) if enabled is None else enabled
        self.every_s, self.clock = every_s, clock
        self.counts = {"init": 0, "tracking": 0, "lost": 0}
        self.frames = 0
        self.t0 = clock()
        self.last = -math.inf
        self.shown = False
        self.recent: collections.deque = collections.deque()  # the times of the frames of the last RATE_WINDOW_S
        # when the source began waiting for the next frame (its first tick; the tracker's own time
        # on the frame before is no wait), None while frames come
        self.waiting_since: float | None = None

    def line(self, now: float | None = None) -> str:
        now = self.clock() if now is None else now
        c = self.counts
        since = now - self.waiting_since if self.waiting_since is not None else 0.0
        if since >= WAIT_SHOWN_S:
            pace = f"waiting for frames {since:.0f} s"
        else:
            dt = now - self.t0
            r = self.recent
            fps = (len(r) - 1) / (r[-1] - r[0]) if len(r) >= 2 and r[-1] > r[0] else self.frames / dt if dt > 0 else 0.0
            pace = f"{fps:.1f} fps"
        return (f"{self.label}: {self.frames} frames, {pace} "
                f"(init {c['init']}, tracking {c['tracking']}, lost {c['lost']})")

    def update(self, status: str | None) -> None:
        self.frames += 1
        if status in self.counts:
            self.counts[status] += 1
        now = self.clock()
        self.waiting_since = None
        self.recent.append(now)
        while now - self.recent[0] > RATE_WINDOW_S:
            self.recent.popleft()
        self._show(now)

    def tick(self) -> None:
        """Redraw the line (if due) though no frame came: what shows a stall as it lasts."""
        if self.enabled:
            now = self.clock()
            self.waiting_since = now if self.waiting_since is None else self.waiting_since
            self._show(now)

    def _show(self, now: float) -> None:
        if self.enabled and now - self.last >= self.every_s:
            self.last = now
            self.stream.write("\r" + self.line(now) + "\x1b[K")
            self.stream.flush()
            self.shown = True

    def close(self) -> None:
        if self.shown:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
            self.shown = False

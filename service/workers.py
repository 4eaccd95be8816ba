"""Several worker processes behind one listening socket: ``quatrack serve --workers N``.

Choice (measured in bench/RESULTS.md, "Serving many cameras"): uvicorn's own multi-process mode.
The parent binds the socket once and starts N workers; the kernel hands each new connection to
one of them, and a WebSocket session lives and dies with its connection, so the connection *is*
the session's affinity — no routing, no shared tracker state. Each worker loads the models itself
(read-only, ≈ a few MB per object) and runs tracking in its own thread pool, off its event loop;
uvicorn restarts a worker that dies. A process pool behind one event loop has to ship every
frame between processes and keeps each session's tracker in a process the session does not own;
processes that own their sessions ship nothing. Measured against a prototype of that model
(``bench/serve_pool.py``, ``quatrack bench serve --workers 1,2,p2``), the pool processed fewer
frames and its /healthz waited for a core just the same under load.

What the workers share lives in one *run directory* (``Settings.run_dir``), wiped at start:

- ``sessions/slot-K`` (K < ``max_sessions``): a session holds an exclusive ``flock`` on one slot
  file for its lifetime, so the limit holds for the whole server; the kernel drops the locks of a
  worker that dies, so a crash never leaks a slot.
- ``ready/PID``: a worker whose models are loaded holds an exclusive ``flock`` on its file
  (:class:`ReadyBoard`); ``/readyz`` answers 200 only when ``workers`` such locks are held, so a
  request that lands on a ready worker does not report the server ready while another one is
  still loading (or has died and is being restarted), and a stopping worker withdraws its file.
- ``placement/PID``: each worker's load (sessions and handshakes), ``flock``-ed by it
  (:mod:`.placement`): a worker holding more than the least-loaded one stops listening on the
  shared socket until that is no longer so, so the kernel gives new connections to the others
  (which worker accepts is otherwise whichever wakes first: random), and passes a connection it
  accepted anyway (a burst) to the least-loaded one through ``placement/PID.sock``.
- ``prometheus/``: ``$PROMETHEUS_MULTIPROC_DIR`` for prometheus-client's multiprocess mode.
- ``server.lock``: ``flock``-ed by the server's main process (:func:`lock_run_dir`): a second
  server given the same directory is refused instead of wiping the first one's files.

``max_pending_requests`` (REST) stays a per-worker limit: a worker's own queue is what it bounds.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import tempfile
import threading
import uuid
from pathlib import Path
from typing import Callable

from .settings import Settings

# prometheus-client's multiprocess directory; named here, not imported from .metrics: importing
# prometheus_client reads it once, and `quatrack serve` must set it first — with one worker the
# app runs in this very process, and a client imported before kept its counters in memory while
# /metrics read the empty directory (every metric but one missing)
MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"

log = logging.getLogger("quatrack.service")


def held_or_removed(path: Path) -> bool | None:
    """Whether a live worker holds the ``flock`` on its board file ``path`` (the ready board's,
    the placement board's): True if so; otherwise the file is a dead worker's (the kernel dropped
    its lock), it is deleted, and False; None if it is gone already."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True  # its worker holds it
    else:
        try:
            path.unlink()  # nobody holds it: a worker that died
        except FileNotFoundError:
            pass
        return False
    finally:
        os.close(fd)


class SlotLimiter:
    """At most ``max_sessions`` sessions in all processes sharing ``directory``.

    Same interface as :class:`quatrack.service.sessions.SessionLimiter` (``try_open``, ``close``,
    ``open``); ``count()`` is the number of slots held by any process. ``on_change(n)``, if set, is
    called with this process's number of sessions after each open and close, in the caller's
    thread (the event loop's): the worker's placement (:mod:`.placement`) decides there, before
    the WebSocket handshake is answered, whether this worker keeps accepting connections.
    """

    def __init__(self, directory: Path, max_sessions: int) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.max = max_sessions
        self._held: dict[str, int] = {}  # session id -> fd holding the lock
        self._lock = threading.Lock()
        self.on_change: Callable[[int], None] | None = None

    def _changed(self) -> None:
        if self.on_change is not None:
            try:
                self.on_change(len(self._held))
            except Exception:  # placement is an optimisation: a failure must not fail the session
                log.exception("placement: could not be told of a session change")

    @property
    def open(self) -> set[str]:
        """This process's sessions."""
        return set(self._held)

    def _grab(self, k: int) -> int | None:
        fd = os.open(self.dir / f"slot-{k}", os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        return fd

    def try_open(self) -> str | None:
        # Two passes: count() probes slots by briefly locking them, which may hide a free slot
        # from one pass.
        for _ in range(2):
            for k in range(self.max):
                fd = self._grab(k)
                if fd is not None:
                    sid = uuid.uuid4().hex[:12]
                    with self._lock:
                        self._held[sid] = fd
                    self._changed()
                    return sid
        return None

    def close(self, sid: str) -> None:
        with self._lock:
            fd = self._held.pop(sid, None)
        if fd is not None:
            os.close(fd)  # releases the flock
            self._changed()

    def count(self) -> int:
        """Slots held by any process (a free slot is locked and released at once to find out)."""
        held = 0
        for k in range(self.max):
            fd = self._grab(k)
            if fd is None:
                held += 1
            else:
                os.close(fd)
        return held


class ReadyBoard:
    """Which worker processes of one server have their models loaded: ``directory/PID``, each
    exclusively ``flock``-ed by its worker while it is ready. The kernel drops the lock of a worker
    that dies, so a crash withdraws it too; a file whose lock a reader can share is stale.

    A worker makes its file under a hidden name, locks it, then renames it into place, so a reader
    never sees a ready file that is not yet locked (and may delete stale ones safely)."""

    def __init__(self, directory: Path, workers: int) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.workers = workers
        self._fd: int | None = None
        self._path: Path | None = None

    def mark_ready(self) -> None:
        if self._fd is not None:
            return
        pid = os.getpid()
        tmp = self.dir / f".{pid}.tmp"
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        fcntl.flock(fd, fcntl.LOCK_EX)  # blocks only while a reader probes this very file
        os.replace(tmp, self.dir / str(pid))
        self._fd, self._path = fd, self.dir / str(pid)

    def withdraw(self) -> None:
        """This worker is no longer ready (it is stopping)."""
        if self._fd is None:
            return
        try:
            self._path.unlink()
        except FileNotFoundError:
            pass
        os.close(self._fd)
        self._fd = self._path = None

    def count(self) -> int:
        """Workers ready now (stale files of dead workers are removed on the way)."""
        return sum(held_or_removed(path) is True for path in self.dir.iterdir() if not path.name.startswith("."))

    def all_ready(self) -> bool:
        return self.count() >= self.workers


def ready_board(settings: Settings) -> ReadyBoard | None:
    """The board of the server's workers when they share a run directory, else None."""
    if settings.run_dir is None:
        return None
    return ReadyBoard(Path(settings.run_dir) / "ready", settings.workers)


RUN_LOCK = "server.lock"


def lock_run_dir(run: Path) -> int:
    """Take an exclusive ``flock`` on ``run/server.lock`` (with this process's id in it) and return
    its file descriptor, which the caller holds while it serves and closes after (the lock goes
    with it), or raise ValueError naming the server that holds it.

    Why: ``prepare_run_dir`` wipes the directory; a second server given the same
    ``QUATRACK_RUN_DIR`` wiped the first one's ``ready/`` and ``prometheus/`` files in silence
    (its ``/readyz`` then 503, its metrics gone) and shared its session slots. The kernel drops
    the lock of a server that died, so a stale file never blocks a restart."""
    path = run / RUN_LOCK
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        os.close(fd)
        raise ValueError(f"QUATRACK_RUN_DIR {run}: another quatrack serve{f' (pid {holder})' if holder.isdigit() else ''} "
                         f"is running with this run directory; give each server its own (or leave it unset)") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def prepare_run_dir(settings: Settings) -> tuple[Settings, Path, bool, int]:
    """Settings with a fresh, empty run directory (made in the temp dir unless given), whether
    the caller made it (then it removes it on exit), and the directory's lock (a file descriptor
    the caller closes when it stops serving: :func:`lock_run_dir`). Sets ``$PROMETHEUS_MULTIPROC_DIR`` for the
    workers about to start; any files of a previous run there are deleted (stale counters). A run
    directory another live server holds is refused (:func:`lock_run_dir`), before anything is wiped."""
    made = settings.run_dir is None
    run = Path(tempfile.mkdtemp(prefix="quatrack-run-")) if made else Path(settings.run_dir)
    run.mkdir(parents=True, exist_ok=True)
    lock = lock_run_dir(run)
    for sub in ("sessions", "ready", "placement", "prometheus"):
        shutil.rmtree(run / sub, ignore_errors=True)
        (run / sub).mkdir()
    os.environ[MULTIPROC_ENV] = str(run / "prometheus")
    return settings.replace(run_dir=run), run, made, lock


def session_limiter(settings: Settings):
    """The limiter the app uses: shared slots when a run directory is set, else in-memory."""
    if settings.run_dir is not None:
        return SlotLimiter(Path(settings.run_dir) / "sessions", settings.max_sessions)
    from .sessions import SessionLimiter

    return SessionLimiter(settings.max_sessions)


def count_open(limiter) -> int:
    """Sessions open in the whole server (all workers for slots, this process otherwise)."""
    return limiter.count() if isinstance(limiter, SlotLimiter) else len(limiter.open)


def app_from_env():
    """uvicorn's app factory in each worker process: the settings come from ``QUATRACK_*``,
    which ``quatrack serve`` set before starting the workers."""
    from .app import create_app

    return create_app(Settings.from_env(), whole_process=True)

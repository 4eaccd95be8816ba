"""Load-aware placement of WebSocket sessions across the worker processes of ``quatrack serve --workers N``.

Why: the workers accept on one shared listening socket and the kernel wakes all of them for a
new connection; whichever runs first takes it. Measured (bench/RESULTS.md, session 18): two
sessions opened together landed on the same worker 4 times in 12, four sessions all on one
worker 5 times in 12 — one worker tracked every stream while the other idled.

Mechanism (standard parts only: the kernel's shared accept queue, ``flock``, uvicorn's own
``loop=`` factory option): a worker that holds more sessions than the least-loaded worker stops
listening on the shared socket until that is no longer so; the kernel then hands the next
connection to a worker that still listens. Connections are never refused or lost: they wait in
the socket's accept queue, which belongs to the socket, not to any one process.

- Every worker publishes its session count in ``RUN_DIR/placement/PID`` (:class:`LoadBoard`),
  a file it holds an exclusive ``flock`` on for its lifetime: the kernel drops the lock of a worker
  that dies, and readers ignore (and delete) a file nobody holds.
- Rule (:meth:`Placement.evaluate`): listen iff this worker's sessions ≤ the smallest count of the
  other live workers (ties listen), so the least-loaded worker always listens and /healthz,
  /readyz and /metrics always find a worker to answer them.
- When: at once, on the event loop, whenever this worker opens or closes a session (the session
  limiter calls :meth:`Placement.sessions_changed` before the WebSocket handshake is answered),
  and every :data:`POLL_S` to see the other workers' changes (a worker that is over its share
  resumes when the others have caught up, or when the least-loaded one died). The poll keeps
  the other workers' files open and reads them (a lock probe and a read each); it looks for
  newly started workers every :data:`RELIST_S`, a session change always does.
- Pausing is closing this process's listening *server* (uvloop's, or asyncio's) while a
  duplicate of the socket's descriptor keeps the socket itself open here; resuming creates a new
  server on another duplicate. uvicorn gets a :class:`PausableServer` from ``create_server``, so
  its shutdown (close, then wait) works on whichever server is current.

Why it is deterministic for sessions opened one after another: a worker's own count is exact
and its view of the others' can only lag behind their growth, so a worker that listens holds
no more sessions than any other truly holds; the next session lands on a least-loaded worker.

Failure modes (documented in bench/RESULTS.md, "Session 23"):

- A burst of connections that arrive before the first of them has opened its session (a few ms,
  more under load) is placed as before — by whoever accepts first: libuv accepts every connection
  waiting in the queue in one go. Cameras reconnecting together after a restart are such a burst.
- Sessions are never moved: if sessions on one worker close, new ones go to it until the counts
  are even again.
- The views are refreshed every :data:`POLL_S`; in between, every worker may be paused for up to
  that long (A paused for B's count, B's sessions grew, A has not looked yet): connections wait in
  the queue meanwhile, they are not refused.
- A worker whose event loop is stuck stops refreshing its entry; after :data:`STALE_S` the others
  ignore it (and listen), so a hung worker cannot hold every connection in the queue.
- The poll notices a newly started worker only within :data:`RELIST_S` (a session change at
  once): until then a worker may listen although the newcomer holds fewer sessions.
- A restarted worker joins with 0 sessions and so gets the next sessions while it is still loading
  its models (``/readyz`` says 503 meanwhile; a session opened then waits for the model).
- Any error reading the board makes a worker listen (fails open: the old, random placement).
"""

from __future__ import annotations

import asyncio
import fcntl
import logging
import os
import threading
import time
from pathlib import Path

from .workers import held_or_removed

log = logging.getLogger("quatrack.service")

POLL_S = 0.05  # how often a worker re-reads the others' counts
STALE_S = 10.0  # an entry not refreshed for this long belongs to a stuck worker: ignored
HEARTBEAT_S = 1.0  # a worker rewrites its unchanged entry this often (what STALE_S checks)
RELIST_S = 1.0  # the poll looks for newly started workers this often (a session change: always)
_RECORD = 48  # bytes per entry: "sessions listening monotonic-time", space-padded, one write


class LoadBoard:
    """``directory/PID``: each live worker's session count, whether it listens, and when it last
    wrote (``time.monotonic()``, one clock for every process of the machine). The file is written
    in place with one ``pwrite`` of a fixed-size record, so a reader sees the old or the new one.
    A worker makes its file under a hidden name, locks it, then renames it into place, so a reader
    never takes a live worker's file for a dead one's."""

    def __init__(self, directory: Path) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.pid = os.getpid()
        self._fd: int | None = None
        self._others: dict[int, int] = {}  # pid -> an open descriptor of its file
        self._listed = 0.0

    def join(self) -> None:
        if self._fd is not None:
            return
        tmp = self.dir / f".{self.pid}.tmp"
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        fcntl.flock(fd, fcntl.LOCK_EX)
        self._fd = fd
        self.publish(0, True)
        os.replace(tmp, self.dir / str(self.pid))

    def publish(self, sessions: int, listening: bool) -> None:
        if self._fd is None:
            return
        record = f"{sessions} {int(listening)} {time.monotonic():.3f}".ljust(_RECORD - 1) + "\n"
        os.pwrite(self._fd, record.encode(), 0)

    def leave(self) -> None:
        """This worker is stopping: it no longer takes part."""
        if self._fd is None:
            return
        try:
            (self.dir / str(self.pid)).unlink()
        except FileNotFoundError:
            pass
        os.close(self._fd)
        self._fd = None
        self.close()

    def entries(self, relist: bool = True) -> dict[int, tuple[int, bool]]:
        """{pid: (sessions, listening)} of the other live workers whose entry is fresh; files of
        dead workers (nobody holds their lock) are deleted on the way. The other workers' files
        stay open between calls; ``relist=False`` skips looking for workers that joined since
        (the periodic poll relists only every :data:`RELIST_S`, to keep its cost at a few
        system calls)."""
        if relist or time.monotonic() - self._listed >= RELIST_S:
            self._relist()
        out: dict[int, tuple[int, bool]] = {}
        now = time.monotonic()
        for pid, fd in list(self._others.items()):
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:  # held: a live worker
                try:
                    fields = os.pread(fd, _RECORD, 0).split()
                    if len(fields) == 3 and now - float(fields[2]) <= STALE_S:
                        out[pid] = (int(fields[0]), fields[1] == b"1")
                except ValueError:  # a record being written for the first time: skip it this once
                    pass
            else:  # nobody holds it: a worker that died
                del self._others[pid]
                os.close(fd)
                held_or_removed(self.dir / str(pid))
        return out

    def _relist(self) -> None:
        self._listed = time.monotonic()
        for name in os.listdir(self.dir):
            if name.startswith(".") or not name.isdigit() or int(name) == self.pid or int(name) in self._others:
                continue
            try:
                self._others[int(name)] = os.open(self.dir / name, os.O_RDONLY)
            except FileNotFoundError:
                continue

    def close(self) -> None:
        for fd in self._others.values():
            os.close(fd)
        self._others.clear()


def read_board(directory: Path) -> dict[int, tuple[int, bool]]:
    """{pid: (sessions, listening)} of every live worker on the board at ``directory`` (for
    ``/metrics``: whichever worker answers reports them all). Nothing is kept open, nothing deleted."""
    out: dict[int, tuple[int, bool]] = {}
    try:
        names = os.listdir(directory)
    except FileNotFoundError:
        return out
    for name in names:
        if not name.isdigit():
            continue
        try:
            fd = os.open(Path(directory) / name, os.O_RDONLY)
        except FileNotFoundError:
            continue
        try:
            try:  # flock locks belong to open files: even the holder's own probe here is refused
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                held = False
            except BlockingIOError:
                held = True
            if held:
                fields = os.pread(fd, _RECORD, 0).split()
                if len(fields) == 3:
                    out[int(name)] = (int(fields[0]), fields[1] == b"1")
        except ValueError:
            pass
        finally:
            os.close(fd)
    return out


class PausableServer:
    """What ``create_server`` returns to uvicorn in a worker with placement: the loop's own
    server, which :class:`Placement` closes (pause) and re-creates on a duplicate of the
    listening socket (resume). ``close()``/``wait_closed()`` act on the current one, so uvicorn's
    shutdown stops listening whatever the state; after ``close()`` nothing resumes."""

    def __init__(self, server, create, sock, on_close=None) -> None:
        self._server = server
        self._on_close = on_close
        self._create = create  # coroutine function: a socket -> a new listening server
        self._spare = sock.dup()  # keeps the socket open in this process while no server holds it
        self._closed = False
        self._resuming: asyncio.Task | None = None
        self.want_listening = True

    @property
    def closed(self) -> bool:
        return self._closed

    def is_serving(self) -> bool:
        return self._server is not None and self._server.is_serving()

    @property
    def listening(self) -> bool:
        return self._server is not None

    @property
    def sockets(self):
        return self._server.sockets if self._server is not None else []

    def get_loop(self):
        return asyncio.get_running_loop()

    async def start_serving(self) -> None:
        if self._server is not None:
            await self._server.start_serving()

    def pause(self) -> None:
        """Stop taking connections here (synchronous: the kernel stops waking this process now)."""
        self.want_listening = False
        if self._server is not None:
            self._server.close()  # closes this process's descriptor of the socket, not the socket
            self._server = None

    def resume(self) -> None:
        self.want_listening = True
        if self._server is None and not self._closed and self._resuming is None:
            self._resuming = asyncio.get_running_loop().create_task(self._resume())

    async def _resume(self) -> None:
        try:
            server = await self._create(self._spare.dup())
        except Exception:  # e.g. out of descriptors: stay paused, the next poll retries
            log.exception("placement: could not listen again")
            return
        finally:
            self._resuming = None
        if self._closed or not self.want_listening or self._server is not None:
            server.close()  # paused (or shut down) while it was being made
        else:
            self._server = server

    def close(self) -> None:
        first = not self._closed
        self._closed = True
        self.pause()
        if not first:
            return
        if self._resuming is not None:
            self._resuming.cancel()
        self._spare.close()
        if self._on_close is not None:
            self._on_close()

    async def wait_closed(self) -> None:
        if self._server is not None:
            await self._server.wait_closed()


class Placement:
    """One worker's side of the placement rule (see the module's docstring); lives on the
    worker's event loop (:func:`loop_factory`) and is told of session changes by the session
    limiter (``SlotLimiter.on_change``, set in the app's lifespan)."""

    def __init__(self, board: LoadBoard) -> None:
        self.board = board
        self.sessions = 0
        self.server: PausableServer | None = None
        self._poller: asyncio.Task | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: int | None = None
        self._published: tuple[int, bool] | None = None
        self._published_at = 0.0

    def attach(self, server: PausableServer) -> PausableServer:
        self.server = server
        self._loop = asyncio.get_running_loop()
        self._thread = threading.get_ident()
        self.board.join()
        self._poller = self._loop.create_task(self._poll())
        return server

    def sessions_changed(self, sessions: int) -> None:
        """This worker now holds ``sessions``. Called on the event loop by the route (via the
        limiter) before the WebSocket handshake is answered, so that a worker over its share has
        stopped listening before the client can open its next connection."""
        if self._loop is None:
            self.sessions = sessions
            return
        if threading.get_ident() != self._thread:
            self._loop.call_soon_threadsafe(self.sessions_changed, sessions)
            return
        self.sessions = sessions
        self.evaluate()

    def evaluate(self, relist: bool = True) -> None:
        """Listen or not, by the rule; publish this worker's entry if it changed (or is due for
        its heartbeat). ``relist``: also look for workers started since the last look."""
        server = self.server
        if server is None or server.closed:
            return
        try:
            others = [n for n, _ in self.board.entries(relist).values()]
        except OSError:
            log.exception("placement: the board could not be read; listening")
            others = []
        if not others or self.sessions <= min(others):
            server.resume()
        else:
            server.pause()
        entry, now = (self.sessions, server.want_listening), time.monotonic()
        if entry != self._published or now - self._published_at >= HEARTBEAT_S:
            try:
                self.board.publish(*entry)
                self._published, self._published_at = entry, now
            except OSError:
                pass

    async def _poll(self) -> None:
        while self.server is not None and not self.server.closed:
            await asyncio.sleep(POLL_S)
            self.evaluate(relist=False)

    def stop(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
        self.board.leave()


class _PlacementLoop:
    """Mixed into the event loop class of a worker process: ``create_server(sock=...)`` (what
    uvicorn calls in each worker with the shared socket) returns a :class:`PausableServer`
    governed by the loop's :class:`Placement`."""

    placement: Placement | None = None

    async def create_server(self, protocol_factory, *args, sock=None, **kwargs):
        base = super().create_server
        if self.placement is None or sock is None:
            return await base(protocol_factory, *args, sock=sock, **kwargs)
        # O_NONBLOCK belongs to the socket's open file description, shared by every duplicate in
        # every worker, and ``socket.dup()`` re-applies the Python object's timeout to it: the
        # socket uvicorn hands over says "blocking" (None), so each dup made the shared listening
        # socket blocking until the loop set it back. A worker whose loop then drained the accept
        # queue blocked in accept() until the next connection came, its accepted connections
        # unread meanwhile: the 30-60 s handshakes of sessions opened together (issue 15).
        # Non-blocking on the object too, every duplicate keeps it so.
        sock.setblocking(False)
        spare = sock.dup()  # before the loop takes ``sock`` over (closing the server closes it)
        try:
            first = await base(protocol_factory, *args, sock=sock, **kwargs)

            async def create(new_sock):
                return await base(protocol_factory, *args, sock=new_sock, **kwargs)

            # uvicorn's shutdown closes it: stop listening for good and leave the board
            server = PausableServer(first, create, spare, on_close=self.placement.stop)
        finally:
            spare.close()
        return self.placement.attach(server)


try:
    from uvloop import Loop as _BaseLoop
except ImportError:  # uvicorn's own fallback
    _BaseLoop = asyncio.SelectorEventLoop


class PlacementLoop(_PlacementLoop, _BaseLoop):
    """The loop uvicorn would use (uvloop, else asyncio's) with :class:`_PlacementLoop`."""


def loop_factory() -> asyncio.AbstractEventLoop:
    """uvicorn's ``loop=`` in each worker process of ``quatrack serve --workers N`` (N > 1): the
    loop uvicorn would use (uvloop, else asyncio's), whose listening server follows the placement
    rule. The run directory and the worker count come from ``QUATRACK_*`` like the app's settings."""
    from .settings import Settings

    settings = Settings.from_env()
    loop = PlacementLoop()
    if settings.run_dir is not None and settings.workers > 1:
        loop.placement = Placement(LoadBoard(Path(settings.run_dir) / "placement"))
    return loop


def placement_of_running_loop() -> Placement | None:
    """The placement of the running event loop (None: one worker, tests' in-thread servers)."""
    return getattr(asyncio.get_running_loop(), "placement", None)

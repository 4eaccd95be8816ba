"""Load-aware placement of WebSocket sessions across the worker processes of ``quatrack serve --workers N``.

Why: the workers accept on one shared listening socket and the kernel wakes all of them for a
new connection; whichever runs first takes it — and libuv then accepts *every* connection waiting
in the queue in one go. Measured (bench/RESULTS.md, sessions 18 and 23): two sessions opened
together landed on the same worker 4 times in 12, four sessions all on one worker 5 times in 12 —
one worker tracked every stream while the other idled.

Mechanism (standard parts only: the kernel's shared accept queue, ``flock``, ``SCM_RIGHTS`` over a
Unix socket, uvicorn's own ``loop=`` factory option), two parts that follow one rule — *a worker
serves a new connection only while its load is no more than the least-loaded worker's*:

- **Listening** (for connections that arrive one after another): a worker over its share stops
  listening on the shared socket until the others have caught up; the kernel then hands the next
  connection to a worker that still listens. Connections are never refused: they wait in the
  socket's accept queue, which belongs to the socket, not to any one process.
- **Passing** (for bursts, which arrive before any worker could stop listening): every accepted
  connection goes through a gate (:class:`_Gate`, the protocol the loop's server makes) *before a
  byte of it is read*. Under the board's lock the gate counts the connection for the least-loaded
  worker (this one on a tie); if that is another worker, the socket is sent there over a Unix
  datagram socket (``sendmsg`` with ``SCM_RIGHTS``), which serves it as if it had accepted it
  (``loop.connect_accepted_socket`` with uvicorn's own protocol factory), and this worker closes
  its descriptor — the connection lives on in the other's. The HTTP upgrade has not been read, so
  nothing of uvicorn's state has to move.

Load = sessions + *pending* connections: accepted (or passed) here, not yet known to be plain
HTTP, whose session has not opened yet. A connection's first bytes tell: a request head without
``websocket`` in it is HTTP (a probe, a REST call: it stops counting at once); a WebSocket
handshake counts until its session opens (the session then counts instead, :meth:`sessions_changed`)
or for at most :data:`PENDING_S`. So a burst of N handshakes is spread N/W per worker before any
session exists, and probes and REST calls do not skew the count.

- Every worker publishes ``load listening time sessions`` in ``RUN_DIR/placement/PID``
  (:class:`LoadBoard`), a file it holds an exclusive ``flock`` on for its lifetime: the kernel
  drops the lock of a worker that dies, and readers ignore (and delete) a file nobody holds. The
  load field is changed by *deltas* under one exclusive ``flock`` on ``RUN_DIR/placement/.lock``,
  by the worker itself and by a worker passing it a connection, so a connection in flight between
  two workers is already counted for its receiver; the lock is held for a few reads and writes
  of 48-byte records (microseconds), and never waited for longer than :data:`LOCK_WAIT_S`.
- Rule: serve (listen) iff load ≤ the smallest load of the other live workers (ties serve), so the
  least-loaded worker always listens and /healthz, /readyz and /metrics always find a worker.
- When: the gate decides for each connection; listening is re-decided when this worker's load
  changes and every :data:`POLL_S` for the other workers' changes; the poll looks for newly
  started workers every :data:`RELIST_S`.
- Pausing is closing this process's listening *server* (uvloop's, or asyncio's) while a
  duplicate of the socket's descriptor keeps the socket itself open here; resuming creates a new
  server on another duplicate. uvicorn gets a :class:`PausableServer` from ``create_server``, so
  its shutdown (close, then wait) works on whichever server is current.
- Blocking mode: ``O_NONBLOCK`` belongs to a socket's open file description, which every
  duplicate shares — the listening socket's in every worker, a passed connection's in its sender
  and receiver — and ``socket.dup()`` re-applies the Python object's timeout to it. Every socket
  object placement duplicates or makes from a descriptor (the listening socket, its spare, a
  passed connection) is set non-blocking first, so nothing here can make a shared socket
  blocking (a blocking listening socket left a worker that had drained the accept queue stuck in
  ``accept()`` with its accepted connections unread: session 25's 30-60 s handshakes;
  tests/test_workers.py checks every descriptor's mode in /proc, also after a burst was passed).

Why it spreads: under the lock a gate always counts a connection for a least-loaded worker, so
after every decision the loads differ by at most one; a session replaces its pending connection
in the count. Each worker then holds at most ⌈n / W⌉ of n sessions opened at once or one after
another (tests/test_workers.py checks both against the sockets' owners in /proc).

Failure modes (documented in bench/RESULTS.md, "Session 24"):

- Sessions are never moved once served: if sessions on one worker close, new ones go to it until
  the counts are even again.
- A connection passed to a worker that dies before reading it from its Unix socket is closed with
  it (the client reconnects). A pass that fails (the other worker's socket is gone, its queue of
  ``net.unix.max_dgram_qlen`` = 10 messages is full) serves the connection here instead.
- A handshake whose head arrives in pieces, or whose session is refused (503, 401, 404), counts as
  pending until it closes or for :data:`PENDING_S` at most.
- The views are refreshed every :data:`POLL_S`; in between, every worker may be paused for up to
  that long (A paused for B's count, B's sessions grew, A has not looked yet): connections wait in
  the queue meanwhile, they are not refused (and a worker that accepts passes them on).
- A worker whose event loop is stuck stops refreshing its entry; after :data:`STALE_S` the others
  ignore it (they listen, and pass nothing to it), so a hung worker cannot hold every connection.
- A newly started worker is seen by the poll within :data:`RELIST_S` (by a gate at once). It
  joins with load 0 and so gets the next connections while it is still loading its models
  (``/readyz`` says 503 meanwhile; a session opened then waits for the model).
- Over TLS (uvicorn's ``ssl``; ``quatrack serve`` has no TLS, a balancer terminates it) the gate
  runs after the TLS handshake, whose session cannot move: nothing is passed, bursts are placed as
  before (listening only).
- Any error reading the board makes a worker listen and serve (fails open: the old, random
  placement). With asyncio's own loop instead of uvloop the same holds (its accept loop also
  drains the queue; the gate passes the excess).
"""

from __future__ import annotations

import array
import asyncio
import contextlib
import fcntl
import logging
import os
import socket
import threading
import time
from pathlib import Path

from .workers import held_or_removed

log = logging.getLogger("quatrack.service")

POLL_S = 0.05  # how often a worker re-reads the others' counts
STALE_S = 10.0  # an entry not refreshed for this long belongs to a stuck worker: ignored
HEARTBEAT_S = 1.0  # a worker rewrites its unchanged entry this often (what STALE_S checks)
RELIST_S = 1.0  # the poll looks for newly started workers this often (a gate: always)
LOCK_WAIT_S = 0.005  # longest wait for the board's lock on the event loop (it is held for microseconds)
DRIFT_S = 1.0  # a board count that differs from what the worker holds for this long is reset
PENDING_S = 5.0  # a WebSocket handshake counts as load for at most this long before its session opens
_RECORD = 48  # bytes per entry: "load listening monotonic-time sessions", space-padded, one write


class LoadBoard:
    """``directory/PID``: each live worker's load, whether it listens, when it last wrote
    (``time.monotonic()``, one clock for every process of the machine) and its sessions, as one
    fixed-size record written in place with one ``pwrite``. Every write of any record happens under
    the exclusive ``flock`` of ``directory/.lock`` (:meth:`locked`), so that the load field can be
    changed by deltas (:meth:`add`) by its worker and by the worker passing it a connection. A
    worker makes its file under a hidden name, locks it, then renames it into place, so a reader
    never takes a live worker's file for a dead one's."""

    def __init__(self, directory: Path) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.pid = os.getpid()
        self._fd: int | None = None
        self._lock: int | None = None
        self._others: dict[int, int] = {}  # pid -> an open (read-write) descriptor of its file
        self._listed = 0.0

    def join(self) -> None:
        if self._fd is not None:
            return
        self._lock = os.open(self.dir / ".lock", os.O_RDWR | os.O_CREAT, 0o600)
        tmp = self.dir / f".{self.pid}.tmp"
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        fcntl.flock(fd, fcntl.LOCK_EX)
        self._fd = fd
        with self.locked():
            self._write(fd, (0, True, 0))
        os.replace(tmp, self.dir / str(self.pid))

    @contextlib.contextmanager
    def locked(self):
        """The board's write lock, held by any worker for a few system calls. Not waited for
        indefinitely: a holder that is descheduled, or stopped (SIGSTOP, a debugger), would stall
        this worker's event loop as long. After :data:`LOCK_WAIT_S` of retries (every 0.2 ms) the
        caller goes on without it — a count may then be off by one until the connections it
        concerns close (fails open, like any other board error)."""
        if self._lock is None:
            yield
            return
        deadline = time.monotonic() + LOCK_WAIT_S
        while True:
            try:
                fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                held = True
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    held = False
                    log.warning("placement: the board's lock is held elsewhere; going on without it")
                    break
                time.sleep(0.0002)
        try:
            yield
        finally:
            if held:
                fcntl.flock(self._lock, fcntl.LOCK_UN)

    @staticmethod
    def _read(fd: int) -> tuple[int, bool, float, int] | None:
        """(load, listening, time written, sessions), or None for a record not written yet."""
        fields = os.pread(fd, _RECORD, 0).split()
        try:
            return int(fields[0]), fields[1] == b"1", float(fields[2]), int(fields[3])
        except (IndexError, ValueError):
            return None

    @staticmethod
    def _write(fd: int, entry: tuple[int, bool, int]) -> None:
        load, listening, sessions = entry
        record = f"{max(load, 0)} {int(listening)} {time.monotonic():.3f} {sessions}".ljust(_RECORD - 1) + "\n"
        os.pwrite(fd, record.encode(), 0)

    def publish(self, listening: bool, sessions: int) -> None:
        """This worker's listening state and sessions (its load is kept). Takes the lock."""
        if self._fd is None:
            return
        with self.locked():
            now = self._read(self._fd)
            self._write(self._fd, (now[0] if now else 0, listening, sessions))

    def add(self, pid: int, delta: int) -> bool:
        """Add ``delta`` to worker ``pid``'s load (this worker's or a live other's). Call under
        :meth:`locked`. False if ``pid`` is not on the board (any more)."""
        fd = self._fd if pid == self.pid else self._others.get(pid)
        if fd is None or delta == 0:
            return fd is not None
        now = self._read(fd)
        if now is None:
            return False
        load, listening, _, sessions = now
        self._write(fd, (load + delta, listening, sessions))
        return True

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

    def own(self) -> int:
        """This worker's load as the board has it (including connections passed to it in flight)."""
        now = self._read(self._fd) if self._fd is not None else None
        return now[0] if now else 0

    def entries(self, relist: bool = True) -> dict[int, tuple[int, bool]]:
        """{pid: (load, listening)} of the other live workers whose entry is fresh; files of
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
                entry = self._read(fd)
                if entry is not None and now - entry[2] <= STALE_S:
                    out[pid] = (entry[0], entry[1])
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
                self._others[int(name)] = os.open(self.dir / name, os.O_RDWR)
            except FileNotFoundError:
                continue

    def close(self) -> None:
        for fd in self._others.values():
            os.close(fd)
        self._others.clear()
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None


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
            entry = LoadBoard._read(fd) if held else None
            if entry is not None:
                out[int(name)] = (entry[3], entry[1])
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
        sock.setblocking(False)  # dup() applies the object's timeout to the shared socket (module doc)
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
    worker's event loop (:func:`loop_factory`). Its gates (:class:`_Gate`) route each new
    connection; the session limiter tells it of session changes (``SlotLimiter.on_change``, set in
    the app's lifespan); its inbox receives the connections other workers pass to it."""

    def __init__(self, board: LoadBoard) -> None:
        self.board = board
        self.sessions = 0
        self.server: PausableServer | None = None
        self.factory = None  # uvicorn's protocol factory: what serves a connection here
        self.pending: dict[object, float] = {}  # handshakes served here, session not open yet -> since
        self._inbox: socket.socket | None = None  # connections passed here arrive on it
        self._out: socket.socket | None = None  # this worker passes connections through it
        self._poller: asyncio.Task | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: int | None = None
        self._published: tuple[bool, int] | None = None
        self._published_at = 0.0
        self._drift_since: float | None = None  # since when the board's count differs from this worker's
        self.passing = True  # False over TLS: a socket can be passed on, its TLS session cannot

    def inbox_path(self, pid: int) -> Path:
        return self.board.dir / f"{pid}.sock"

    def attach(self, server: PausableServer, factory) -> PausableServer:
        self.server, self.factory = server, factory
        self._loop = asyncio.get_running_loop()
        self._thread = threading.get_ident()
        self.board.join()
        try:
            self._out = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._out.setblocking(False)
            inbox = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            inbox.setblocking(False)
            inbox.bind(str(self.inbox_path(self.board.pid)))
            self._inbox = inbox
            self._loop.add_reader(inbox.fileno(), self._receive)
        except OSError:  # e.g. a run directory whose path is too long for a Unix socket's address
            log.exception("placement: no inbox; connections are not passed to this worker")
        self._poller = self._loop.create_task(self._poll())
        return server

    # --- where a new connection is served -------------------------------------------------------
    def route(self, transport) -> bool:
        """Count a new connection for a least-loaded worker (this one on a tie), under the board's
        lock; if that is another worker, pass the socket to it. True if it was passed (the caller
        then closes this worker's descriptor of it)."""
        me = self.board.pid
        target = me
        try:
            with self.board.locked():
                others = {pid: load for pid, (load, _) in self.board.entries().items()}
                if self.passing and others and self.board.own() > min(others.values()):
                    target = min(others, key=lambda pid: (others[pid], pid))
                self.board.add(target, +1)
        except OSError:
            log.exception("placement: the board could not be read; serving here")
            return False
        if target == me:
            return False
        if self._send(target, transport):
            return True
        try:
            with self.board.locked():
                self.board.add(target, -1)
                self.board.add(me, +1)
        except OSError:
            pass
        return False

    def _send(self, pid: int, transport) -> bool:
        sock = transport.get_extra_info("socket")
        if sock is None or self._out is None:
            return False
        try:
            # sendmsg, not socket.send_fds: that one drops its address argument (CPython 3.11)
            self._out.sendmsg([b"c"], [(socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", [sock.fileno()]))], 0,
                              str(self.inbox_path(pid)))
        except OSError:  # its inbox is gone (it stopped) or full: serve it here
            return False
        return True

    def _receive(self) -> None:
        """The inbox is readable: serve each connection passed here (counted already by its sender)."""
        while self._inbox is not None:
            try:
                _, fds, _, _ = socket.recv_fds(self._inbox, 16, 4)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                log.exception("placement: the inbox could not be read")
                return
            for fd in fds:
                self._loop.create_task(self._adopt(fd))

    async def _adopt(self, fd: int) -> None:
        try:
            sock = socket.socket(fileno=fd)
            # The descriptor shares its open file description (and so its O_NONBLOCK) with the
            # sender's, which its loop made non-blocking; the object made from it says "blocking"
            # (timeout None), and a dup() of it would re-apply that to the connection. Made
            # non-blocking on the object too (what asyncio's connect_accepted_socket does itself,
            # and uvloop's create_server; uvloop's connect_accepted_socket leaves the object as is).
            sock.setblocking(False)
        except OSError:
            os.close(fd)
            self._count(-1)
            return
        try:
            if self.server is None or self.server.closed:
                raise ConnectionAbortedError("this worker is stopping")
            await self._loop.connect_accepted_socket(lambda: _Gate(self, passed=True), sock)
        except Exception as exc:
            if not isinstance(exc, ConnectionAbortedError):
                log.exception("placement: a connection passed here could not be served")
            sock.close()
            self._count(-1)

    # --- load: pending handshakes and sessions ---------------------------------------------------
    def _count(self, delta: int) -> None:
        """This worker's load changes by ``delta``; re-decide listening."""
        try:
            with self.board.locked():
                self.board.add(self.board.pid, delta)
        except OSError:
            pass
        self.evaluate()

    def served(self) -> object:
        """A connection is served here (counted already): it is pending until its first bytes."""
        token = object()
        self.pending[token] = time.monotonic()
        return token

    def first_bytes(self, token: object, data: bytes) -> None:
        """A complete request head without ``websocket`` in it is plain HTTP: no session, no load."""
        if token in self.pending and b"\r\n\r\n" in data and b"websocket" not in data[:8192].lower():
            self.release(token)

    def release(self, token: object) -> None:
        if self.pending.pop(token, None) is not None:
            self._count(-1)

    def sessions_changed(self, sessions: int) -> None:
        """This worker now holds ``sessions``. Called on the event loop by the route (via the
        limiter) before the WebSocket handshake is answered. A session that opens takes over the
        load of a pending handshake (the oldest: which one is the same for the count)."""
        if self._loop is None:
            self.sessions = sessions
            return
        if threading.get_ident() != self._thread:
            self._loop.call_soon_threadsafe(self.sessions_changed, sessions)
            return
        delta, self.sessions = sessions - self.sessions, sessions
        for token in list(self.pending)[:max(delta, 0)]:
            del self.pending[token]
            delta -= 1
        self._count(delta)

    def evaluate(self, relist: bool = True) -> None:
        """Listen or not, by the rule; publish this worker's entry if it changed (or is due for
        its heartbeat). ``relist``: also look for workers started since the last look."""
        server = self.server
        if server is None or server.closed:
            return
        try:
            others = [n for n, _ in self.board.entries(relist).values()]
            mine = self.board.own()
        except OSError:
            log.exception("placement: the board could not be read; listening")
            others, mine = [], 0
        if not others or mine <= min(others):
            server.resume()
        else:
            server.pause()
        entry, now = (server.want_listening, self.sessions), time.monotonic()
        if entry != self._published or now - self._published_at >= HEARTBEAT_S:
            try:
                self.board.publish(*entry)
                self._published, self._published_at = entry, now
            except OSError:
                pass

    async def _poll(self) -> None:
        while self.server is not None and not self.server.closed:
            await asyncio.sleep(POLL_S)
            expired = [t for t, since in self.pending.items() if time.monotonic() - since > PENDING_S]
            for token in expired:
                del self.pending[token]
            if expired:
                self._count(-len(expired))
            else:
                self.evaluate(relist=False)
            self._heal()

    def _heal(self) -> None:
        """Reset this worker's load on the board to what it holds (sessions + pending handshakes)
        when the two have differed for :data:`DRIFT_S`: a connection passed here is in flight for
        milliseconds, so a longer difference is a count lost when the lock was not had
        (:meth:`LoadBoard.locked`), and would otherwise skew placement for good."""
        try:
            if self.board.own() == self.sessions + len(self.pending):
                self._drift_since = None
                return
            now = time.monotonic()
            if self._drift_since is None:
                self._drift_since = now
            elif now - self._drift_since >= DRIFT_S:
                with self.board.locked():
                    self.board.add(self.board.pid, self.sessions + len(self.pending) - self.board.own())
                self._drift_since = None
        except OSError:
            pass

    def stop(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
        if self._inbox is not None:  # connections still queued in it are closed with it
            try:
                self._loop.remove_reader(self._inbox.fileno())
            except (RuntimeError, ValueError):
                pass
            self._inbox.close()
            self._inbox = None
            try:
                self.inbox_path(self.board.pid).unlink()
            except FileNotFoundError:
                pass
        if self._out is not None:
            self._out.close()
            self._out = None
        self.board.leave()


class _Gate(asyncio.Protocol):
    """The protocol the worker's listening server makes for each accepted connection, and the
    inbox for each connection passed here. At ``connection_made`` — before the loop starts reading
    the socket — it asks :meth:`Placement.route` where the connection is served; passed on, it
    closes this worker's descriptor (the receiver holds its own). Served here, it hands the
    transport to uvicorn's protocol, and at the first bytes steps aside (``set_protocol``) after
    telling the placement whether they are a plain HTTP request."""

    def __init__(self, placement: Placement, passed: bool = False) -> None:
        self.placement, self.passed = placement, passed
        self.inner = None
        self.transport = None
        self.token = None

    def connection_made(self, transport) -> None:
        self.transport = transport
        if not self.passed and self.placement.route(transport):
            transport.abort()  # this descriptor only: the connection lives on in the receiver's
            return
        self.token = self.placement.served()
        self.inner = self.placement.factory()
        self.inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        self.transport.set_protocol(self.inner)  # from now on the loop calls uvicorn's protocol
        self.placement.first_bytes(self.token, data)
        self.inner.data_received(data)

    def eof_received(self):
        return self.inner.eof_received() if self.inner is not None else None

    def connection_lost(self, exc) -> None:
        if self.inner is not None:
            self.placement.release(self.token)
            self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        if self.inner is not None:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.inner is not None:
            self.inner.resume_writing()


class _PlacementLoop:
    """Mixed into the event loop class of a worker process: ``create_server(sock=...)`` (what
    uvicorn calls in each worker with the shared socket) returns a :class:`PausableServer`
    governed by the loop's :class:`Placement`, whose connections go through :class:`_Gate`."""

    placement: Placement | None = None

    async def create_server(self, protocol_factory, *args, sock=None, **kwargs):
        base = super().create_server
        placement = self.placement
        if placement is None or sock is None:
            return await base(protocol_factory, *args, sock=sock, **kwargs)
        # O_NONBLOCK belongs to the socket's open file description, shared by every duplicate in
        # every worker, and ``socket.dup()`` re-applies the Python object's timeout to it: the
        # socket uvicorn hands over says "blocking" (None), so each dup made the shared listening
        # socket blocking until the loop set it back. A worker whose loop then drained the accept
        # queue blocked in accept() until the next connection came, its accepted connections
        # unread meanwhile: the 30-60 s handshakes of sessions opened together (issue 15).
        # Non-blocking on the object too, every duplicate keeps it so.
        sock.setblocking(False)

        def gate():
            return _Gate(placement)

        spare = sock.dup()  # before the loop takes ``sock`` over (closing the server closes it)
        try:
            first = await base(gate, *args, sock=sock, **kwargs)

            async def create(new_sock):
                return await base(gate, *args, sock=new_sock, **kwargs)

            # uvicorn's shutdown closes it: stop listening for good and leave the board
            server = PausableServer(first, create, spare, on_close=placement.stop)
        finally:
            spare.close()
        placement.passing = kwargs.get("ssl") is None  # the gate runs after a TLS handshake
        return placement.attach(server, protocol_factory)


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

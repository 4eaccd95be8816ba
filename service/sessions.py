"""WebSocket tracking sessions: one receiver, one processor, and a single-slot mailbox between.

Why this shape: frames may arrive faster than the CPU can track them. The receiver never blocks
on tracking; it keeps only the *newest* unprocessed frame (a newer one replaces it and counts as
skipped), so memory per session is bounded by one frame and latency by one processing time. The
processor runs the tracker in the shared thread pool, one frame at a time, so a session's
tracker is never used by two threads at once; the frame is taken from the mailbox when a thread
starts on it, not when the job is queued, so a frame never goes stale waiting for a thread.
Control messages (camera, reset, init) travel with the frame they preceded, so they act in the
order the client sent them even when frames are skipped. Bad input is answered with an error message and the session stays open.
A frame's header may give the frame an id, echoed in every answer about it (:meth:`TrackSession._on_header`):
with frames skipped and refused, a client that sends ahead of the answers cannot match them by counting.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import threading
import time
import uuid
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field, replace
from typing import Callable

from pydantic import ValidationError
from starlette.websockets import WebSocket, WebSocketDisconnect, WebSocketState

from quatrack.recognition.images import ImageError
from quatrack.recognition.trackio import step_message
from quatrack.recognition.match import ModelIndex
from quatrack.recognition.video import TrackStep
from quatrack.viewsets.camera import CAMERA_FIELDS
from quatrack.viewsets.store import ObjectModel
from quatrack.viewsets.errors import SpecError
from quatrack.viewsets.spec import parse_pose

from .codes import CAMERA_REQUIRED, RATE_LIMITED, TOO_LARGE, UNSUPPORTED_IMAGE, error_body
from .errors import ApiError
from .imagein import decode_upload, size_mismatch, sniff
from .learning import learns, store_session_views
from .metrics import Metrics
from .ros import add_to_track_message
from .schemas import CameraIn, CameraMessage
from .settings import Settings
from .tracker_factory import TRACKER_KIND, make_tracker

log = logging.getLogger("quatrack.service")
MAX_CONTROLS = 32  # control messages waiting for a frame; more is a misbehaving client
MAX_TEXT = 65_536  # characters in one text message: a camera or a control is a few hundred
# answers owed to frames that newer ones replaced (``dropped``) before the session stops reading:
# a client that sends without reading the answers (they wait in the socket's buffers, the
# processor's send waits for them) is then not read either — TCP pushes back on its sending —
# until it reads; one that reads nothing for ``idle_timeout_s`` is closed ("stalled")
MAX_UNANSWERED = 64
CLOSE_TIMEOUT_S = 5.0  # the session's closing frame, sent at its end: waited for this long at most
# a frame header's optional "id", echoed in every answer about that frame (_frame_id): a string of
# at most this many characters, or an integer a JavaScript client reads back exactly
MAX_ID_CHARS = 64
MAX_ID_INT = 2**53 - 1
# a lock-step frame over QUATRACK_MAX_FPS waits for its token this long at most (_borrow_token);
# a longer wait (QUATRACK_MAX_FPS below 1) is refused as before, the client's timeouts being seconds
MAX_HOLD_S = 1.0
# RFC 6455 "message too big": the WebSocket layer (uvicorn's ws_max_size, twice
# QUATRACK_MAX_BODY_BYTES) closes with it a frame too large to be read at all
MESSAGE_TOO_BIG = 1009


class SessionLimiter:
    """Counts open sessions; the route refuses a new one with 503 when full."""

    def __init__(self, max_sessions: int) -> None:
        self.max = max_sessions
        self.open: set[str] = set()

    def try_open(self) -> str | None:
        if len(self.open) >= self.max:
            return None
        sid = uuid.uuid4().hex[:12]
        self.open.add(sid)
        return sid

    def close(self, sid: str) -> None:
        self.open.discard(sid)


@dataclass
class _PendingFrame:
    number: int
    time_s: float
    data: bytes
    arrival: float  # perf_counter
    controls: list = field(default_factory=list)
    id: int | str | None = None  # the client's id of the frame (its header's "id"), echoed in its answers
    reason: str | None = None  # why it was not tracked, when answered ``dropped`` for another cause than a newer frame
    hold_until: float = 0.0  # perf_counter: not tracked before (a lock-step frame over the rate, _borrow_token)


class _SessionError(Exception):
    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code, self.message = code, message


def _seconds(value) -> float | None:
    """A JSON number as a finite float, else None (a boolean, a string, NaN, or an integer too
    large for a float: ``math.isfinite(10**400)`` raises OverflowError, which ended the session)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        value = float(value)
    except OverflowError:
        return None
    return value if math.isfinite(value) else None


def _frame_id(msg: dict) -> tuple[int | str | None, str | None]:
    """A frame header's optional ``"id"``: ``(id, None)`` (``id`` None when there is none), or
    ``(None, why)`` when it is not an integer (no boolean, ``|id| ≤ 2**53 - 1``) nor a string of
    at most :data:`MAX_ID_CHARS` characters. Only such ids: they come back unchanged, also through
    a JavaScript client's JSON (a larger integer would not), and equal only themselves (a float or
    a list would not make a reliable key)."""
    if "id" not in msg:
        return None, None
    value = msg["id"]
    if isinstance(value, str) and len(value) <= MAX_ID_CHARS:
        return value, None
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) <= MAX_ID_INT:
        return value, None
    return None, (f"'id' must be an integer (at most 2**53 - 1 in size) or a string of at most {MAX_ID_CHARS} "
                  f"characters; got {repr(value)[:40]}")


class TrackSession:
    def __init__(self, ws: WebSocket, sid: str, name: str, model: tuple[ObjectModel, ModelIndex], settings: Settings,
                 executor: Executor, metrics: Metrics, clock: Callable[[], float] = time.monotonic,
                 ros_unit: str | None = None) -> None:
        self.ws, self.sid, self.name = ws, sid, name
        self.ros_unit = ros_unit  # ?format=ros: each pose message also carries "ros" (service/ros.py)
        # the model the session started with, to its end (a retrained one serves new sessions)
        self.model, self.settings, self.executor, self.metrics = model, settings, executor, metrics
        self.camera: CameraIn | None = None
        self.controls: list = []
        # the single-slot mailbox: filled on the event loop, emptied by the worker thread that
        # processes the frame (_process_newest)
        self.mailbox = threading.Lock()
        self.pending: _PendingFrame | None = None
        self.skipped = 0
        # frames replaced by newer ones before their turn, not yet answered (_answer_dropped)
        self.dropped: list[_PendingFrame] = []  # (without their image bytes)
        self.answered = asyncio.Event()  # set when dropped frames were answered (_answer_dropped)
        self.next_frame = 0
        self.last_answered = -1  # the number of the latest frame whose answer was sent (pose or error)
        # messages answering what the client sent after frame N (a refusal on arrival, an error about
        # a header or a control, "ready"), held as (N, message) until frame N's answer is sent
        # (:meth:`reply`, :meth:`_flush_replies`): answers stay in the order of what they answer
        self.replies: list[tuple[int, dict]] = []
        self.last_time: float | None = None
        self.last_clock = 0.0  # the session clock at the latest frame's arrival
        self.header_time: float | None = None
        # the time of a header refused as out_of_order (not after the previous frame's): its frame is
        # answered ``dropped`` at that time, untracked, and the session's clock stays where it was
        self.header_refused: float | None = None
        self.header_id: int | str | None = None  # the next binary frame's id (its header's "id")
        self.t0: float | None = None
        self.wakeup = asyncio.Event()
        self.send_lock = asyncio.Lock()
        self.closed = False
        self.stalled = False  # closed because the client read nothing (_stall)
        # token bucket: max_fps per second, bursts up to 1 s — and at least one frame (max_fps < 1)
        self.burst = max(settings.max_fps, 1.0)
        self.tokens = self.burst
        self.clock = clock
        self.token_time = clock()
        # owned by the processor (worker thread, one job at a time):
        self.tracker = None
        self.tracker_camera = None
        self.last_status: str | None = None
        self.job: Future | None = None  # the processor's job in the pool (_process_newest), the latest

    # --- sending ----------------------------------------------------------------------------------
    async def send(self, payload: dict) -> None:
        if self.closed:
            return
        async with self.send_lock:
            try:  # (bounded: a client reading nothing would hold the session, and what waits to be sent, forever)
                await asyncio.wait_for(self.ws.send_text(json.dumps(payload)), self.settings.idle_timeout_s)
            except asyncio.TimeoutError:
                self._stall()
            except (WebSocketDisconnect, RuntimeError, OSError):
                self.closed = True

    def _log(self, level: int, msg: str, *args, exc_info: bool = False, **fields) -> None:
        """One log line of this session, its id a field (``session_id``), as a request's line
        carries ``request_id``: a session's lines are found by the field, not by reading messages."""
        log.log(level, msg, *args, exc_info=exc_info, extra={"session_id": self.sid, **fields})

    def _stall(self) -> None:
        """The client read nothing for ``idle_timeout_s``: the session ends ("stalled")."""
        if not self.closed:
            self._log(logging.INFO, "session %s: the client read no answer for %g s; closing", self.sid,
                      self.settings.idle_timeout_s)
        self.closed = self.stalled = True
        self.answered.set()  # (wakes a receive loop waiting for the answers to be read)

    async def reply(self, payload: dict) -> None:
        """Send the answer to a message the client sent after the frames received so far: now, or,
        while an earlier frame's answer is still owed, right after it. Why: the README's "each
        frame is answered by one message, in frame order" — a refusal on arrival (``rate_limited``,
        ``unsupported_image``) or a header's ``out_of_order`` was sent at once and overtook the
        pose answers of earlier frames still being tracked, so a client counting answers filed
        them under the wrong frames."""
        if self.replies or self.last_answered < self.next_frame - 1:
            self.replies.append((self.next_frame - 1, payload))
            return
        await self.send(payload)

    async def _flush_replies(self) -> None:
        """Send the held replies whose frame is answered (:meth:`reply`), in the order received."""
        sent = False
        while self.replies and self.replies[0][0] <= self.last_answered:
            _, payload = self.replies.pop(0)
            await self.send(payload)
            sent = True
        if sent:
            self.answered.set()

    async def send_error(self, code: str, message: str, frame: int | None = None,
                         frame_id: int | str | None = None, now: bool = False) -> None:
        """An error message. One about a numbered frame (``frame``: the processor's, in that frame's
        turn) is sent at once; any other answers what the client sent last, after the answers of
        the frames before it (:meth:`reply`), unless ``now`` (the session's own end)."""
        body = {"type": "error", **error_body(code, message)}
        if frame is not None:
            body["frame"] = frame
        if frame_id is not None:  # (the client's id of the frame the error is about: absent without one)
            body["id"] = frame_id
        self._log(logging.INFO, "session %s: %s: %s", self.sid, code, message, code=code)
        await (self.send(body) if frame is not None or now else self.reply(body))

    # --- receiving --------------------------------------------------------------------------------
    async def run(self) -> str:
        """Serve until the client leaves or idles; returns the outcome for the metrics. Logs one
        line as the session opens and one as it ends (outcome, frames, duration)."""
        started = time.perf_counter()
        self._log(logging.INFO, "session opened", object=self.name)
        processor = asyncio.create_task(self._process_loop())
        outcome = "closed"
        try:
            while not self.closed:
                if not await self._answers_read():
                    break
                try:
                    msg = await asyncio.wait_for(self.ws.receive(), self.settings.idle_timeout_s)
                except asyncio.TimeoutError:
                    await self.send_error("idle_timeout", f"no message for {self.settings.idle_timeout_s:g} s; closing",
                                          now=True)
                    outcome = "idle"
                    break
                if msg["type"] == "websocket.disconnect":
                    if msg.get("code") == MESSAGE_TOO_BIG:  # (it was logged and counted "closed", as a client's close)
                        outcome = "too_large"
                        self._log(logging.INFO, "session %s: a frame over %d bytes; closed (1009)", self.sid,
                                  2 * self.settings.max_body_bytes, code=TOO_LARGE)
                    break
                try:
                    if msg.get("bytes") is not None:
                        await self._on_frame(msg["bytes"])
                    elif msg.get("text") is not None:
                        await self._on_text(msg["text"])
                except Exception:  # a bug on one message must not pass for a disconnect (RuntimeError) nor end the session
                    self._log(logging.ERROR, "session %s: a message could not be handled", self.sid, exc_info=True)
                    await self.send_error("internal", "this message could not be handled (logged); the session goes on")
        except (WebSocketDisconnect, RuntimeError):  # receive() after the client left
            outcome = "disconnected"
        finally:
            if self.stalled:
                outcome = "stalled"
            self.closed = True
            self.wakeup.set()
            processor.cancel()
            try:
                await processor
            except (asyncio.CancelledError, Exception):
                pass
            await self._step_finished()
            if self.ws.client_state == WebSocketState.CONNECTED:
                try:  # (a client that reads nothing never lets the close frame out: not waited for)
                    await asyncio.wait_for(self.ws.close(*_close_of(outcome)), CLOSE_TIMEOUT_S)
                except (RuntimeError, OSError, asyncio.TimeoutError):
                    pass
            stored = await store_session_views(self)  # QUATRACK_LEARN_VIEWS (service/learning.py)
            # (a learning session's line says how many views it stored: the protocol has no closing
            # message, and the count was only in the store's own line, found by the session's id)
            learned = {"learned_views_stored": stored} if getattr(getattr(self.tracker, "params", None), "learn", False) else {}
            self._log(logging.INFO, "session ended", object=self.name, outcome=outcome, frames=self.next_frame,
                      duration_s=round(time.perf_counter() - started, 3), **learned)
        return outcome

    async def _step_finished(self) -> None:
        """At the session's end, wait (at most ``idle_timeout_s``) for the tracker's step in
        flight: cancelling the processor stops no worker thread, and the learned views stored
        next (:func:`store_session_views`) were read from the tracker on another thread while
        it stepped — the session's tracker used by two threads at once, the last step's views
        lost. A job still waiting for a thread was cancelled with the processor: none runs."""
        job = self.job
        if job is None or job.done():
            return
        try:
            await asyncio.wait_for(asyncio.wrap_future(job), self.settings.idle_timeout_s)
        except (asyncio.TimeoutError, Exception):  # (the step's own failure was answered, or is moot now)
            pass

    async def _answers_read(self) -> bool:
        """Whether the session may read the next message: fewer than :data:`MAX_UNANSWERED`
        frames wait for their ``dropped`` answer, now or within ``idle_timeout_s`` (False: the
        client reads nothing). Without it, a client sending frames and reading no answers grew
        ``dropped`` by one frame — its image bytes included — per frame, for as long as it sent."""
        while len(self.dropped) + len(self.replies) >= MAX_UNANSWERED and not self.closed:
            self.answered.clear()
            try:
                await asyncio.wait_for(self.answered.wait(), self.settings.idle_timeout_s)
            except asyncio.TimeoutError:
                self._stall()
        return not self.closed

    def _take_token(self) -> bool:
        now = self.clock()
        rate = self.settings.max_fps
        self.tokens = min(self.burst, self.tokens + (now - self.token_time) * rate)
        self.token_time = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True

    def _borrow_token(self) -> float | None:
        """Right after :meth:`_take_token` refused: the seconds a lock-step frame (every earlier
        frame answered) waits for its token instead of being refused, or None (refused: frames
        in flight, or a wait over :data:`MAX_HOLD_S`). A lock-step client is paced by the
        answers: refused, ``quatrack demo`` lost ~11 % of its frames at 76 frames/s against the
        default 60. Held instead, it is tracked at ``max_fps`` at most, so the limit still bounds
        what a session costs; the debt is at most one token."""
        if self.last_answered != self.next_frame - 1:
            return None
        debt = max(self.tokens, 0.0) - 1.0
        hold = -debt / self.settings.max_fps
        if hold > MAX_HOLD_S:
            return None
        self.tokens = debt
        return hold

    async def _on_frame(self, data: bytes) -> None:
        """A binary frame: refused on arrival, unnumbered, with one of ``codes.REFUSED_FRAME``
        (the client's bookkeeping relies on that set: add a new refusal's code there), else
        numbered, timed and put in the mailbox. Either way the frame takes its header's id, and
        every answer about it carries that id."""
        arrival = time.perf_counter()
        fid, self.header_id = self.header_id, None
        if self.camera is None:
            await self.send_error(CAMERA_REQUIRED, "send the camera as a JSON text message before any frame", frame_id=fid)
            return
        if len(data) > self.settings.max_body_bytes:
            self.header_time = self.header_refused = None
            self.metrics.frames.labels("error").inc()
            await self.send_error(TOO_LARGE, f"a frame may have at most {self.settings.max_body_bytes} bytes", frame_id=fid)
            return
        if sniff(data) is None:  # cheap, and keeps garbage from using a frame number or a time
            self.header_time = self.header_refused = None
            self.metrics.frames.labels("error").inc()
            await self.send_error(UNSUPPORTED_IMAGE, "a binary message must be a JPEG, PNG or WebP frame", frame_id=fid)
            return
        hold = 0.0 if self._take_token() else self._borrow_token()
        if hold is None:
            self.header_time = self.header_refused = None
            self.metrics.frames.labels("rate_limited").inc()
            await self.send_error(RATE_LIMITED, f"more than {self.settings.max_fps:g} frames per second; frame dropped",
                                  frame_id=fid)
            return
        if self.header_refused is not None:
            self._answer_untracked(arrival, fid)
            return
        now = self.clock()
        if self.header_time is not None:
            time_s, self.header_time = self.header_time, None
        elif self.last_time is None:
            self.t0 = now if self.t0 is None else self.t0
            time_s = now - self.t0
        else:
            # the previous frame's time plus the time between their arrivals: the session clock when
            # no frame is timed; after a client's time (say 100 s), its continuation — measuring
            # from the session's start (0.1 s) and bumping by 1 µs put frames 0.1 s apart 1 µs
            # apart, and the velocities blew up (v ≈ −17 000 mesh units/s)
            time_s = self.last_time + max(now - self.last_clock, 1e-6)
        self.last_time, self.last_clock = time_s, now
        number, self.next_frame = self.next_frame, self.next_frame + 1
        self.metrics.frames.labels("received").inc()
        controls, self.controls = self.controls, []
        with self.mailbox:
            stale = self.pending
            if stale is not None:  # not started yet: the newer frame wins
                self.skipped += 1
                controls = _bounded(stale.controls + controls)  # (frame after frame replaced: still bounded)
                self.dropped.append(replace(stale, data=b"", controls=[]))  # (answered, never decoded)
            self.pending = _PendingFrame(number, time_s, data, arrival, controls, fid, hold_until=arrival + hold)
        if stale is not None:
            self.metrics.frames.labels("skipped").inc()
        self.wakeup.set()

    def _answer_untracked(self, arrival: float, fid) -> None:
        """The frame after a header refused as ``out_of_order``: numbered, answered ``dropped`` at the
        client's (refused) time, in frame order, and not tracked. Tracked at a time the session made
        up (the previous frame's plus the gap between arrivals) it moved the session's clock past
        the client's next times, and every later frame was refused in turn. The controls sent
        before it wait for the next tracked frame (this one is never decoded)."""
        time_s, self.header_refused = self.header_refused, None
        number, self.next_frame = self.next_frame, self.next_frame + 1
        self.metrics.frames.labels("received").inc()
        self.metrics.frames.labels("error").inc()
        why = f"not tracked: its time_s {time_s:g} is not after the previous frame's {self.last_time:g}"
        with self.mailbox:
            self.dropped.append(_PendingFrame(number, time_s, b"", arrival, [], fid, why))
        self.wakeup.set()

    async def _on_text(self, text: str) -> None:
        if len(text) > MAX_TEXT:
            await self.send_error("too_large", f"a text message may have at most {MAX_TEXT} characters")
            return
        try:
            msg = json.loads(text)
        except RecursionError:  # a RuntimeError: uncaught, the receive loop took it for a disconnect
            await self.send_error("bad_message", "the JSON is nested too deeply")
            return
        except ValueError:
            await self.send_error("bad_message", "a text message must be a JSON object")
            return
        if not isinstance(msg, dict):
            await self.send_error("bad_message", "a text message must be a JSON object")
            return
        kind = msg.get("type")
        # an untyped object is a camera when it has a camera's field, and any untyped object is one
        # before the camera: {} first was "camera_required" (send the camera), while it was the
        # camera, with every field missing (bad_camera naming them)
        if kind is None and (self.camera is None or any(k in msg for k in CAMERA_FIELDS)) or kind == "camera":
            await self._on_camera(msg)
        elif kind == "frame":
            await self._on_header(msg)
        elif self.camera is None:
            await self.send_error("camera_required", "the first message must be the camera (JSON)")
        elif kind == "reset":
            self._control(("reset",))
            self.header_time = self.header_refused = None
        elif kind == "init":
            try:
                pose = parse_pose(msg.get("pose"), "init.pose")
            except SpecError as exc:
                await self.send_error("bad_pose", str(exc))
                return
            ts = _seconds(msg.get("time_s"))
            if ts is None and msg.get("time_s") is not None:  # (was dropped without a word: the pose taken at the next frame)
                await self.send_error("bad_message", "init: 'time_s' must be a finite number of seconds, or left out "
                                                     "(the pose is then the next frame's)")
                return
            self._control(("init", pose.t, pose.q_wxyz, ts))
        else:
            await self.send_error("bad_message", f"unknown message type {repr(kind)[:40]}; use camera, frame, reset or init")

    async def _on_header(self, msg: dict) -> None:
        """``{"type": "frame", "time_s"?, "id"?}``: the time and the id of the next binary frame.
        A header with an id may leave out ``time_s`` (the frame is then timed as an untimed one).
        A valid id names the next frame even when the header's time is refused: that frame is
        still answered (untimed), and the error about the header carries the id too, so a client
        matching answers by id files both under the right frame. Without an id, exactly the
        answers of before."""
        fid, why = _frame_id(msg)
        if why is not None:  # (the whole header ignored, as one with a bad time_s is)
            await self.send_error("bad_message", why)
            return
        pending = any(h is not None for h in (self.header_time, self.header_id, self.header_refused))  # a header without its frame yet
        if fid is not None:
            self.header_id = fid
        if self.camera is None:
            await self.send_error("camera_required", "the first message must be the camera (JSON)", frame_id=fid)
            return
        untimed = fid is not None and "time_s" not in msg
        ts = None if untimed else _seconds(msg.get("time_s"))
        if not untimed and (ts is None or ts < 0):
            await self.send_error("bad_message", "'time_s' must be a finite number of seconds ≥ 0", frame_id=fid)
        elif pending:
            self.header_time = self.header_refused = None
            await self.send_error("out_of_order", "two frame headers in a row; send the binary frame after each",
                                  frame_id=fid)
        elif ts is not None and self.last_time is not None and ts <= self.last_time:
            self.header_refused = float(ts)  # (its frame: answered dropped at this time, untracked)
            await self.send_error("out_of_order", f"time_s {ts:g} is not after the previous frame's {self.last_time:g}",
                                  frame_id=fid)
        else:
            self.header_time = None if ts is None else float(ts)

    def _control(self, op: tuple) -> None:
        self.controls = _bounded([*self.controls, op])

    async def _on_camera(self, msg: dict) -> None:
        # The contract's exchange is one message per frame; a client that wants the camera
        # acknowledged asks for it with "ack": true (then {"type": "ready", ...} answers). The
        # message's forms and fields are schemas.CameraMessage's to check, "ack" included.
        try:
            cam = CameraMessage.model_validate(msg)
            if cam.width is not None and cam.height is not None:
                cam.to_camera()  # the project's own checks (plausibility); else at the first frame
        except ValidationError as exc:
            await self.send_error("bad_camera", CameraIn.error_message(exc))
            return
        except ApiError as exc:
            await self.send_error(exc.code, exc.message)
            return
        first = self.camera is None
        self.camera = cam
        self._control(("camera", cam))
        if cam.ack:
            await self.reply({"type": "ready", "session": self.sid, "object": self.name, "tracker": TRACKER_KIND,
                             "camera_replaced": not first, "learns": self._learns(cam)})

    def _learns(self, camera: CameraIn) -> bool:
        """Whether this session's tracker learns views: its object learns (QUATRACK_LEARN_VIEWS)
        and the camera is a calibration, not a guess (``guessed``)."""
        return learns(self.settings, self.name) and not camera.guessed

    # --- processing -------------------------------------------------------------------------------
    async def _process_loop(self) -> None:
        while not self.closed:
            await self.wakeup.wait()
            self.wakeup.clear()
            if self.pending is None:  # (no frame in flight: frames answered without tracking are owed now)
                await self._answer_dropped(self.next_frame)
                continue
            wait = self.pending.hold_until - time.perf_counter()
            if wait > 0:  # (a lock-step frame over the rate: its token comes then, _borrow_token)
                await asyncio.sleep(wait)
            self.job = self.executor.submit(self._process_newest)
            taken = await asyncio.wrap_future(self.job)
            if taken is None:
                continue
            item, skipped, out = taken
            await self._answer_dropped(item.number)
            if isinstance(out, _SessionError):
                self.metrics.frames.labels("error").inc()
                await self.send_error(out.code, out.message, item.number, item.id)
                self.last_answered = item.number
                await self._flush_replies()
                continue
            out["skipped"] = skipped
            out["latency_ms"] = round((time.perf_counter() - item.arrival) * 1e3, 2)
            add_to_track_message(out, self.ros_unit)
            self.metrics.frames.labels("processed").inc()
            self.metrics.frame_latency.observe(out["latency_ms"] / 1e3)
            await self.send(out)
            self.last_answered = item.number
            await self._flush_replies()

    async def _answer_dropped(self, before: int) -> None:
        """Answer, in order, the frames numbered below ``before`` that newer ones replaced: the
        contract's "for each frame the server sends one JSON text message" holds when a client
        sends faster than the tracker runs (a burst got 2 answers for 20 frames, and a client
        reading one answer per frame sent waited forever). Such a frame was not tracked: its
        message is ``lost`` with no pose, ``"dropped": true`` and the reason; the next processed
        frame's ``skipped`` still counts them. Sent just before the answer of the frame that
        replaced them, so answers stay in frame order. A frame answered without being tracked for
        another reason (:meth:`_answer_untracked`: its ``reason``) goes the same way, sorted
        among them by number."""
        with self.mailbox:
            early = sorted((d for d in self.dropped if d.number < before), key=lambda d: d.number)
            self.dropped = [d for d in self.dropped if d.number >= before]
        newer = "not tracked: a newer frame arrived before this one's turn (the newest is tracked)"
        for d in early:
            why = d.reason or newer
            msg = {**_message(d, TrackStep(d.number, d.time_s, "lost", reason=why)), "dropped": True, "skipped": 0,
                   "latency_ms": round((time.perf_counter() - d.arrival) * 1e3, 2)}
            await self.send(add_to_track_message(msg, self.ros_unit))
            self.last_answered = max(self.last_answered, d.number)
            await self._flush_replies()
        if early:
            self.answered.set()

    def _process_newest(self) -> tuple[_PendingFrame, int, dict | _SessionError] | None:
        """Worker thread: take the session's newest frame *now*, when a thread is free, and
        process it. Taking it on the event loop before the job waits in the pool's queue (every
        thread busy with other sessions or re-anchoring) would process a frame that went stale
        while waiting, and its newer successor only after it; taken here, the newest wins.
        The mailbox is shared with the event loop (:meth:`_on_frame`), hence its lock (held for
        a few attribute reads and writes on either side)."""
        with self.mailbox:
            item, skipped = self.pending, self.skipped
            self.pending, self.skipped = None, 0
        if item is None:
            return None
        self.metrics.frame_wait.observe(time.perf_counter() - item.arrival)
        try:
            return item, skipped, self._process(item)
        except _SessionError as exc:
            return item, skipped, exc

    def _process(self, item: _PendingFrame) -> dict:
        """Worker thread: apply the controls, decode, step the tracker. Raises _SessionError."""
        for op in item.controls:
            if op[0] == "camera":
                self.tracker, self.tracker_camera = None, op[1]
            elif op[0] == "reset" and self.tracker is not None:
                self.tracker.reset()
        try:
            image = decode_upload(item.data, self.settings.max_image_pixels)
        except ApiError as exc:
            raise _SessionError(exc.code, exc.message) from None
        h, w = image.shape[:2]
        cam_in = self.tracker_camera
        if cam_in.width is not None and (cam_in.width, cam_in.height) != (w, h):
            try:  # (what to send for this size when the frames are the camera's own, resized)
                msg = size_mismatch(cam_in.to_camera(), w, h)
            except ApiError:  # (implausible intrinsics: the size is the first thing to say)
                msg = None
            raise _SessionError("bad_image", msg or f"the camera is for {cam_in.width}×{cam_in.height} px images but the "
                                                    f"image is {w}×{h} px")
        if self.tracker is None:
            model, index = self.model
            try:
                camera = cam_in.to_camera((w, h))
            except ApiError as exc:  # a camera without a size, implausible for this frame's
                raise _SessionError(exc.code, exc.message) from None
            self.tracker = make_tracker(model, camera, index, self.settings.locate_max_pixels, self.executor,
                                        learn=self._learns(cam_in), sources=self.settings.tracker_sources,
                                        relocate_interval_s=self.settings.relocate_interval_s)
            self.tracker_camera = cam_in.model_copy(update={"width": w, "height": h})
        for op in item.controls:
            if op[0] == "init":
                try:
                    self.tracker.init_pose(op[1], op[2], op[3])
                except ValueError as exc:
                    raise _SessionError("bad_pose", str(exc)) from None
        try:
            step = self.tracker.step(image, item.time_s)
        except ImageError as exc:
            raise _SessionError("bad_image", str(exc)) from None
        except ValueError as exc:  # e.g. time going backwards after an init at a later time
            raise _SessionError("bad_frame", str(exc)) from None
        except Exception:  # a tracker bug must not end the session nor leak a traceback
            self._log(logging.ERROR, "session %s: tracker failed on frame %d; resetting it", self.sid, item.number,
                      exc_info=True, frame=item.number)
            self.tracker.reset()
            raise _SessionError("internal", "tracking failed on this frame (logged); the tracker was reset") from None
        if step.status == "lost" and self.last_status != "lost":
            self.metrics.losses.inc()
        if step.status == "init" and self.last_status != "init":
            self.metrics.inits.inc()
        self.metrics.statuses.labels(step.status).inc()
        self.metrics.observe_stages(self.metrics.stages, getattr(step, "timings_ms", None))
        self.last_status = step.status
        return _message(item, step)


def _close_of(outcome: str) -> tuple:
    """The arguments of the close ending a session: idle, 1001 (going away) with its error code
    ``idle_timeout`` as the reason, so a client whose send meets the close before it reads the
    error message still learns why (a normal 1000 without a reason made ``Client.track`` raise
    ``"closed"``, as if the server had gone); else 1000 (a stalled client reads nothing, the
    close frame included)."""
    return (1001, "idle_timeout") if outcome == "idle" else (1000,)


def _bounded(controls: list) -> list:
    """Controls waiting for a frame, at most :data:`MAX_CONTROLS`: only the newest camera (the
    one the next frame is tracked with), then the newest of the others. A client flooding
    controls loses the oldest — never the camera: lost, the frames were tracked with the
    previous camera while the session held the new one."""
    cameras = [i for i, c in enumerate(controls) if c[0] == "camera"]
    if len(cameras) > 1:
        controls = [c for i, c in enumerate(controls) if c[0] != "camera" or i == cameras[-1]]
    while len(controls) > MAX_CONTROLS:
        controls.pop(next(i for i, c in enumerate(controls) if c[0] != "camera"))
    return controls


def _message(item: _PendingFrame, step) -> dict:
    """The per-frame message (:func:`recognition.trackio.step_message`), numbered and timed as
    the session received the frame, with the client's id of the frame when it gave one."""
    msg = {**step_message(step), "frame": item.number, "time_s": item.time_s}
    if item.id is not None:
        msg["id"] = item.id
    return msg

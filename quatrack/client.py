"""A Python client for a running ``quatrack serve``: poses of images, tracks of frame streams.

    from quatrack.client import Client

    with Client("http://127.0.0.1:8000", token=None) as client:
        found = client.pose("photo.jpg", "camera.json", object="cookie-box")  # a LocateOut
        for msg in client.track(frames, "camera.json", object="cookie-box"):  # frames: images or (time_s, image)
            print(msg.frame, msg.status, msg.pose)

Results are the service's own pydantic schemas (:mod:`service.schemas`): :class:`LocateOut` for
a pose, :class:`LocateAllOut` for every object searched in one image (``client.pose_all(image,
camera)``), :class:`TrackMessage` per tracked frame. Every error the server answers becomes a
:class:`QuatrackError` carrying its ``code`` (``unknown_object``, ``bad_camera``,
``unauthorized``, ...) and HTTP ``status``; an unreachable server is ``code="unreachable"``. An
error the client finds in its own arguments before sending (a camera file missing, an object
name no store can hold) is an :class:`InputError`, a QuatrackError with the server's code for
it (``bad_camera``, ``invalid_object_name``, ...) and ``status`` None.

:class:`AsyncClient` is the same for asyncio (``await client.pose(...)``, ``async for msg in
client.track(...)``). ``track`` is *lock-step*: it sends a frame, waits for its answer, yields it, then sends the
next, so every frame is tracked and answers arrive in order. :func:`stream` (asyncio) is the
other protocol, for live sources: it sends at a fixed rate regardless and the server skips the
frames it cannot keep up with (``quatrack demo --fps`` and ``quatrack bench serve`` use it).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Literal
from urllib.parse import urlsplit, urlunsplit

import numpy as np

from quatrack.service.codes import REFUSED_FRAME
from quatrack.service.schemas import LocateAllOut, LocateOut, ObjectList, TrackMessage
from quatrack.viewsets.errors import SpecError, StoreError  # (standard library only, as codes: no server stack)


class QuatrackError(Exception):
    """An error answered by the server (``code``, ``message``, HTTP ``status``), or one of the
    client's own: ``code="unreachable"`` when there is no server at the address, ``"timeout"``
    when the server does not answer within the client's ``timeout``, ``"closed"`` when the
    connection is lost in the middle of a stream (a session the server ends keeps the code it
    closes with: ``"idle_timeout"``)."""

    def __init__(self, code: str, message: str, status: int | None = None) -> None:
        super().__init__(f"{code}: {message}" if status is None else f"{status} {code}: {message}")
        self.code, self.message, self.status = code, message, status


class InputError(QuatrackError, ValueError):
    """An error the client finds in its own arguments, before anything is sent (``status``
    None), with the server's code for the same problem: ``bad_camera`` (a camera file missing or
    unreadable, a camera of another type), ``invalid_object_name`` (a name the store cannot hold:
    ``"../etc"``, or none given), ``bad_image`` (an image file that cannot be read, an image of
    another type), ``bad_message`` (a frame's time that is not a number), ``invalid_input`` (an
    ``fps`` ≤ 0), or ``bad_url`` (not a server's address).

    Why: these raised the object-model layer's ``SpecError`` and ``StoreError`` (or
    ``FileNotFoundError``, ``TypeError``), so code catching :class:`QuatrackError`, as the
    README's example does, missed them. Each is still the exception it was (a ``ValueError``;
    for a camera file also a ``SpecError``, for a name a ``StoreError``, for an image file an
    ``OSError``, for an argument of another type a ``TypeError``), so code catching those goes
    on working."""


class _CameraError(InputError, SpecError):
    """A camera file the client cannot read (was :class:`SpecError`)."""


class _ObjectNameError(InputError, StoreError):
    """An object name the store cannot hold (was :class:`StoreError`)."""


class _FileError(InputError, OSError):
    """An image file the client cannot read (was the ``OSError`` of reading it)."""


class _KindError(InputError, TypeError):
    """An argument of a type the client does not take (was a ``TypeError``)."""


class FrameError(TrackMessage):
    """The answer to one frame the server could not track, yielded by :meth:`Client.track` and
    :meth:`AsyncClient.track` in that frame's place: an error naming the frame (``bad_image``:
    not decodable, another size than the camera's; ``bad_frame``, ``bad_pose``) or a refusal on
    arrival (``unsupported_image``, ``too_large``, ``rate_limited``). Its ``status`` is ``lost``,
    without pose; ``code`` and ``message`` are the server's, ``reason`` is ``"CODE: message"``;
    ``frame`` is the server's number of the frame (None for a frame refused on arrival, which
    gets none), ``index`` the frame's place in the ``frames`` given to ``track`` (from 0: known
    to the client for every frame, a refused one included, while the server's numbers move up
    one after a refusal), ``time_s`` the time the frame was sent with (None: untimed).

    Why: the session stays open after such an error, but ``track`` raised it and closed the
    socket, so one damaged JPEG from a camera ended the whole stream. Errors about the session
    (``unauthorized``, ``unknown_object``, ``closed``, ``idle_timeout``, ...) still raise
    :class:`QuatrackError`."""

    frame: int | None = None
    index: int | None = None
    time_s: float | None = None
    status: Literal["lost"] = "lost"
    pose: None = None
    velocity: None = None
    covariance: None = None
    inliers: int = 0
    latency_ms: float = 0.0
    skipped: int = 0
    code: str
    message: str


def api_token(token: str | None = None) -> str | None:
    """The bearer token a client sends: ``token`` when given, else ``$QUATRACK_API_TOKEN``; an
    empty one is none. The one place the client reads the variable: :class:`Client` read it and
    :func:`stream` did not, so ``quatrack demo --fps`` and ``bench serve`` were refused where
    ``Client`` was let in."""
    if token is None:
        token = os.environ.get("QUATRACK_API_TOKEN")
    return token or None


def auth_headers(token: str | None) -> dict[str, str]:
    """The ``Authorization`` header of a token (none without one)."""
    return {"Authorization": f"Bearer {token}"} if token else {}


def base_urls(url: str) -> tuple[str, str]:
    """``(http_url, ws_url)`` of a server address given as ``http(s)://`` or ``ws(s)://`` HOST[:PORT].
    A path, query or fragment is refused: the client adds the API's own paths."""
    parts = urlsplit(url.strip())
    if parts.scheme not in ("http", "https", "ws", "wss") or not parts.netloc:
        raise ValueError(f"{url!r}: give the server's address, e.g. http://127.0.0.1:8000 or ws://127.0.0.1:8000")
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ValueError(f"{url!r}: give the server's address only (scheme://host:port), without a path")
    try:
        parts.port  # (a port that is not a number, or out of range)
    except ValueError:
        raise ValueError(f"{url!r}: the port must be a number from 1 to 65535") from None
    secure = parts.scheme in ("https", "wss")
    http = urlunsplit(("https" if secure else "http", parts.netloc, "", "", ""))
    ws = urlunsplit(("wss" if secure else "ws", parts.netloc, "", "", ""))
    return http, ws


def camera_json(camera: Any) -> dict:
    """The contract's camera object from a dict, a :class:`PinholeCamera` or a camera file path."""
    from quatrack.tracking.camera import PinholeCamera
    from quatrack.viewsets.camera import camera_to_dict, load_camera

    if isinstance(camera, dict):
        return camera
    if isinstance(camera, PinholeCamera):
        return camera_to_dict(camera)
    if isinstance(camera, (str, os.PathLike)):
        try:
            return camera_to_dict(load_camera(camera))
        except SpecError as exc:  # (its message names the file: "cannot read camera file PATH: no such file")
            raise _CameraError("bad_camera", str(exc)) from None
    raise _KindError("bad_camera", f"camera: a dict, a PinholeCamera or the path of a camera file, not "
                                   f"{type(camera).__name__}")


def image_bytes(image: Any, quality: int = 95) -> bytes:
    """Encoded image bytes from bytes (sent as they are), a path, or a numpy image (BGR or grey:
    JPEG at ``quality``)."""
    if isinstance(image, (bytes, bytearray, memoryview)):
        return bytes(image)
    if isinstance(image, (str, os.PathLike)):
        try:
            return Path(image).read_bytes()
        except OSError as exc:
            raise _FileError("bad_image", f"image {os.fspath(image)}: cannot read it ({exc.strerror or exc})") from None
    if isinstance(image, np.ndarray):
        import cv2

        from quatrack.recognition.images import to_bgr8

        ok, buf = cv2.imencode(".jpg", to_bgr8(image), [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise InputError("bad_image", "image: cannot be encoded as JPEG")
        return buf.tobytes()
    raise _KindError("bad_image", f"image: bytes, a file path or a numpy array, not {type(image).__name__}")


def _error_of(status: int, body: bytes | str) -> QuatrackError:
    try:
        e = json.loads(body)["error"]
        return QuatrackError(str(e["code"]), str(e["message"]), status)
    except (ValueError, KeyError, TypeError):
        text = body.decode("utf-8", "replace") if isinstance(body, bytes) else str(body)
        return QuatrackError("http_error", text.strip()[:200] or f"HTTP {status}", status)


_CODE = re.compile(r"[a-z][a-z0-9_]*")  # a close reason that is an error code (the service's: idle_timeout)


@contextlib.contextmanager
def _typed_stream_errors(url: str, timeout: float) -> Iterator[None]:
    """A stream's failures after the handshake raised as QuatrackError: ``"closed"`` (the
    connection lost), ``"too_large"`` (a frame so large the server closed it: 1009),
    ``"timeout"`` (no answer within ``timeout``); any other exception as it is.
    (A plain context manager: it wraps the blocking and the asyncio streams alike.)"""
    from websockets.exceptions import ConnectionClosed

    try:
        yield
    except ConnectionClosed as exc:
        if exc.rcvd is not None and exc.rcvd.code == 1009:  # (RFC 6455: "message too big")
            # a frame over twice the server's QUATRACK_MAX_BODY_BYTES is not read: the server closes
            # the socket; a smaller one over the limit is answered too_large, as REST answers 413
            raise QuatrackError("too_large", f"{url}: the server closed the connection: {exc.rcvd.reason}") from None
        if exc.rcvd is not None and exc.rcvd.code != 1000 and _CODE.fullmatch(exc.rcvd.reason or ""):
            # the service ends a session with its error code as the close reason (idle_timeout):
            # the error message before it may go unread when a send meets the close first
            raise QuatrackError(exc.rcvd.reason, f"{url}: the server closed the session ({exc.rcvd.code} "
                                                 f"{exc.rcvd.reason})") from None
        why = f" ({exc.rcvd.code} {exc.rcvd.reason})".rstrip() if exc.rcvd is not None else ""
        raise QuatrackError("closed", f"{url}: the connection was closed{why}") from None
    except TimeoutError:
        raise QuatrackError("timeout", f"{url}: no answer within {timeout:g} s") from None


def _message(text: str | bytes) -> dict:
    """One message of the track socket, a JSON object; anything else (not JSON, not an object:
    a proxy's error page, another service at that address) is a QuatrackError ``"protocol"``
    (it was json's or Python's own exception, from inside the stream)."""
    try:
        msg = json.loads(text)
    except (ValueError, RecursionError):
        msg = None
    if not isinstance(msg, dict):
        raise QuatrackError("protocol", f"the server's message is not a JSON object: {str(text)[:80]!r}")
    return msg


def _ws_error(exc: BaseException) -> QuatrackError:
    """A refused WebSocket handshake (its HTTP answer) or a connection failure, as a QuatrackError."""
    from websockets.exceptions import InvalidStatus

    if isinstance(exc, InvalidStatus):
        return _error_of(exc.response.status_code, exc.response.body or b"")
    if isinstance(exc, (OSError, TimeoutError)):
        return QuatrackError("unreachable", f"cannot connect: {exc.strerror if isinstance(exc, OSError) and exc.strerror else exc}")
    return QuatrackError("protocol", str(exc))


class _Endpoint:
    """What :class:`Client` and :class:`AsyncClient` share: the server's URLs, the default object,
    the token (default ``$QUATRACK_API_TOKEN``), the request bodies and the reading of answers.
    Only the transport (blocking or asyncio) differs between the two."""

    def __init__(self, url: str, object: str | None, token: str | None, timeout: float) -> None:
        try:
            self.http_url, self.ws_url = base_urls(url)
        except ValueError as exc:
            raise InputError("bad_url", str(exc)) from None
        self.object = object
        self.token = api_token(token)
        self.timeout = timeout

    @property
    def _headers(self) -> dict[str, str]:
        return auth_headers(self.token)

    def _name(self, object: str | None) -> str:
        """The object's name for the URL path: the store's rule (letters, digits, ``._-``), so
        that no name can reach another path ("../x") or add a query ("a?b=1")."""
        from quatrack.viewsets.names import check_object_name

        name = self.object if object is None else object
        if not name:
            raise _ObjectNameError("invalid_object_name", f"which object? give object=NAME here or to {type(self).__name__}(...)")
        try:
            return check_object_name(name)
        except StoreError as exc:
            raise _ObjectNameError("invalid_object_name", str(exc)) from None

    def _unreachable(self, exc: Exception) -> QuatrackError:
        import httpx

        if isinstance(exc, httpx.TimeoutException) and not isinstance(exc, httpx.ConnectTimeout):
            # (connected, then no answer in time: a slow server, not an absent one)
            return QuatrackError("timeout", f"{self.http_url}: no answer within {self.timeout:g} s")
        return QuatrackError("unreachable", f"{self.http_url}: {exc}")

    @staticmethod
    def _answer(r):
        """``r``, or the server's error as a :class:`QuatrackError`."""
        if r.status_code >= 400:
            raise _error_of(r.status_code, r.content)
        return r

    @staticmethod
    def _pose_files(image: Any, camera: Any) -> dict:
        return {"image": ("image", image_bytes(image), "application/octet-stream"),
                "camera": (None, json.dumps(camera_json(camera)))}

    @staticmethod
    def _pose_all_query(ros_mesh_unit: str | dict[str, str] | None) -> dict[str, str]:
        """``POST /v1/pose``'s query: ``format=ros`` with the mesh units, one for all
        (``"cm"``) or per object (``{"cookie-box": "cm", "cube": "m"}``, a ``None`` key: every
        object not named); none without ``ros_mesh_unit``."""
        if ros_mesh_unit is None:
            return {}
        if isinstance(ros_mesh_unit, dict):
            text = ",".join(str(u) if n is None else f"{n}:{u}" for n, u in ros_mesh_unit.items())
        else:
            text = str(ros_mesh_unit)
        return {"format": "ros", "mesh_unit": text}

    def _track_url(self, object: str | None, ros_mesh_unit: str | None) -> str:
        from urllib.parse import urlencode

        url = f"{self.ws_url}/v1/objects/{self._name(object)}/track"
        if ros_mesh_unit is not None:
            url += "?" + urlencode({"format": "ros", "mesh_unit": ros_mesh_unit})
        return url

    @staticmethod
    def _hello(camera: Any) -> str:
        return json.dumps({**camera_json(camera), "ack": True})

    @staticmethod
    def _frame_parts(item: Any) -> tuple[str | None, bytes]:
        """A frame as sent: an optional ``{"type": "frame", "time_s"}`` text, then the image bytes."""
        if isinstance(item, tuple) and len(item) == 2:
            try:
                time_s = float(item[0])
            except (TypeError, ValueError):
                kind = _KindError if not isinstance(item[0], str) else InputError
                raise kind("bad_message", f"a frame's time_s (the first of its pair) must be a number of seconds, not "
                                          f"{str(item[0])[:40]!r}") from None
            return json.dumps({"type": "frame", "time_s": time_s}), image_bytes(item[1])
        return None, image_bytes(item)

    @classmethod
    def _answer_of(cls, msg: dict, time_s: float | None, index: int | None = None) -> TrackMessage:
        """A lock-step frame's answer: its :class:`TrackMessage`, or a :class:`FrameError` for an
        error about that frame alone (one naming its ``frame``, or a refusal on arrival: the only
        frame in flight); any other error raised as :class:`QuatrackError`."""
        error = msg.get("error") if isinstance(msg.get("error"), dict) else {}
        if msg.get("type") == "error" and ("frame" in msg or error.get("code") in REFUSED_FRAME):
            code, text = str(error.get("code", "error")), str(error.get("message", ""))
            frame = msg.get("frame")
            return FrameError(frame=frame if isinstance(frame, int) and not isinstance(frame, bool) else None,
                              index=index, time_s=time_s, code=code, message=text, reason=f"{code}: {text}",
                              id=msg.get("id"))
        return TrackMessage.model_validate(cls._expect(msg, "pose"))

    @staticmethod
    def _sent_time(item: Any) -> float | None:
        """The ``time_s`` a frame is sent with (None: untimed, the server's clock)."""
        return float(item[0]) if isinstance(item, tuple) and len(item) == 2 else None

    @staticmethod
    def _expect(msg: dict, kind: str) -> dict:
        if msg.get("type") == "error":
            e = msg.get("error") if isinstance(msg.get("error"), dict) else {}
            raise QuatrackError(str(e.get("code", "error")), str(e.get("message", "")))
        if msg.get("type") != kind:
            raise QuatrackError("protocol", f"expected a {kind!r} message, got {str(msg)[:120]}")
        return msg


class Client(_Endpoint):
    """A synchronous client of one server (``http://HOST:PORT``; ``ws://`` is accepted too).
    ``object`` is the default object name of :meth:`pose` and :meth:`track`; ``token`` the
    bearer token (default ``$QUATRACK_API_TOKEN``). Use as a context manager, or :meth:`close`."""

    def __init__(self, url: str = "http://127.0.0.1:8000", object: str | None = None, token: str | None = None,
                 timeout: float = 60.0) -> None:
        import httpx

        super().__init__(url, object, token, timeout)
        self._http = httpx.Client(base_url=self.http_url, headers=self._headers, timeout=timeout)

    # --- REST -------------------------------------------------------------------------------------
    def _request(self, method: str, path: str, **kw):
        import httpx

        try:
            return self._answer(self._http.request(method, path, **kw))
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None

    def objects(self) -> ObjectList:
        """The server's trained objects."""
        return ObjectList.model_validate(self._request("GET", "/v1/objects").json())

    def pose(self, image: Any, camera: Any, object: str | None = None) -> LocateOut:
        """Recognise the object in one image and estimate its pose (``found`` False if absent)."""
        r = self._request("POST", f"/v1/objects/{self._name(object)}/pose", files=self._pose_files(image, camera))
        return LocateOut.model_validate(r.json())

    def pose_all(self, image: Any, camera: Any, ros_mesh_unit: str | dict[str, str] | None = None) -> LocateAllOut:
        """Search every trained object in one image (``POST /v1/pose``): the objects found, each
        with its pose and its ``rivals`` (look-alikes found at the same place with less
        confidence), the objects ``searched``, those ``not_found`` (each with its reason) and the
        models that ``failed`` to load. The server searches every object of its store (~40–60 ms
        each on a 640×480 image where it is found, 1.5–2.5× that where it is not); :meth:`pose`
        searches one. ``ros_mesh_unit``: ``format=ros``, each object found then carries ``ros``
        in metres — one unit for all meshes (``"cm"``) or one per object (``{"cookie-box": "cm",
        "cube": "m"}``; an object found without one carries ``ros_note`` instead)."""
        r = self._request("POST", "/v1/pose", files=self._pose_files(image, camera),
                          params=self._pose_all_query(ros_mesh_unit))
        return LocateAllOut.model_validate(r.json())

    def mesh_edges(self, object: str | None = None) -> np.ndarray:
        """The object's wireframe, (k, 2, 3) segments in mesh units (``GET /v1/objects/{name}/mesh``):
        what an overlay draws."""
        data = self._request("GET", f"/v1/objects/{self._name(object)}/mesh").json()
        return np.asarray(data["edges"], float).reshape(-1, 2, 3)

    # --- WebSocket --------------------------------------------------------------------------------
    def track(self, frames: Iterable[Any], camera: Any, object: str | None = None,
              ros_mesh_unit: str | None = None) -> Iterator[TrackMessage]:
        """Track ``frames`` lock-step: one :class:`TrackMessage` per frame, in order. A frame is
        an image (numpy array, encoded bytes or a path), timed by the server's clock, or a pair
        ``(time_s, image)`` (seconds, increasing). ``ros_mesh_unit`` (mm, cm, m: the mesh's unit) asks for
        ``format=ros``: each message's ``ros`` is then a ``geometry_msgs/PoseWithCovarianceStamped``
        (metres). A frame the server cannot track (not decodable, another size than the camera's,
        not an image) is answered by a :class:`FrameError` (status ``lost``, with the server's
        ``code``) in its place, and the stream goes on; an error about the session (refused
        token, unknown object, the connection lost) raises :class:`QuatrackError`."""
        from websockets.sync.client import connect

        url = self._track_url(object, ros_mesh_unit)
        hello = self._hello(camera)  # (a camera file that cannot be read: refused before connecting)
        try:
            ws = connect(url, additional_headers=self._headers or None, max_size=None, open_timeout=self.timeout)
        except Exception as exc:  # refused handshake or no server: typed, with the server's code
            raise _ws_error(exc) from None
        with ws, _typed_stream_errors(self.ws_url, self.timeout):  # (the server gone, or silent)
            ws.send(hello)
            self._expect(_message(ws.recv(self.timeout)), "ready")
            for index, item in enumerate(frames):
                header, data = self._frame_parts(item)
                if header is not None:
                    ws.send(header)
                ws.send(data)
                yield self._answer_of(_message(ws.recv(self.timeout)), self._sent_time(item), index)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class AsyncClient(_Endpoint):
    """:class:`Client` for asyncio: ``await client.pose(...)``, ``async for msg in
    client.track(frames, camera)`` (``frames`` an iterable or an async iterable of images or
    ``(time_s, image)`` pairs). Same arguments, results and errors as :class:`Client`."""

    def __init__(self, url: str = "http://127.0.0.1:8000", object: str | None = None, token: str | None = None,
                 timeout: float = 60.0) -> None:
        import httpx

        super().__init__(url, object, token, timeout)
        self._http = httpx.AsyncClient(base_url=self.http_url, headers=self._headers, timeout=timeout)

    async def _request(self, method: str, path: str, **kw):
        import httpx

        try:
            return self._answer(await self._http.request(method, path, **kw))
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None

    async def objects(self) -> ObjectList:
        return ObjectList.model_validate((await self._request("GET", "/v1/objects")).json())

    async def pose(self, image: Any, camera: Any, object: str | None = None) -> LocateOut:
        r = await self._request("POST", f"/v1/objects/{self._name(object)}/pose", files=self._pose_files(image, camera))
        return LocateOut.model_validate(r.json())

    async def pose_all(self, image: Any, camera: Any, ros_mesh_unit: str | dict[str, str] | None = None) -> LocateAllOut:
        r = await self._request("POST", "/v1/pose", files=self._pose_files(image, camera),
                                params=self._pose_all_query(ros_mesh_unit))
        return LocateAllOut.model_validate(r.json())

    async def track(self, frames, camera: Any, object: str | None = None, ros_mesh_unit: str | None = None):
        import websockets

        url = self._track_url(object, ros_mesh_unit)
        hello = self._hello(camera)  # (a camera file that cannot be read: refused before connecting)
        try:
            ws = await websockets.connect(url, additional_headers=self._headers or None, max_size=None,
                                          open_timeout=self.timeout)
        except Exception as exc:
            raise _ws_error(exc) from None

        async def items():
            if hasattr(frames, "__aiter__"):
                async for item in frames:
                    yield item
            else:
                for item in frames:
                    yield item

        async with ws:
            with _typed_stream_errors(self.ws_url, self.timeout):  # (the server gone, or silent)
                await ws.send(hello)
                self._expect(_message(await asyncio.wait_for(ws.recv(), self.timeout)), "ready")
                index = 0
                async for item in items():
                    header, data = self._frame_parts(item)
                    if header is not None:
                        await ws.send(header)
                    await ws.send(data)
                    msg = _message(await asyncio.wait_for(ws.recv(), self.timeout))
                    yield self._answer_of(msg, self._sent_time(item), index)
                    index += 1

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc) -> None:
        await self.aclose()


# --- the streaming protocol (asyncio): lock-step or real time --------------------------------------

@dataclass
class StreamResult:
    """Answers by the index of the frame they are for (the caller's numbering), matched by the
    frame id the server echoes."""

    poses: dict[int, dict] = field(default_factory=dict)
    errors: list[dict] = field(default_factory=list)
    error_index: list = field(default_factory=list)  # the caller's index of each error's frame (None: of no frame)
    sent: int = 0
    skipped: int = 0
    rtt_ms: list[float] = field(default_factory=list)  # send → answer, per processed frame
    wall_s: float = 0.0
    local_port: int | None = None  # the socket's own port (which server process holds it: bench serve)


class _Session:
    """One open socket's bookkeeping. The k-th frame sent gets ``"id": k`` in its header, and the
    server echoes that id in every answer about the frame (pose, ``dropped``, refusal, error), so
    each answer is filed under its own caller's index whatever the server refused or replaced
    meanwhile. Counting alone slipped in real time: a refusal coming back after newer frames
    were sent dropped the newest index instead of the refused one, and every later answer went
    under the index before its own. A server that echoes no id (one older than the id) is still
    matched by counting, as before: ``numbers`` holds the ids of the frames it numbered."""

    def __init__(self, ws, res: StreamResult, on_answer=None) -> None:
        self.ws, self.res, self.on_answer = ws, res, on_answer
        self.indices: list = []  # the caller's index of each id (ids count the frames sent, from 0)
        self.sent_at: list[float] = []  # each id's send time
        self.numbers: list[int] = []  # the id of each server frame number (the frames it did not refuse)
        self.closed: set[int] = set()  # ids answered for good

    async def send(self, idx, t: float, data: bytes) -> int:
        """Send one frame (its header, with the time and the id, then the image); returns its id."""
        k = len(self.indices)
        await self.ws.send(json.dumps({"type": "frame", "time_s": float(t), "id": k}))
        self.indices.append(idx)
        self.numbers.append(k)
        self.sent_at.append(time.perf_counter())
        await self.ws.send(data)
        self.res.sent += 1
        return k

    def _id_of(self, msg: dict, refused: bool) -> int | None:
        """The id of the frame ``msg`` is about: the one it echoes, else (a server without ids)
        the one its frame number counts to — a refused frame's is the newest sent (lock-step:
        the only one in flight)."""
        k = msg.get("id")
        if isinstance(k, int) and not isinstance(k, bool) and 0 <= k < len(self.indices):
            if refused and k in self.numbers:  # (not numbered by the server: the later frames' numbers move up)
                self.numbers.remove(k)
            return k
        if "id" in msg:  # (not one of ours: filed under no frame)
            return None
        if refused:
            return self.numbers.pop() if self.numbers else None
        n = msg.get("frame")
        return self.numbers[n] if isinstance(n, int) and 0 <= n < len(self.numbers) else None

    def take(self, msg: dict) -> int | None:
        """Record one answer; returns the id of the frame it answers for good, if any: its pose
        (tracked, or ``dropped``: not tracked, newer frames came), an error naming its server
        frame number, or its refusal on arrival (an error without ``frame`` whose code is one of
        ``codes.REFUSED_FRAME``: such a frame gets no number). An error about a frame's header
        alone (``out_of_order``, ``bad_message``) is recorded and the frame's answer still
        awaited; other errors are recorded."""
        kind = msg.get("type")
        error = msg.get("error") if isinstance(msg.get("error"), dict) else {}
        refused = kind == "error" and "frame" not in msg and error.get("code") in REFUSED_FRAME
        k = self._id_of(msg, refused) if kind in ("pose", "error") else None
        if kind == "error":
            self.res.errors.append(msg)
            self.res.error_index.append(None if k is None else self.indices[k])
            if not (refused or "frame" in msg):
                return None
        elif kind == "pose" and k is not None and not msg.get("dropped"):
            self.res.poses[self.indices[k]] = msg
            self.res.skipped += msg.get("skipped", 0)
            self.res.rtt_ms.append((time.perf_counter() - self.sent_at[k]) * 1e3)
            if self.on_answer is not None:
                self.on_answer(msg)
        if k is not None:
            self.closed.add(k)
        return k

    def last_answered(self) -> bool:
        return len(self.indices) - 1 in self.closed


async def _lockstep(s: _Session, frames, timeout: float) -> None:
    for idx, t, data in frames:
        k = await s.send(idx, t, data)
        while True:
            msg = _message(await asyncio.wait_for(s.ws.recv(), timeout))
            if s.take(msg) == k:
                break
            if msg.get("type") == "error" and "frame" not in msg and "id" not in msg:
                break  # (an error about no frame, e.g. the session's idle timeout: not waited past)


async def _realtime(s: _Session, frames, fps: float, timeout: float) -> None:
    async def receive():
        while True:
            s.take(_message(await s.ws.recv()))

    receiver = asyncio.create_task(receive())
    try:
        t0 = time.perf_counter()
        for k, (idx, t, data) in enumerate(frames):
            delay = t0 + k / fps - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            await s.send(idx, t, data)
        deadline = time.perf_counter() + timeout  # the newest frame is always answered: wait for it
        while s.indices and not s.last_answered() and time.perf_counter() < deadline and not receiver.done():
            await asyncio.sleep(0.01)
        if receiver.done():  # the connection lost before the last answer: raised (as lock-step raises),
            receiver.result()  # not returned as if complete, with "Task exception was never retrieved" on stderr
    finally:
        receiver.cancel()
        await asyncio.gather(receiver, return_exceptions=True)


async def stream(url: str, camera: Any, frames: Iterable[tuple[int, float, bytes]], fps: float | None = None,
                 token: str | None = None, timeout: float = 60.0, on_answer=None,
                 result: StreamResult | None = None) -> StreamResult:
    """Stream ``(index, time_s, JPEG bytes)`` through one tracking session at ``url`` (the full
    ``ws://.../v1/objects/NAME/track``) and collect the answers: lock-step when ``fps`` is None,
    else real time at ``fps`` frames/s (> 0); ``token`` as :class:`Client` takes it (default
    ``$QUATRACK_API_TOKEN``); ``on_answer(msg)`` is called on each pose message as
    it arrives. Each frame goes with an id (its place in the stream), so every answer is filed
    under its own index whatever the server refused or skipped meanwhile. ``camera``: as :class:`Client` takes it (a dict, a PinholeCamera or a camera
    file's path). Raises :class:`QuatrackError` when the server refuses. ``result``: the
    :class:`StreamResult` to file the answers in (returned), so that a caller whose stream is
    interrupted (Ctrl-C: ``asyncio.run`` raises ``KeyboardInterrupt``) keeps what was answered."""
    import websockets

    if fps is not None and not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise InputError("invalid_input", f"fps: frames per second above 0, or None for lock-step; got {fps!r}")
    hello = json.loads(Client._hello(camera))

    headers = auth_headers(api_token(token)) or None
    res = StreamResult() if result is None else result
    t_start = time.perf_counter()
    try:
        ws = await websockets.connect(url, additional_headers=headers, max_size=None, open_timeout=timeout)
    except Exception as exc:
        raise _ws_error(exc) from None
    try:
        await _stream_on(ws, url, hello, frames, fps, timeout, res, on_answer)
    finally:  # (an interrupted stream's too)
        res.wall_s = time.perf_counter() - t_start
    return res


async def _stream_on(ws, url: str, hello: dict, frames, fps: float | None, timeout: float, res: StreamResult,
                     on_answer) -> None:
    """:func:`stream`'s session on the open socket ``ws``."""
    async with ws:
        try:
            res.local_port = int(ws.local_address[1])
        except (AttributeError, IndexError, TypeError, ValueError):
            pass
        with _typed_stream_errors(url, timeout):  # (the server gone, or silent)
            await ws.send(json.dumps(hello))  # (with "ack": the "ready" handshake)
            Client._expect(_message(await asyncio.wait_for(ws.recv(), timeout)), "ready")
            s = _Session(ws, res, on_answer)
            if fps is None:
                await _lockstep(s, frames, timeout)
            else:
                await _realtime(s, frames, fps, timeout)


def video_frames(path: str, max_frames: int | None = None, quality: int = 90) -> Iterator[tuple[int, float, bytes]]:
    """``(index, time_s, JPEG bytes)`` of a video, timed by :mod:`recognition.trackio`'s rule."""
    from quatrack.recognition.trackio import jpeg_frames, open_frames

    return jpeg_frames(open_frames(video=str(path), max_frames=max_frames), quality)

"""HTTP and WebSocket endpoints. Thin: parse at the edge, then call recognition in the pool.

Dependencies are injected the FastAPI way (``Depends``): the shared :class:`ServiceState` and
the bearer-token check. CPU-bound work (decoding, recognition, tracking) never runs on the
event loop, so health checks and other sessions stay responsive under load.
"""

from __future__ import annotations

import asyncio
import functools
import hmac
import inspect
import logging
import time
import json
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Annotated, Callable
from urllib.parse import urlsplit

from fastapi import APIRouter, Depends, Query, Request, WebSocket
from fastapi.responses import JSONResponse, PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from quatrack.recognition.images import MIN_SIDE, ImageError
from quatrack.recognition.locate import LocateParams, locate
from quatrack.viewsets.store import learned_points

from . import ros
from .errors import ApiError, error_body
from .imagein import decode_upload, size_mismatch
from .logs import mark_refused
from .metrics import CONTENT_TYPE, Metrics
from .registry import ModelRegistry
from .schemas import CameraIn, ErrorResponse, Health, LocateOut, ObjectDetail, ObjectList, ObjectSummary, Ready, ReloadOut
from .sessions import SessionLimiter, TrackSession
from .settings import Settings
from .tracker_factory import TRACKER_KIND

log = logging.getLogger("quatrack.service")


@dataclass
class ServiceState:
    """What every request shares: read-only models, the worker pool, limits and metrics."""

    settings: Settings
    registry: ModelRegistry
    executor: Executor
    metrics: Metrics
    sessions: SessionLimiter
    pending: int = 0  # REST pose requests in flight
    warm_error: str | None = None  # why start-up loading (app._warm) failed; /readyz says it
    # the sessions' clock (rate limit, arrival times of frames without a time_s): tests inject
    # a controlled one, so that what they check does not depend on the machine's speed
    clock: Callable[[], float] = time.monotonic


def get_state(request: Request) -> ServiceState:
    return request.app.state.quatrack


def get_ws_state(websocket: WebSocket) -> ServiceState:
    return websocket.app.state.quatrack


_bearer = HTTPBearer(auto_error=False, description="`Authorization: Bearer $QUATRACK_API_TOKEN` when the server sets one")


def _token_ok(expected: str | None, given: str | None) -> bool:
    return expected is None or (given is not None and hmac.compare_digest(given.encode(), expected.encode()))


def bearer_token(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header (the scheme in any case, blanks
    around the token ignored), else None. The one rule of the REST endpoints and the WebSocket:
    REST took HTTPBearer's reading, which keeps the blanks (``Bearer  tok``, two spaces, or a
    trailing blank was 401), while the WebSocket stripped them and accepted the same header."""
    scheme, _, token = (authorization or "").strip().partition(" ")
    return (token.strip() or None) if scheme.lower() == "bearer" else None


def require_token(
    state: Annotated[ServiceState, Depends(get_state)],
    request: Request,
    _scheme: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """``_scheme`` only declares the bearer scheme in the OpenAPI description (the docs' Authorize
    button); the header is read by :func:`bearer_token`, as the WebSocket reads it."""
    if not _token_ok(state.settings.api_token, bearer_token(request.headers.get("authorization"))):
        raise ApiError(401, "unauthorized", "a valid bearer token is required", {"WWW-Authenticate": "Bearer"})


State = Annotated[ServiceState, Depends(get_state)]
MAX_CAMERA_BYTES = 65_536  # a camera JSON is ~200 bytes
MAX_FILES = 4  # multipart files parsed: 'image' and 'camera', and room to name one given twice
ERRORS = {code: {"model": ErrorResponse} for code in (400, 401, 404, 408, 413, 415, 422, 503)}

health = APIRouter(tags=["health"])
api = APIRouter(prefix="/v1", tags=["objects"], dependencies=[Depends(require_token)], responses=ERRORS)
ops = APIRouter(tags=["operations"], dependencies=[Depends(require_token)])
sockets = APIRouter(prefix="/v1")  # authenticated inside: HTTPBearer needs an HTTP request


@health.get("/healthz", response_model=Health, summary="the process is alive")
async def healthz() -> Health:
    return Health()


def serves_an_object(state: ServiceState, loaded: list[str]) -> bool:
    """Whether the server has an object to serve: one loaded. An empty store, or one whose every
    model is broken, is not ready: ``/readyz`` said 200 ``"models": []`` and a balancer or
    Kubernetes sent requests that could only be 404 or 503 (the deployment did not wait for the
    training Job); the store is polled, so the server becomes ready when a model is trained into
    it. With ``QUATRACK_PRELOAD=0`` models load at their first request, so none need be loaded:
    the store must hold an object whose model is not known to be broken (it had answered 200
    whatever the store held, an empty one included)."""
    if loaded:
        return True
    if state.settings.preload:
        return False
    failed = state.registry.failed()
    return any(name not in failed for name in state.registry.names())


@health.get("/readyz", response_model=Ready, summary="models are loaded (at least one)", responses={503: {"model": Ready}})
async def readyz(state: State):
    loaded = state.registry.loaded()
    body = Ready(ready=state.warm_error is None and state.registry.ready and serves_an_object(state, loaded),
                 models=loaded, tracker=TRACKER_KIND, failed=state.registry.failed(), error=state.warm_error)
    return JSONResponse(body.model_dump(), status_code=200 if body.ready else 503)


@ops.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics (text format 0.0.4)")
def metrics(state: State) -> PlainTextResponse:
    """A plain ``def``: FastAPI runs it in a thread. Rendering merges every worker's sample files
    (multiprocess mode) — ≈ 15 ms of Python per scrape measured with one worker's files, more
    with more workers — and on the event loop that stalled the worker's probes and sessions
    for as long at every scrape."""
    state.metrics.models.set(len(state.registry.loaded()))
    return PlainTextResponse(state.metrics.render(), media_type=CONTENT_TYPE)


@api.get("/objects", response_model=ObjectList, summary="the trained objects (broken ones with their `error`)")
async def list_objects(state: State) -> ObjectList:
    loaded = set(state.registry.loaded())
    failed = state.registry.failed()
    out = []
    for name in state.registry.names():
        try:
            m = state.registry.manifest(name)
            s = m.get("training_summary")
            s = s if isinstance(s, dict) else {}
            item = ObjectSummary(name=name, created=m.get("created"), viewsets=s.get("viewsets"),
                                 points3d=s.get("points3d_total"), learned_viewsets=int(m.get("learned_viewsets") or 0),
                                 learned_points3d=learned_points(m),
                                 loaded=name in loaded, error=failed.get(name))
        except (ApiError, ValidationError) as exc:  # a manifest nobody can read: listed as broken
            item = ObjectSummary(name=name, loaded=name in loaded,
                                 error=failed.get(name) or getattr(exc, "message", f"object {name!r}: unreadable manifest"))
        out.append(item)
    return ObjectList(objects=out)


@api.get("/objects/{name}", response_model=ObjectDetail, summary="one object's training summary")
async def get_object(name: str, state: State) -> ObjectDetail:
    m = state.registry.manifest(name)
    summary, params = m.get("training_summary"), m.get("parameters")
    return ObjectDetail(name=name, created=m.get("created") if isinstance(m.get("created"), str) else None,
                        training_summary=summary if isinstance(summary, dict) else {},
                        parameters=params if isinstance(params, dict) else None,
                        error=state.registry.failed().get(name))


@api.post("/objects/{name}/reload", response_model=ReloadOut,
          summary="load the object's model from the store now (after `quatrack train` or `models delete`)")
async def reload_object(name: str, state: State) -> ReloadOut:
    """The store is also watched (every `QUATRACK_MODEL_POLL_S` seconds); this call does it at once.
    Sessions already running keep the model they started with."""
    out = await asyncio.get_running_loop().run_in_executor(state.executor, state.registry.reload, name)
    return ReloadOut(**out)


_POSE_BODY = {
    "requestBody": {
        "required": True,
        "description": "The image: a multipart form (`image` file + optional `camera` JSON), or the raw image bytes.",
        "content": {
            "multipart/form-data": {"schema": {
                "type": "object", "required": ["image"],
                "properties": {"image": {"type": "string", "format": "binary", "description": "JPEG, PNG or WebP"},
                               "camera": {"type": "string", "description": "camera JSON (contract format)",
                                          "example": json.dumps({"width": 640, "height": 480, "fx": 669.7, "fy": 667.8,
                                                                 "cx": 320.0, "cy": 240.0})}}}},
            "image/jpeg": {"schema": {"type": "string", "format": "binary"}},
            "image/png": {"schema": {"type": "string", "format": "binary"}},
            "image/webp": {"schema": {"type": "string", "format": "binary"}},
        },
    }
}


POSE_OPTIONS = ("format", "mesh_unit")  # the pose endpoints' query parameters besides the camera's
ROUTE_OPTIONS = {"pose_all": ("objects",)}  # ... and those of one endpoint (by its function's name)


def given_twice(params) -> ApiError | None:
    """The 422 for a query parameter given more than once (``?fx=669.7&…&fx=100``), else None:
    the last one was used in silence (a different pose, or none); REST and WebSocket alike."""
    counts: dict[str, int] = {}
    for key, _ in params.multi_items():
        counts[key] = counts.get(key, 0) + 1
    for key, n in counts.items():
        if n > 1:
            shown = repr(key if len(key) <= 40 else key[:37] + "...")
            return ApiError(422, "invalid_input", f"query parameter {shown} is given {n} times: give it once")
    return None


def unknown_query(request: Request) -> ApiError | None:
    """The 422 for a query parameter the pose endpoints do not read, else None. Why: they were
    ignored, so ``?dist_coeffs=…`` (the camera JSON's name; the query's is ``dist``) gave a pose
    without the lens's distortion and no word of it. Another program's name for a camera field
    is pointed to the query's (:data:`~quatrack.viewsets.camera.FIELD_ALIASES`, as camera JSON
    refuses it), a misspelling to the nearest name."""
    import difflib

    from quatrack.viewsets.camera import FIELD_ALIASES

    camera = [p for p in inspect.signature(camera_query).parameters if p != "request"]
    route = request.scope.get("route")
    known = camera + list(POSE_OPTIONS) + list(ROUTE_OPTIONS.get(getattr(route, "name", ""), ()))
    to_query = {"dist_coeffs": "dist"}  # the camera JSON's field names that the query spells otherwise
    if (twice := given_twice(request.query_params)) is not None:
        return twice
    for key in request.query_params.keys():
        if key in known:
            continue
        shown = repr(key if len(key) <= 40 else key[:37] + "...")
        if key.strip().lower() in ("token", "access_token"):
            return ApiError(422, "invalid_input", f"query parameter {shown}: the REST endpoints read the token from "
                                                  f"the header Authorization: Bearer … only")
        low = key.lower()
        meant = ([to_query[low]] if low in to_query else [to_query.get(f, f) for f in FIELD_ALIASES.get(low, ())]) \
            or difflib.get_close_matches(low, known, n=1, cutoff=0.75)
        hint = f" (did you mean {', '.join(map(repr, meant))}?)" if meant else ""
        code = "bad_camera" if not meant or meant[0] in camera else "invalid_input"
        return ApiError(422, code, f"unknown query parameter {shown}{hint}: the pose endpoints take "
                                   f"{', '.join(known)}")
    return None


TRACK_QUERY = ("token", "format", "mesh_unit")  # the track WebSocket's query parameters


def unknown_track_query(params) -> ApiError | None:
    """The 422 for a query parameter the track WebSocket does not read, else None: as the pose
    endpoints refuse theirs (:func:`unknown_query`). Why: the handshake ignored them, so a client
    giving the camera in the URL, as the pose endpoints take it (``?fx=…``, ``?dist_coeffs=…``),
    opened a session and heard nothing of it. A camera field is pointed to the first message,
    where a session's camera goes; another name to the nearest one the endpoint reads."""
    import difflib

    from quatrack.viewsets.camera import CAMERA_FIELDS, FIELD_ALIASES

    takes = f"the track endpoint takes {', '.join(TRACK_QUERY)}"
    if (twice := given_twice(params)) is not None:
        return twice
    for key in params.keys():
        if key in TRACK_QUERY:
            continue
        shown = repr(key if len(key) <= 40 else key[:37] + "...")
        low = key.strip().lower()
        if low in CAMERA_FIELDS or low in FIELD_ALIASES:
            return ApiError(422, "bad_camera", f"unknown query parameter {shown}: a session's camera is its first "
                                               f"message (the camera JSON), not the URL's query; {takes}")
        meant = ["token"] if low in ("token", "access_token") else difflib.get_close_matches(low, TRACK_QUERY, n=1,
                                                                                           cutoff=0.75)
        hint = f" (did you mean {meant[0]!r}?)" if meant else ""
        return ApiError(422, "invalid_input", f"unknown query parameter {shown}{hint}: {takes}")
    return None


def camera_query(
    request: Request,
    fx: Annotated[float | None, Query(description="focal length x, px (when no `camera` form field)")] = None,
    fy: Annotated[float | None, Query(description="focal length y, px")] = None,
    cx: Annotated[float | None, Query(description="principal point x, px")] = None,
    cy: Annotated[float | None, Query(description="principal point y, px")] = None,
    width: Annotated[int | None, Query(gt=0, description="image width the camera is for (default: the image's)")] = None,
    height: Annotated[int | None, Query(gt=0, description="image height the camera is for")] = None,
    dist: Annotated[str | None, Query(description="distortion: 4, 5 or 8 comma-separated numbers, OpenCV order "
                                                  "k1,k2,p1,p2[,k3[,k4,k5,k6]]")] = None,
) -> CameraIn | None:
    """The camera given in the query (a dependency of both pose endpoints), or None when the
    request gives none there (it may come as the multipart field ``camera``). A query parameter
    they do not read is refused first (:func:`unknown_query`)."""
    if (refused := unknown_query(request)) is not None:
        raise refused
    given = [v is not None for v in (fx, fy, cx, cy)]
    if not any(given):
        if width is not None or height is not None or dist is not None:  # (they were ignored)
            raise ApiError(422, "bad_camera", "query parameters width, height and dist go with fx, fy, cx and cy "
                                              "(a camera in the multipart field 'camera' holds its own)")
        return None
    if not all(given):
        raise ApiError(422, "bad_camera", "query parameters fx, fy, cx and cy go together")
    if (width is None) != (height is None):  # (as a camera file with one of them is refused)
        raise ApiError(422, "bad_camera", "query parameters width and height go together "
                                          "(both, or neither for the image's size)")
    coeffs = None
    if dist:
        # (named as the query names it: the camera's own check said "field 'dist_coeffs'", the
        # very name this endpoint refuses, and the order k1,k2,p1,p2[,k3] left out the 8)
        form = f"4, 5 or 8 comma-separated numbers (OpenCV order {DIST_ORDER})"
        try:
            coeffs = [float(x) for x in dist.split(",")]
        except ValueError:
            raise ApiError(422, "bad_camera", f"dist: {form}") from None
        if len(coeffs) not in (4, 5, 8):
            raise ApiError(422, "bad_camera", f"dist: {form}, got {len(coeffs)}") from None
    try:
        return CameraIn(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height, dist_coeffs=coeffs)
    except ValidationError as exc:
        e = exc.errors()[0]
        raise ApiError(422, "bad_camera", f"{'.'.join(map(str, e['loc']))}: {e['msg']}") from None


DIST_ORDER = "k1,k2,p1,p2[,k3[,k4,k5,k6]]"


CameraQuery = Annotated[CameraIn | None, Depends(camera_query)]


def _camera_from_json(text: str) -> CameraIn:
    """The multipart field ``camera``; a camera file saved with a UTF-8 byte order mark (Windows
    editors) is read, as ``quatrack`` reads camera files (it was 422 "Invalid JSON")."""
    text = text.removeprefix("\ufeff")
    try:
        return CameraIn.model_validate_json(text)
    except ValidationError as exc:
        if exc.errors()[0]["type"] == "json_invalid" and _opencv_yaml(text):  # (was "camera: Invalid JSON: expected value ...")
            raise ApiError(422, "bad_camera", "camera: the multipart field 'camera' is the contract's camera JSON "
                                              "(width, height, fx, fy, cx, cy, dist_coeffs), not OpenCV YAML: convert "
                                              "it (quatrack.client.camera_json('cam.yaml') gives the JSON), or send it "
                                              "with the Python client, which converts camera files") from None
        raise ApiError(422, "bad_camera", CameraIn.error_message(exc)) from None


def _opencv_yaml(text: str) -> bool:
    """Whether a camera field that is not JSON reads as an OpenCV YAML/XML calibration file
    (what ``quatrack locate --camera`` and the Python client accept as a file)."""
    head = text.lstrip()
    return head.startswith(("%YAML", "<?xml", "<opencv_storage")) or "camera_matrix" in text


def _client_left() -> ApiError:
    """The client closed the connection before its body ended (a timeout, a dropped link): nobody
    hears the answer; 499 (nginx's "client closed request") keeps it out of the 5xx counts and the
    error log, where an unhandled ClientDisconnect put it (a 500 with a traceback)."""
    return ApiError(499, "client_closed", "the client closed the connection before the body ended")


async def read_pose_request(request: Request, camera: CameraIn | None) -> tuple[bytes, CameraIn, str | None]:
    """The image bytes, the camera and the image's file name of a pose request (multipart fields
    ``image`` and ``camera``, or a raw image body — no name — with the camera from the query,
    given as ``camera``); both pose endpoints."""
    name = None
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype == "multipart/form-data":
        try:
            form = await request.form(max_files=MAX_FILES, max_fields=8, max_part_size=MAX_CAMERA_BYTES)
        except ApiError:
            raise
        except ClientDisconnect:
            raise _client_left() from None
        except StarletteHTTPException as exc:
            if "maximum size" in str(exc.detail):
                raise ApiError(413, "too_large", f"a multipart text field (the camera) may have at most "
                                                 f"{MAX_CAMERA_BYTES} bytes") from None
            if "too many files" in str(exc.detail).lower():
                raise ApiError(400, "bad_request", f"more than {MAX_FILES} files in the multipart body: a pose request "
                                                   f"has one field 'image' and at most one 'camera'") from None
            raise ApiError(400, "bad_request", f"malformed multipart body: {exc.detail}") from None
        except Exception as exc:
            raise ApiError(400, "bad_request", f"malformed multipart body ({exc.__class__.__name__})") from None
        for field in ("image", "camera"):  # (the first was used, the others dropped in silence)
            if (n := len(form.getlist(field))) > 1:
                raise ApiError(400, "bad_request", f"multipart field {field!r} is given {n} times: "
                                                   f"a pose request has one (one image per request)")
        upload = form.get("image")
        if upload is None or isinstance(upload, str):
            raise ApiError(422, "missing_image", "multipart field 'image' (a file) is required")
        data = await upload.read()
        name = upload.filename or None
        cam_field = form.get("camera")
        if cam_field is not None and camera is not None:  # (the multipart one won in silence)
            raise ApiError(422, "bad_camera", "the camera is given twice, in the query (fx, fy, cx, cy) and as the "
                                              "multipart field 'camera': give one")
        if cam_field is not None:
            if not isinstance(cam_field, str):
                raw = await cam_field.read(MAX_CAMERA_BYTES + 1)
                if len(raw) > MAX_CAMERA_BYTES:
                    raise ApiError(413, "too_large", f"the camera may have at most {MAX_CAMERA_BYTES} bytes")
                cam_field = raw.decode("utf-8", "replace")
            camera = _camera_from_json(cam_field)
    elif ctype.startswith("image/") or ctype == "application/octet-stream":
        try:
            data = await request.body()
        except ClientDisconnect:
            raise _client_left() from None
    else:
        # (it said "with an image/* content type", while application/octet-stream is taken too: the
        # image's format is read from its bytes, whatever type the header names)
        shown = repr(ctype[:60]) if ctype else "none"
        raise ApiError(415, "unsupported_media_type",
                       f"content type {shown}: send multipart/form-data (fields image, camera), or the raw image "
                       f"bytes as image/* (e.g. image/jpeg) or application/octet-stream")
    if camera is None:
        raise ApiError(422, "bad_camera", "a camera is required: multipart field 'camera' or query parameters fx, fy, cx, cy")
    if (camera.width is None) != (camera.height is None):  # (the image's size filled the other one in silence)
        raise ApiError(422, "bad_camera", "camera: width and height go together (both, or neither for the image's size)")
    if camera.width is not None and camera.height is not None:
        camera.to_camera()  # implausible intrinsics: 422 before any decoding
    return data, camera, name


def decode_with_camera(state: ServiceState, data: bytes, camera: CameraIn):
    """The decoded image and the camera checked against its size (worker thread; both pose
    endpoints). A too-small image is said before the camera is checked against its size."""
    image = decode_upload(data, state.settings.max_image_pixels)
    h, w = image.shape[:2]
    if min(h, w) < MIN_SIDE:
        raise ApiError(422, "bad_image", f"the image is too small ({w}×{h} px; at least {MIN_SIDE} px a side)")
    cam = camera.to_camera((w, h))
    if (msg := size_mismatch(cam, w, h)) is not None:
        raise ApiError(422, "bad_image", msg)
    return image, cam


async def serve_pose(state: ServiceState, request: Request, camera: CameraIn | None, work) -> tuple[str | None, dict]:
    """A pose request from its body to its answer (both pose endpoints): the image's file name
    and ``work(data, camera)``'s result, run in the CPU pool.

    The request's slot (one of ``max_pending_requests``) is taken *before* its body is read and
    held until its work is done: the bodies were read whole first and the limit checked after,
    so 60 clients holding 10 MB uploads open grew a worker's memory by 600 MB, the "8, then
    503" applying only to bodies already in memory. Now a request beyond the limit is 503
    ``busy`` (Retry-After) before any byte of its body is read (uvicorn drops the rest of it),
    and a body must arrive within ``body_timeout_s`` (else 408 ``body_timeout``, the connection
    closed): a client trickling its upload holds a slot for that long at most."""
    if state.pending >= state.settings.max_pending_requests:
        raise ApiError(503, "busy", "too many pose requests in progress; retry later",
                       {"Retry-After": str(state.settings.retry_after_s)})
    state.pending += 1
    try:
        try:
            data, camera, name = await asyncio.wait_for(read_pose_request(request, camera),
                                                        state.settings.body_timeout_s)
        except asyncio.TimeoutError:
            raise ApiError(408, "body_timeout", f"the request body did not arrive within "
                                                f"{state.settings.body_timeout_s:g} s", {"Connection": "close"}) from None
        return name, await asyncio.get_running_loop().run_in_executor(state.executor, work, data, camera)
    finally:
        state.pending -= 1


# the pose endpoints' output format (one definition for both: ``/v1/objects/{name}/pose``, ``/v1/pose``)
FormatQuery = Annotated[str, Query(description="json, or ros: also a geometry_msgs/PoseWithCovarianceStamped under \"ros\"")]
MeshUnitQuery = Annotated[str | None, Query(description="with format=ros: the mesh's unit, mm, cm or m")]


@api.post("/objects/{name}/pose", response_model=LocateOut, openapi_extra=_POSE_BODY,
          summary="recognise the object in one image and estimate its pose (as `quatrack locate --json`)")
async def pose(
    name: str, request: Request, state: State, query_camera: CameraQuery,
    format: FormatQuery = "json", mesh_unit: MeshUnitQuery = None,
) -> dict:
    unit = ros.ros_unit({"format": format, "mesh_unit": mesh_unit})
    registry = state.registry
    registry.check_name(name)
    if not registry.is_known(name):
        raise ApiError(404, "unknown_object", f"no object named {name!r} in the store")
    image_name, out = await serve_pose(state, request, query_camera, functools.partial(_locate, state, name))
    result = {"image": image_name, **out}
    return JSONResponse(ros.add_to_locate(result, unit)) if unit else result  # "ros" added: LocateOut + ros


def _locate(state: ServiceState, name: str, data: bytes, camera: CameraIn) -> dict:
    """Worker thread: decode, check the camera against the image, recognise."""
    image, cam = decode_with_camera(state, data, camera)
    model, index = state.registry.get(name)
    try:
        result = locate(image, cam, model, LocateParams(max_pixels=state.settings.locate_max_pixels), index=index)
    except ImageError as exc:
        raise ApiError(422, "bad_image", str(exc)) from None
    state.metrics.observe_stages(state.metrics.locate_stages, result.time_ms)
    return result.to_json()


def _same_origin(origin: str, host: str) -> bool:
    """Whether a browser page of ``origin`` (``scheme://host[:port]``) is this server's own, as
    reached through ``host`` (the ``Host`` or ``X-Forwarded-Host`` header). A ``host`` without a
    port (a proxy's ``Host $host``, which drops it) compares host names only."""
    try:
        o = urlsplit(origin)
        h = urlsplit("//" + host.split(",")[0].strip())
        o_port = o.port or {"http": 80, "https": 443}.get(o.scheme)
        h_port = h.port
    except ValueError:
        return False
    if o.scheme not in ("http", "https") or not o.hostname or not h.hostname:
        return False
    return o.hostname == h.hostname and (h_port is None or h_port == o_port)


def origin_allowed(settings: Settings, headers) -> bool:
    """Cross-site WebSocket hijacking: a WebSocket is not bound by the same-origin policy, so any
    page the user visits could open one to a server without a token (one on 127.0.0.1 included),
    occupy its sessions and, with ``QUATRACK_LEARN_VIEWS``, make it learn views. Without a token
    a browser's handshake (it always sends ``Origin``) must come from this server's own pages or
    an origin of ``QUATRACK_CORS_ORIGINS``; clients that are no browser send no ``Origin``. With a
    token there is nothing for another site to borrow: browsers never send the token by
    themselves (no cookie; the viewer keeps it in its field only), so the token alone decides."""
    origin = headers.get("origin")
    if origin is None or settings.api_token is not None:
        return True
    if "*" in settings.cors_origins or origin in settings.cors_origins:
        return True
    return any(_same_origin(origin, headers.get(h, "")) for h in ("host", "x-forwarded-host") if headers.get(h))


@sockets.websocket("/objects/{name}/track")
async def track(websocket: WebSocket, name: str) -> None:
    """Camera JSON first, then binary frames; one JSON message per frame (see the README)."""
    state = get_ws_state(websocket)
    token = bearer_token(websocket.headers.get("authorization")) or websocket.query_params.get("token")
    if not _token_ok(state.settings.api_token, token):
        return await deny_websocket(websocket, 401, "unauthorized", "a valid bearer token is required (the Authorization header, or the query parameter token)", 1008)
    if not origin_allowed(state.settings, websocket.headers):
        return await deny_websocket(websocket, 403, "forbidden_origin",
                           "a page of another site may not open this server's WebSocket (its origin is not "
                           "this server's; allow it with QUATRACK_CORS_ORIGINS, or set QUATRACK_API_TOKEN)", 1008)
    if (refused := unknown_track_query(websocket.query_params)) is not None:
        return await deny_websocket(websocket, refused.status_code, refused.code, refused.message, 1008)
    try:
        state.registry.check_name(name)
    except ApiError as exc:
        return await deny_websocket(websocket, exc.status_code, exc.code, exc.message, 1008)
    if not state.registry.is_known(name):
        return await deny_websocket(websocket, 404, "unknown_object", f"no object named {name!r} in the store", 1008)
    try:
        unit = ros.ros_unit(websocket.query_params)  # ?format=ros&mesh_unit=cm
    except ApiError as exc:
        return await deny_websocket(websocket, exc.status_code, exc.code, exc.message, 1008)
    sid = state.sessions.try_open()
    if sid is None:
        return await deny_websocket(websocket, 503, "too_many_sessions",
                           f"{state.settings.max_sessions} tracking sessions are open; retry later", 1013,
                           {"Retry-After": str(state.settings.retry_after_s)})
    m = state.metrics
    outcome = "error"
    try:
        try:  # the session keeps this model to its end, whatever a retraining does meanwhile
            model = await asyncio.get_running_loop().run_in_executor(state.executor, state.registry.get, name)
        except ApiError as exc:  # e.g. a corrupt model: 503 naming the object
            return await deny_websocket(websocket, exc.status_code, exc.code, exc.message, 1011)
        try:
            await websocket.accept()
        except OSError:  # (uvicorn's ClientDisconnected) the client gave up while the model loaded: no
            outcome = "disconnected"  # session to serve, and no server error (it was counted "error")
            return
        session = TrackSession(websocket, sid, name, model, state.settings, state.executor, m, clock=state.clock,
                               ros_unit=unit)
        outcome = await session.run()
    finally:
        state.sessions.close(sid)
        m.sessions.labels(outcome).inc()


def close_reason(code: str, message: str) -> str:
    """A close frame's reason: ``code: message``, cut to the 123 bytes of UTF-8 a close frame holds
    (at a character's boundary)."""
    return f"{code}: {message}".encode()[:123].decode("utf-8", "ignore")


#: refusals a browser's handshake still gets as the documented HTTP answer: a page of a foreign
#: origin, or one reaching the server under a host name it does not serve (DNS rebinding), is the
#: attack these checks stop, and is told nothing more (the viewer, served by the server itself,
#: never meets them)
_REFUSED_IN_HTTP = frozenset({"forbidden_origin", "invalid_host"})


async def deny_websocket(ws: WebSocket, status: int, code: str, message: str, close_code: int, headers=None) -> None:
    """Refuse a WebSocket. A client that is no browser (no ``Origin`` header), and any handshake
    refused as a foreign origin or host (``_REFUSED_IN_HTTP``), gets an HTTP error response where
    the server supports it. A browser's other handshakes (``Origin``), and any handshake
    where the server cannot answer in HTTP, is accepted, gets the error message
    ``{"type": "error", "error": {...}}`` and is closed with ``close_code`` (1008 policy, 1011
    server error, 1013 try again later) and the reason ``code: message``: browsers hide a refused
    handshake's HTTP answer, and the page saw a bare 1006 whatever the cause. Logged at info
    level with the reason: a refusal is the service working, not an error (see
    ``logs.mark_refused``), and counted in ``quatrack_ws_refused_total{code}``.

    Public because every refusal of a handshake goes through it, the routes' and the app's
    middleware's (``app.AllowedHosts``: a ``Host`` not allowed): one log line, one metric, one
    answer format, wherever the refusal is decided."""
    log.info("websocket refused", extra={"status": status, "code": code, "reason": message, "path": ws.url.path})
    get_ws_state(ws).metrics.ws_refused.labels(code).inc()
    if "origin" not in ws.headers or code in _REFUSED_IN_HTTP:
        try:
            await ws.send_denial_response(JSONResponse(error_body(code, message), status_code=status, headers=headers))
            mark_refused()
            return
        except RuntimeError:
            pass
    try:
        await ws.accept()
        await ws.send_text(json.dumps({"type": "error", **error_body(code, message)}))
        await ws.close(close_code, close_reason(code, message))
    except OSError:  # (uvicorn's ClientDisconnected) the client left first: nobody to tell
        pass

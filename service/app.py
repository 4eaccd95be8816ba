"""The application factory: ``create_app(settings)`` wires models, pool, limits and routes.

One app per process normally; tests build several, so each app owns its state (registry, pool,
limits, metrics registry). What it sets for the whole process, because those settings are
process-wide by nature: OpenCV's thread count, the allocator (``tune_allocator``), the
interpreter's switch interval (the event loop gets the lock sooner), and the log filters that
keep tokens out of uvicorn's lines (installed once, idempotent). The clean close of sessions on
SIGTERM is uvicorn's WebSocket protocol's business (``shutdown.py``, given as ``ws=``).
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import os
import sys
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from pathlib import Path

from importlib.metadata import version

import cv2
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from starlette.datastructures import Headers
from starlette.websockets import WebSocket

from quatrack.recognition.runtime import compile_hot_loops, limit_blas_threads, tune_allocator

from . import docs, errors, pose_all, slashes, viewer
from .errors import ApiError, error_body
from .logs import install_filters
from .metrics import Metrics, worker_exit
from .placement import placement_of_running_loop, read_board
from .registry import ModelRegistry
from .routes import ServiceState, api, deny_websocket, health, ops, origin_allowed, sockets
from .settings import Settings, usable_cores
from .workers import ReadyBoard, count_open, ready_board, session_limiter

log = logging.getLogger("quatrack.service")


def _cpu_thread_start(nice: int) -> None:
    """Each CPU thread runs at a lower priority than the event loop thread of its process.

    Why: ``/healthz`` p99 and the frames' own latency are made on the event loop (it reads the
    frames, answers probes, sends the poses). On a loaded machine the kernel scheduled the loop
    behind the tracking threads of every session; a positive nice value on the tracking threads
    (``Settings.thread_nice``, per thread: Linux ``setpriority(PRIO_PROCESS, tid)``; +5 is CFS
    weight 335 against the loop's 1024) lets the loop run first whenever it is runnable, while
    tracking still gets every cycle the loop leaves. Ignored where the call is refused."""
    if nice <= 0:
        return
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except (AttributeError, OSError):
        pass


class ServerRegistry(ModelRegistry):
    """The model registry whose ``ready`` (what ``/readyz`` answers) is true only when this
    process has loaded its models *and*, with several worker processes, every one of them has
    (:class:`workers.ReadyBoard`): whichever worker answers, the answer is the server's."""

    def __init__(self, store, on_load=None, board: ReadyBoard | None = None) -> None:
        self.board = board
        self._loaded = False
        super().__init__(store, on_load=on_load)

    @property
    def ready(self) -> bool:
        return self._loaded and (self.board is None or self.board.all_ready())

    @ready.setter
    def ready(self, value: bool) -> None:  # ModelRegistry sets it when loading is done
        self._loaded = bool(value)


DESCRIPTION = """Find a trained object in an image and estimate its 6-DoF pose (`POST /v1/objects/{name}/pose`),
or track it through a video stream over the WebSocket `/v1/objects/{name}/track`.

Pose = object → camera (`X_cam = R(q) X_obj + t`, `t` in mesh units, `q_wxyz` scalar first, `w ≥ 0`);
covariances are 6×6 over `[p, δθ]`, row-major. Errors are `{"error": {"code", "message"}}` with a 4xx status.

**WebSocket protocol**: send the camera JSON as the first text message; then binary frames (JPEG/PNG/WebP),
optionally each preceded by `{"type": "frame", "time_s": t}`; also `{"type": "reset"}` and
`{"type": "init", "pose": {"q_wxyz": [...], "t": [...]}}`. With `"ack": true` in the camera message the server answers `{"type": "ready", ...}` to it,
then one `{"type": "pose", "frame", "time_s", "status", "pose", "velocity", "covariance", "inliers", "latency_ms",
"skipped"}` per processed frame, and `{"type": "error", "error": {...}}` for bad input (the session stays open).
"""


class BodyLimit:
    """Refuse request bodies above ``limit`` bytes with 413, by header or while streaming."""

    def __init__(self, app, limit: int) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        length = dict(scope.get("headers") or []).get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.limit):
            return await _send_json(send, 413, error_body("too_large", f"the body may have at most {self.limit} bytes"))
        seen = 0

        async def limited():
            nonlocal seen
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.limit:
                    raise ApiError(413, "too_large", f"the body may have at most {self.limit} bytes")
            return msg

        await self.app(scope, limited, send)


async def _send_json(send, status: int, body: dict, headers: list | None = None) -> None:
    data = json.dumps(body).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(data)).encode()),
                            *(headers or [])]})
    await send({"type": "http.response.body", "body": data})


class AllowedHosts:
    """Requests whose ``Host`` is not in ``QUATRACK_ALLOWED_HOSTS``, or that carry more than one
    ``Host`` header, are refused, 400 ``invalid_host`` (a WebSocket's handshake too). Why: DNS rebinding — a page of an attacker's site whose name
    is made to resolve to 127.0.0.1 is same-origin with a local server, and its requests carry
    the attacker's name as ``Host``; without a token, that server is the page's. The probes
    (:data:`PROBES`) answer whatever the ``Host``: a container's health check, a kubelet or a
    balancer calls them by address and they hold nothing to steal."""

    PROBES = frozenset({"/healthz", "/readyz"})

    def __init__(self, app, hosts: tuple[str, ...]) -> None:
        self.app, self.hosts = app, hosts
        self.any = "*" in hosts
        self.suffixes = tuple(h[1:] for h in hosts if h.startswith("*."))  # "*.example.org" -> ".example.org"

    def allowed(self, host_header: str) -> bool:
        host = host_header.strip().lower()
        if host.startswith("["):  # [::1]:8000
            host = host[1:host.find("]")] if "]" in host else ""
        elif host.count(":") == 1:  # name:port (more colons: a bare IPv6 address)
            host = host.split(":")[0]
        host = host.rstrip(".")
        return self.any or (bool(host) and (host in self.hosts or host.endswith(self.suffixes)))

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket") or scope["path"] in self.PROBES:
            return await self.app(scope, receive, send)
        hosts = [v for k, v in scope.get("headers") or [] if k == b"host"]
        host = hosts[0].decode("latin-1") if hosts else ""
        if len(hosts) <= 1 and self.allowed(host):
            return await self.app(scope, receive, send)
        message = f"this server does not answer to the host {host[:80]!r} (QUATRACK_ALLOWED_HOSTS)"
        if len(hosts) > 1:  # (which one is meant? the routes read the first, a proxy may read the last)
            message = f"a request names one host, not {len(hosts)} (several Host headers)"
        if scope["type"] == "http":
            return await _send_json(send, 400, error_body("invalid_host", message))
        # as the routes refuse a handshake: an HTTP answer where the server supports it, logged,
        # counted in quatrack_ws_refused_total
        await deny_websocket(WebSocket(scope, receive, send), 400, "invalid_host", message, 1008)


class ForeignPosts:
    """On a server without a token, a ``POST`` carrying an ``Origin`` that is neither the server's
    own nor one of ``QUATRACK_CORS_ORIGINS`` is refused, 403 ``forbidden_origin``, before its body
    is read — the WebSocket's rule (:func:`~.routes.origin_allowed`) for the REST calls that do
    work. Why: a multipart ``POST …/pose`` or a ``POST …/reload`` is a "simple" request that a
    browser sends from any page without asking first; the page cannot read the answer, but every
    page a user on the network opened could make the server search images or reload models.
    Clients that are no browser send no ``Origin``; with a token the token decides."""

    METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})

    def __init__(self, app, settings: Settings) -> None:
        self.app, self.settings = app, settings

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] not in self.METHODS:
            return await self.app(scope, receive, send)
        headers = Headers(scope=scope)
        if origin_allowed(self.settings, headers):
            return await self.app(scope, receive, send)
        message = (f"a page of another site ({headers.get('origin', '')[:80]!r}) may not call this server "
                   f"(its origin is not the server's own nor in QUATRACK_CORS_ORIGINS)")
        log.info("request refused", extra={"code": "forbidden_origin", "path": scope["path"]})
        await _send_json(send, 403, error_body("forbidden_origin", message))


class HeadAsGet:
    """``HEAD`` answered as ``GET`` without the body, on every path: the same status and headers
    (``Content-Length`` the body's, ETag, security headers), so a monitor, a balancer or ``curl -I``
    probing ``/viewer``, ``/docs`` or ``/metrics`` gets what GET gets; they answered 405 (only the
    probes and Starlette's static files knew HEAD). What has no GET has no HEAD either (405 naming
    the methods it has). The request log and metrics still say ``HEAD``; uvicorn, which sees
    ``HEAD``, sends no body whatever the app passes on."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] != "HEAD":
            return await self.app(scope, receive, send)
        inner = {**scope, "method": "GET"}

        async def send_headers_only(msg):
            if msg["type"] == "http.response.body":
                msg = {**msg, "body": b""}
            await send(msg)

        try:
            await self.app(inner, receive, send_headers_only)
        finally:
            scope.setdefault("route", inner.get("route"))  # the route matched, for the request log


class SecurityHeaders:
    """``X-Content-Type-Options: nosniff`` on every answer (a JSON error echoing input is never
    sniffed as HTML), and on every HTML page (``/viewer``, ``/docs``, ``/redoc``) a refusal to be
    framed by another site (``X-Frame-Options``, CSP ``frame-ancestors``), unless the page sets
    its own policy (the viewer's: :data:`viewer.VIEWER_CSP`)."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def send_with_headers(msg):
            if msg["type"] == "http.response.start":
                headers = list(msg.get("headers", []))
                names = {k.lower() for k, _ in headers}
                extra = [] if b"x-content-type-options" in names else [(b"x-content-type-options", b"nosniff")]
                ctype = dict((k.lower(), v) for k, v in headers).get(b"content-type", b"")
                if ctype.startswith(b"text/html"):
                    extra.append((b"x-frame-options", b"DENY"))
                    if b"content-security-policy" not in names:
                        extra.append((b"content-security-policy", b"frame-ancestors 'none'"))
                msg = {**msg, "headers": headers + extra}
            await send(msg)

        await self.app(scope, receive, send_with_headers)


class RequestLog:
    """A request id (``X-Request-ID``, the client's if sane), one log line and metrics per request."""

    def __init__(self, app, metrics: Metrics) -> None:
        self.app, self.metrics = app, metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        given = dict(scope.get("headers") or []).get(b"x-request-id", b"").decode("latin-1")
        # ASCII letters, digits and '-' only: str.isalnum() also passes '²' or 'ª' (the header's
        # bytes read as latin-1), which were echoed UTF-8-encoded, other bytes than the client's
        sane = 0 < len(given) <= 64 and given.isascii() and given.replace("-", "").isalnum()
        rid = given if sane else uuid.uuid4().hex[:16]
        status = 500
        t0 = time.perf_counter()

        async def send_with_id(msg):
            nonlocal status
            if msg["type"] == "http.response.start":
                status = msg["status"]
                msg = {**msg, "headers": [*msg.get("headers", []), (b"x-request-id", rid.encode())]}
            await send(msg)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            dt = time.perf_counter() - t0
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            self.metrics.requests.labels(scope["method"], route, str(status)).inc()
            self.metrics.latency.labels(route).observe(dt)
            log.info("request", extra={"request_id": rid, "method": scope["method"], "route": route,
                                       "path": scope["path"], "status": status, "ms": round(dt * 1e3, 1)})


class StopAnswer:
    """A REST request the server's stop cut short is answered 503 ``shutting_down`` (JSON,
    ``Connection: close``), not uvicorn's plain-text 500 with an ERROR traceback.

    Why: on SIGTERM uvicorn waits ``timeout_graceful_shutdown`` seconds for requests in flight,
    then cancels them; a slow upload still being read then raised ``CancelledError`` out of the
    app ("Exception in ASGI application"). Only that stop cancels a request's task (a client
    that leaves is an ``http.disconnect``, not a cancellation), so a cancellation here is the
    server stopping: the answer tells the client to retry (on another replica), and the
    cancellation ends here (the task has nothing left to do). A request whose answer had begun
    is left as it is (its connection is closed)."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        watched, started = errors.watch_start(send)
        try:
            await self.app(scope, receive, watched)
        except asyncio.CancelledError:
            log.warning("%s %s cut short by the server's stop: answered 503 shutting_down",
                        scope.get("method"), scope.get("path"))
            if not started():
                await _send_json(send, 503, error_body("shutting_down", "the server is stopping; retry the request"),
                                 [(b"connection", b"close")])


class EncodedSlashInName:
    """An object name holding an encoded ``/`` (``/v1/objects/a%2fb``, ``..%2f..%2fetc/pose``) is
    refused 400 ``invalid_object_name``, as every other name that could leave the store is, on
    REST and on the WebSocket. Why here, before routing: the path is matched decoded, so the
    ``/`` split the name — no route matched (404 ``not_found``, where the contract says 400), or
    another one did (``POST /v1/objects/cookie-box%2fpose`` reached the pose of ``cookie-box``).
    The raw path (``raw_path``, as the client wrote it) tells an encoded ``/`` from a real one."""

    PREFIX = b"/v1/objects/"

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send):
        raw = scope.get("raw_path") if scope["type"] in ("http", "websocket") else None
        if not raw or not raw.startswith(self.PREFIX) or b"%2f" not in raw.lower():
            return await self.app(scope, receive, send)
        segment = raw[len(self.PREFIX):].split(b"?")[0].split(b"/")[0]
        if b"%2f" not in segment.lower():
            return await self.app(scope, receive, send)
        from urllib.parse import unquote

        try:
            ModelRegistry.check_name(unquote(segment.decode("latin-1")))
        except ApiError as exc:
            if scope["type"] == "http":
                return await _send_json(send, exc.status_code, error_body(exc.code, exc.message))
            return await deny_websocket(WebSocket(scope, receive, send), exc.status_code, exc.code, exc.message, 1008)
        return await self.app(scope, receive, send)  # (unreachable: a name with '/' is never valid)


class UnmatchedWebSocket:
    """The router's ``default`` for a WebSocket handshake no route matched: the tracking path with
    a final slash (``/v1/objects/NAME/track/``, which ``deploy/nginx.conf``'s ``track/?$`` passes
    on) is served as the path without it; any other path (``..%2f``, a typo) is refused 404
    ``not_found`` through :func:`~quatrack.service.routes.deny_websocket`, as the routes and
    :class:`AllowedHosts` refuse a handshake (a JSON body, logged, counted). Starlette's answer
    was a bare 403 with an empty body. HTTP requests go to the previous default (``slashes``)."""

    def __init__(self, router) -> None:
        self.router, self.fallback = router, router.default

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "websocket":
            return await self.fallback(scope, receive, send)
        from starlette.routing import Match

        path = scope["path"]
        other = slashes.other_slash(path)
        if other is not None and len(other[0]) < len(path):  # (the path with its final slash removed)
            target = {**scope, "path": other[0]}
            for route in self.router.routes:
                match, child = route.matches(target)
                if match is Match.FULL:
                    target.update(child)
                    return await route.handle(target, receive, send)
        await deny_websocket(WebSocket(scope, receive, send), 404, "not_found",
                             f"no WebSocket endpoint at {path[:120]!r}: tracking is /v1/objects/NAME/track", 1008)


def _warmed(state: ServiceState, done) -> None:
    """After :func:`_warm`: a failure is logged at once with its traceback and said by
    ``/readyz`` (``error``, 503 for good). Why: the future's exception was never read, so a
    server whose loading failed (an OpenCV without a function the loops use) answered
    ``/readyz`` 503 ``{"failed": {}}`` with nothing in the log until its shutdown printed "Future
    exception was never retrieved"."""
    if done.cancelled() or done.exception() is None:
        return
    exc = done.exception()
    state.warm_error = f"{type(exc).__name__}: {exc}"[:300]
    log.error("loading the models and warming the service failed; the server stays not ready: %s",
              state.warm_error, exc_info=exc)


def _warm(state: ServiceState, freeze: bool = False) -> None:
    """Load the store's models, compile the numba loops (:func:`~quatrack.recognition.runtime.compile_hot_loops`:
    up to ~5 s where no on-disk cache exists yet, as in a fresh container) and build each worker
    thread's matcher (a barrier puts one warming job on every thread), so the first real
    request pays none of it; then, in a process that serves only this app, freeze the heap
    (:func:`_freeze_heap`)."""
    state.registry.load_all()
    log.info("compiled loops ready in %.1f s", compile_hot_loops())
    n = state.settings.threads
    barrier = threading.Barrier(n)

    def one():
        try:
            barrier.wait(timeout=30)
        except threading.BrokenBarrierError:
            pass
        state.registry.warm()

    futures = [state.executor.submit(one) for _ in range(n)]
    for f in futures:
        f.result()
    if freeze:
        _freeze_heap()
    if isinstance(state.registry, ServerRegistry) and state.registry.board is not None:
        state.registry.board.mark_ready()  # this worker counts for the server's /readyz
    log.info("ready: %d object(s) loaded from %s", len(state.registry.loaded()), state.registry.store)


def _freeze_heap() -> None:
    """Move every object alive once the models are loaded out of the cyclic garbage collector's
    reach (``gc.freeze``), after one last collection.

    Why: a worker holds ~145 000 GC-tracked objects after start-up (modules, functions, the
    app, the models' Python parts), and a full (generation 2) collection walks them all holding
    the interpreter lock: 35–110 ms measured in a worker tracking one stream (load 3–4), a few
    times every 10 s — the event loop, and so ``/healthz`` and every session's I/O, waits for as
    long. Those objects live as long as the process; frozen, a full collection walks only what
    was allocated since (frames, tracker state). Reference counting still frees anything that
    is not in a cycle, frozen or not; what a frozen cycle holds (e.g. a model replaced by a
    retraining, if its objects form a cycle) stays until the process ends."""
    import gc

    gc.collect()
    gc.freeze()


def create_app(settings: Settings | None = None, whole_process: bool = False) -> FastAPI:
    """``whole_process``: this app is all its process serves (``quatrack serve``'s workers), so
    it may also tune what belongs to the process (the garbage collector, :func:`_freeze_heap`);
    tests build many apps in one process and leave it alone."""
    settings = (settings or Settings.from_env()).checked()
    # worker processes × threads × OpenCV threads ≈ cores: the CPUs this process may use, its
    # container's quota included (settings.usable_cores, as the default of workers and threads count
    # them); os.cpu_count() counts the host's, and on a 64-core host a 2-CPU container's two
    # workers got 32 OpenCV threads each
    cores = usable_cores()
    cv2.setNumThreads(max(1, cores // (settings.workers * settings.threads)))
    tune_allocator()  # no page faults from re-allocated frame-sized arrays
    limit_blas_threads()  # small BLAS products: one thread each, the cores go to OpenCV and the workers
    # The event loop needs the interpreter lock for every message and probe; with tracking
    # threads running Python it waits up to one switch interval each time it asks (5 ms by
    # default, several times per request): ask them to hand it over sooner.
    sys.setswitchinterval(settings.switch_interval_ms / 1e3)
    sessions = session_limiter(settings)  # shared by all worker processes when run_dir is set
    per_worker = None  # with several workers: each live one's sessions, from the placement board (service/placement.py)
    if settings.run_dir is not None and settings.workers > 1:
        per_worker = functools.partial(read_board, Path(settings.run_dir) / "placement")
    metrics = Metrics(lambda: count_open(sessions), per_worker)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        executor = ThreadPoolExecutor(settings.threads, thread_name_prefix="quatrack-cpu", initializer=_cpu_thread_start,
                                      initargs=(settings.thread_nice,))
        board = ready_board(settings)
        registry = ServerRegistry(settings.store, on_load=lambda result: metrics.model_loads.labels(result).inc(),
                                  board=board)
        state = ServiceState(settings, registry, executor, metrics, sessions)
        app.state.quatrack = state
        loop = asyncio.get_running_loop()
        placement = placement_of_running_loop()  # quatrack serve --workers N (N > 1): service/placement.py
        if placement is not None and hasattr(sessions, "on_change"):
            sessions.on_change = placement.sessions_changed
        if settings.preload:
            warm = loop.run_in_executor(None, _warm, state, whole_process)  # readyz says 503 until done
            warm.add_done_callback(lambda f: _warmed(state, f))
        else:
            state.registry.ready = True
            if board is not None:
                board.mark_ready()
            warm = None
        registry.start_watching(settings.model_poll_s)  # retrained, new and deleted models, live
        try:
            yield
        finally:
            if placement is not None and hasattr(sessions, "on_change"):
                sessions.on_change = None
            if board is not None:
                board.withdraw()
            registry.stop()
            if warm is not None and not warm.done():
                warm.cancel()
            executor.shutdown(wait=False, cancel_futures=True)
            worker_exit()

    app = FastAPI(title="quatrack", version=version("quatrack"), description=DESCRIPTION, lifespan=lifespan,
                  docs_url=None, redoc_url=None)
    errors.install(app)
    docs.install(app)  # /docs and /redoc with local assets (they work offline)
    install_filters()  # no token in uvicorn's lines, refused handshakes not logged as errors
    app.include_router(health)
    app.include_router(ops)
    app.include_router(api)
    app.include_router(sockets)
    app.include_router(viewer.router)  # /viewer page + GET /v1/objects/{name}/mesh (service/viewer.py)
    app.include_router(pose_all.router)  # POST /v1/pose: every trained object searched (service/pose_all.py)
    slashes.install(app)  # /v1/objects/ → ../objects: a relative Location, within a proxy's prefix
    app.router.default = UnmatchedWebSocket(app.router)  # .../track/ served, other handshakes a JSON 404
    app.add_middleware(errors.UnexpectedErrors)  # innermost: a 500 gets CORS, request id, nosniff as any answer
    app.add_middleware(EncodedSlashInName)  # a%2fb: 400 invalid_object_name, not the router's 404
    app.add_middleware(HeadAsGet)  # HEAD reaches the routes as GET (their body dropped)
    app.add_middleware(BodyLimit, limit=settings.max_body_bytes)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=list(settings.cors_origins), allow_methods=["GET", "POST"],
                           allow_headers=["Authorization", "Content-Type", "X-Request-ID"], expose_headers=["X-Request-ID", "Retry-After"])
    if settings.api_token is None:
        app.add_middleware(ForeignPosts, settings=settings)  # (before the body is read)
    if settings.allowed_hosts:
        app.add_middleware(AllowedHosts, hosts=settings.allowed_hosts)
    app.add_middleware(StopAnswer)  # (inside the request log: its status is logged and counted)
    app.add_middleware(SecurityHeaders)
    app.add_middleware(RequestLog, metrics=metrics)
    app.state.settings = settings
    return app

"""The contract's error body ``{"error": {"code", "message"}}`` for every failure, REST and WebSocket.

:class:`ApiError` subclasses Starlette's ``HTTPException`` on purpose: FastAPI re-raises
``HTTPException`` untouched from body parsing, so a limit hit while the body is still streaming
keeps its own status and code instead of becoming a generic 400. Anything unexpected is logged
with its traceback and answered as a 500 *without* details — bad input never gets there.
"""

from __future__ import annotations

import functools
import inspect
import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from .codes import error_body

log = logging.getLogger("quatrack.service")

_CODES = {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed",
          406: "not_acceptable", 411: "length_required", 413: "too_large", 415: "unsupported_media_type",
          422: "invalid_input", 429: "too_many_requests", 503: "unavailable"}


class ApiError(StarletteHTTPException):
    """A client-visible error: HTTP status, a stable machine-readable ``code`` and a message."""

    def __init__(self, status: int, code: str, message: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(status_code=status, detail=message, headers=headers)
        self.code = code
        self.message = message


def _json(status: int, code: str, message: str, headers=None) -> JSONResponse:
    return JSONResponse(error_body(code, message), status_code=status, headers=headers)


async def _on_http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    code = getattr(exc, "code", None) or _CODES.get(exc.status_code, "error")
    message = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    return _json(exc.status_code, code, message, getattr(exc, "headers", None))


@functools.cache
def _camera_query() -> frozenset[str]:
    """The pose endpoints' camera query parameters (:func:`.routes.camera_query`'s, read from its
    signature: one list): a value of the wrong type there is a bad camera."""
    from .routes import camera_query  # (routes imports this module: imported when first needed)

    return frozenset(inspect.signature(camera_query).parameters)


async def _on_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
    parts, camera = [], True
    for e in exc.errors():
        loc = tuple(e.get("loc", ()))
        camera &= len(loc) == 2 and loc[0] == "query" and loc[1] in _camera_query()
        if len(parts) < 5:
            # (a camera parameter by its name alone, as the camera's other messages say it: "fx: ...")
            named = loc[1:] if len(loc) == 2 and loc[0] == "query" and loc[1] in _camera_query() else loc
            where = ".".join(str(x) for x in named if x != "body") or "request"
            parts.append(f"{where}: {e.get('msg', 'invalid')}")
    # (the contract: a camera given as strings is 422 bad_camera, in the query as in the JSON field)
    return _json(422, "bad_camera" if camera and parts else "invalid_input", "; ".join(parts) or "invalid request")


async def _on_unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unexpected error on %s %s", request.method, request.url.path)
    return _json(500, "internal", "internal error (logged on the server)")


def watch_start(send):
    """``send`` wrapped to note whether the answer began, and a function saying so: a middleware
    that answers for a failed request may do so only before the app's own answer started
    (:class:`UnexpectedErrors`, ``app.StopAnswer``)."""
    started = False

    async def watched(msg):
        nonlocal started
        started = started or msg["type"] == "http.response.start"
        await send(msg)

    return watched, lambda: started


class UnexpectedErrors:
    """An exception nothing handled becomes the contract's JSON 500 *inside* the middleware stack
    (``app.py`` adds it innermost), so the answer passes the CORS, security-header and request-id
    middlewares as any other: Starlette runs an ``Exception`` handler in its outermost
    ``ServerErrorMiddleware``, and the 500 went out without ``Access-Control-Allow-Origin`` (a
    browser page saw a network error, not the answer), ``X-Request-ID`` or ``nosniff``. An
    answer already begun is left to the server (re-raised: nothing can be said any more)."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        watched, started = watch_start(send)
        try:
            await self.app(scope, receive, watched)
        except Exception as exc:
            if started():
                raise
            await (await _on_unexpected(Request(scope), exc))(scope, receive, send)


def install(app: FastAPI) -> None:
    """Register the handlers that turn every error into the contract's JSON body. (The
    ``Exception`` handler stays for what fails outside :class:`UnexpectedErrors`: the outer
    middlewares.)"""
    app.add_exception_handler(StarletteHTTPException, _on_http)
    app.add_exception_handler(RequestValidationError, _on_validation)
    app.add_exception_handler(Exception, _on_unexpected)

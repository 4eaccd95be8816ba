"""Error codes the service and its Python client (:mod:`quatrack.client`) both rely on, and the
contract's error body. Standard library only: the client imports this module, and importing it
must not pull in the server's stack (FastAPI, Starlette, uvicorn).
"""

from __future__ import annotations

# A binary frame the WebSocket session refuses *on arrival*, before numbering it
# (:meth:`service.sessions.TrackSession._on_frame`): the error carries no ``"frame"``, and the
# next frame takes the number this one would have had. The client's streaming bookkeeping
# (``quatrack.client._Session.take``) drops such a frame's index; a code refused on arrival
# but missing here left it waiting for a frame number that never came.
CAMERA_REQUIRED = "camera_required"  # a frame before any camera message
TOO_LARGE = "too_large"  # over QUATRACK_MAX_BODY_BYTES
UNSUPPORTED_IMAGE = "unsupported_image"  # not a JPEG, PNG or WebP
RATE_LIMITED = "rate_limited"  # over QUATRACK_MAX_FPS
REFUSED_FRAME = frozenset({CAMERA_REQUIRED, TOO_LARGE, UNSUPPORTED_IMAGE, RATE_LIMITED})


def error_body(code: str, message: str) -> dict:
    """The contract's error body, REST and WebSocket alike: ``{"error": {"code", "message"}}``."""
    return {"error": {"code": code, "message": message}}

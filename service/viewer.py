"""The browser viewer (``GET /viewer``) and the object wireframe it draws (``GET /v1/objects/{name}/mesh``).

The page is plain HTML + one small script, served from ``service/static/`` (package data; no
build step, no CDN, so it works on a machine without internet). Its URLs are relative (the
script finds the service's root from its own URL), so it works behind a proxy that serves the
service under a path prefix. It streams the browser's
webcam or a dropped video file over the existing WebSocket ``/v1/objects/{name}/track`` and
draws each answer. The page itself is open (it holds no data); the mesh and the socket need the
token when the server has one, which the page sends from its token field.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends
from fastapi.responses import FileResponse, RedirectResponse
from pydantic import BaseModel, Field

from quatrack.recognition.visibility import mesh_edges

from .errors import ApiError
from .routes import ERRORS, ServiceState, get_state, require_token

STATIC = Path(__file__).with_name("static")
# The viewer page's Content-Security-Policy: its own script and style only (no inline code, none
# from elsewhere: an injected <script> does not run), its socket and requests to its own origin
# ('self' covers ws:/wss: to it: Chromium 71+, Firefox, Safari 16+), the video from the webcam
# (mediastream:) or a dropped file (blob:), and no page may frame it (clickjacking the token
# field and the webcam button).
VIEWER_CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
              "media-src 'self' blob: mediastream:; connect-src 'self'; base-uri 'none'; form-action 'none'; "
              "frame-ancestors 'none'")
_FILES = {"viewer.html": "text/html; charset=utf-8", "viewer.js": "text/javascript; charset=utf-8",
          "viewer.css": "text/css; charset=utf-8"}


class MeshEdges(BaseModel):
    """The object's wireframe: the mesh's feature edges (creases and borders), in mesh units."""

    name: str
    edges: list[list[list[float]]] = Field(description="k segments, each [[x, y, z], [x, y, z]], object frame")
    bbox: list[list[float]] = Field(description="[[xmin, ymin, zmin], [xmax, ymax, zmax]] of the mesh")


viewer = APIRouter(include_in_schema=False)
mesh_api = APIRouter(prefix="/v1", tags=["objects"], dependencies=[Depends(require_token)], responses=ERRORS)


@viewer.get("/viewer")
async def viewer_page() -> RedirectResponse:
    """307 to ``viewer/``, a Location relative to ``…/viewer``: behind a proxy serving the service
    under a path prefix it lands on ``/prefix/viewer/`` (``/viewer/`` left the prefix). Not the
    page itself: its script and style are relative to it (for the same proxies), which resolve to
    ``/viewer/…`` only from ``/viewer/``; a ``<base>`` would fix the other one, and its CSP
    (``base-uri 'none'``) refuses any."""
    return RedirectResponse("viewer/")


_PAGE_HEADERS = {"Content-Security-Policy": VIEWER_CSP, "Referrer-Policy": "no-referrer"}


@viewer.get("/viewer/")
async def viewer_index() -> FileResponse:
    return FileResponse(STATIC / "viewer.html", media_type=_FILES["viewer.html"], headers=_PAGE_HEADERS)


@viewer.get("/viewer/{file}")
async def viewer_file(file: str) -> FileResponse:
    if file not in _FILES:  # a fixed list: no path from the client ever reaches the file system
        raise ApiError(404, "not_found", f"no file {file!r} in the viewer")
    return FileResponse(STATIC / file, media_type=_FILES[file], headers=_PAGE_HEADERS if file == "viewer.html" else None)


@mesh_api.get("/objects/{name}/mesh", response_model=MeshEdges, summary="the object's wireframe (for overlays)")
async def object_mesh(name: str, state: Annotated[ServiceState, Depends(get_state)]) -> MeshEdges:
    state.registry.check_name(name)
    if not state.registry.is_known(name):
        raise ApiError(404, "unknown_object", f"no object named {name!r} in the store")
    model, _ = await asyncio.get_running_loop().run_in_executor(state.executor, state.registry.get, name)
    v = model.mesh.vertices
    # (a scan's wireframe from its run-time decimation: thousands of edges, not a million)
    return MeshEdges(name=name, edges=[[list(map(float, a)), list(map(float, b))] for a, b in mesh_edges(model.mesh.run_time)],
                     bbox=[v.min(axis=0).tolist(), v.max(axis=0).tolist()])


router = APIRouter()  # what app.py mounts: the page and the mesh endpoint
router.include_router(viewer)
router.include_router(mesh_api)

"""``/docs`` (Swagger UI) and ``/redoc`` served with local assets, so they work offline.

FastAPI's default pages load their scripts from a CDN: on a machine without internet access
``/docs`` is blank. The assets come from the ``fastapi-offline`` package (Swagger UI and ReDoc
distribution builds, MIT/Apache-2.0), served under ``/docs-assets`` — FastAPI's own recipe for
self-hosted docs (``get_swagger_ui_html`` with local URLs), without replacing the app class.

Open without a token, like ``/openapi.json``: they describe the API (and how to authenticate),
never the store's objects or traffic.

Behind a reverse proxy that serves the service under a path prefix (nginx ``location /quatrack/
{ proxy_pass http://127.0.0.1:8000/; }``) the pages work with no setting: every URL they name
(the description, the assets, the OAuth2 redirect page) is relative to the page (``/docs`` and
``/redoc`` are at the root, so ``./openapi.json`` is ``/openapi.json`` there and
``/quatrack/openapi.json`` behind the proxy); they were absolute and left the prefix (a blank
page). Swagger UI's "Try it out" sends requests to the description's ``servers``, by default the
host's root, which the proxy does not serve: a proxy that says its prefix in
``X-Forwarded-Prefix`` (Traefik's ``StripPrefix`` does; nginx: ``proxy_set_header
X-Forwarded-Prefix /quatrack;``) gets ``servers: [{"url": "/quatrack"}]`` in ``/openapi.json``
(:class:`ForwardedPrefix`). A relative server (``.``) would need no header, but tools reading the
description (schemathesis, client generators) resolve it against the host, not the document.
``/docs/`` and ``/redoc/`` redirect to ``../docs``, ``../redoc`` as every final-slash redirect
does (:mod:`.slashes`).
"""

from __future__ import annotations

import re
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

ASSETS = "/docs-assets"
# A path prefix as a proxy may send it: segments of URL path characters, no empty segment; a
# value starting "//" would name another host, where "Try it out" would send the user's token.
# No comma: proxies in a chain may each append theirs ("/a,/b"), which is no one path.
_PREFIX = re.compile(r"(?:/[A-Za-z0-9._~!$&+=:;@%-]+)+/?")
# FastAPI's Swagger page prefixes the redirect page's URL with the origin (the host's root):
# resolved against the page's own URL instead, it stays within a proxy's prefix.
_REDIRECT_JS = "window.location.origin + '/docs/oauth2-redirect'"


class ForwardedPrefix:
    """``GET /openapi.json`` with ``X-Forwarded-Prefix: /PREFIX`` answers as FastAPI answers a
    request whose ASGI ``root_path`` is ``/PREFIX``: ``servers`` gains ``{"url": "/PREFIX"}``, so
    Swagger UI's "Try it out" stays within the proxy's prefix. Only that path is touched (the
    routes and the other middleware see the scope as before); a value that is not a path is
    ignored."""

    def __init__(self, app, path: str) -> None:
        self.app, self.path = app, path

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http" and scope["path"] == self.path and not scope.get("root_path"):
            given = dict(scope.get("headers") or []).get(b"x-forwarded-prefix", b"").decode("latin-1").strip()
            if given != "/" and _PREFIX.fullmatch(given):
                scope = {**scope, "root_path": given.rstrip("/")}
        return await self.app(scope, receive, send)


def _asset_dir() -> Path:
    import fastapi_offline

    return Path(fastapi_offline.__file__).resolve().parent / "static"


def install(app: FastAPI) -> None:
    """Add ``/docs``, ``/docs/oauth2-redirect``, ``/redoc`` and the assets to ``app``, which must be
    created with ``docs_url=None, redoc_url=None``."""
    app.mount(ASSETS, StaticFiles(directory=_asset_dir()), name="docs-assets")
    app.add_middleware(ForwardedPrefix, path=app.openapi_url)
    title = f"{app.title} {app.version}"
    spec, assets = f".{app.openapi_url}", f".{ASSETS}"  # relative to /docs and /redoc (see above)

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> HTMLResponse:
        page = get_swagger_ui_html(openapi_url=spec, title=f"{title} — Swagger UI",
                                   oauth2_redirect_url="/docs/oauth2-redirect",
                                   swagger_js_url=f"{assets}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{assets}/swagger-ui.css",
                                   swagger_favicon_url=f"{assets}/favicon.png")
        # (another FastAPI's page may word it otherwise: tests/test_docs_prefix.py says so)
        html = page.body.decode().replace(_REDIRECT_JS, "new URL('docs/oauth2-redirect', window.location.href).href")
        return HTMLResponse(html)

    @app.get("/docs/oauth2-redirect", include_in_schema=False)
    async def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    async def redoc() -> HTMLResponse:
        return get_redoc_html(openapi_url=spec, title=f"{title} — ReDoc",
                              redoc_js_url=f"{assets}/redoc.standalone.js", redoc_favicon_url=f"{assets}/favicon.png",
                              with_google_fonts=False)

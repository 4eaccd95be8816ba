"""A path with a final slash too many or too few (``/v1/objects/``, ``/docs-assets``) is a 307 to
the path a route serves, as Starlette's ``redirect_slashes`` answers it, but with a relative
``Location``: ``../objects``, ``./docs-assets/``.

Starlette's Location is an absolute URL of the address the server was reached at: behind a
reverse proxy that serves the service under a path prefix (nginx ``location /quatrack/ {
proxy_pass http://127.0.0.1:8000/; }``) it left the prefix (``http://host/v1/objects``, which the
proxy does not serve), and named the proxy's upstream (``127.0.0.1:8000``) when the proxy does not
pass ``Host``. A relative reference resolves against the URL the client asked for, prefix
included, with no setting and no header (``/viewer`` answers the same way: :mod:`.viewer`). The
query string is kept; the method too (307). A path ending in two slashes is not redirected
(:func:`other_slash`): no route serves it, 404.
"""

from __future__ import annotations

from urllib.parse import quote

from fastapi import FastAPI
from starlette.responses import RedirectResponse
from starlette.routing import Match, Router

# the characters a path segment may hold as they are (RFC 3986 pchar); the rest percent-encoded
_SEGMENT_SAFE = "!$&'()*+,;=:@-._~"


def other_slash(path: str) -> tuple[str, str] | None:
    """``(the path with the final slash added or removed, a reference to it relative to path)``;
    None for the root and a path ending in ``//`` (clients resolve ``../`` against empty segments
    differently: Python's ``urljoin`` and httpx drop them, browsers keep them; Starlette took every
    final slash off). ``./`` and ``../`` lead every reference, so a segment holding ``:`` never
    reads as a scheme.

    >>> other_slash("/v1/objects/"), other_slash("/v1/objects")
    (('/v1/objects', '../objects'), ('/v1/objects/', './objects/'))
    """
    stripped = path.removesuffix("/")
    if not stripped or stripped.endswith("/"):
        return None
    last = quote(stripped.rsplit("/", 1)[1], safe=_SEGMENT_SAFE)
    if stripped != path:
        return stripped, f"../{last}"
    return path + "/", f"./{last}/"


class RelativeSlashRedirect:
    """The router's ``default`` (what answers a request no route matched): the redirect above
    when the other slash matches a route, else the router's own answer (404)."""

    def __init__(self, router: Router) -> None:
        self.router, self.fallback = router, router.default

    async def __call__(self, scope, receive, send) -> None:
        other = other_slash(scope["path"]) if scope["type"] == "http" else None
        if other is not None:
            target = {**scope, "path": other[0]}
            if any(route.matches(target)[0] is not Match.NONE for route in self.router.routes):
                query = scope.get("query_string", b"").decode("latin-1")
                return await RedirectResponse(other[1] + (f"?{query}" if query else ""))(scope, receive, send)
        await self.fallback(scope, receive, send)


def install(app: FastAPI) -> None:
    """Answer ``app``'s final-slash redirects with a relative Location (Starlette's own off)."""
    app.router.redirect_slashes = False
    app.router.default = RelativeSlashRedirect(app.router)

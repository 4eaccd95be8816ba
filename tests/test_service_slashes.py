"""A final slash too many or too few is a 307 whose Location is relative (``service/slashes.py``):
behind a reverse proxy that serves the service under a path prefix (the viewer's
:class:`PathPrefixProxy`) it stays within the prefix. Starlette's own was an absolute URL of the
address the server was reached at: ``/quatrack/v1/objects/`` went to ``http://testserver/v1/objects``,
which the proxy does not serve."""

from __future__ import annotations

from urllib.parse import urljoin

import pytest
from fastapi.testclient import TestClient

from quatrack.service.app import create_app
from quatrack.service.slashes import other_slash

from test_docs_prefix import _settings
from test_viewer_prefix import PREFIX, PathPrefixProxy


@pytest.fixture
def proxied(tmp_path):
    with TestClient(PathPrefixProxy(create_app(_settings(tmp_path)), PREFIX)) as c:
        yield c


def _target(client, method: str, url: str) -> str:
    r = client.request(method, url, follow_redirects=False)
    assert r.status_code == 307 and r.content == b"", (url, r.status_code, r.text[:200])
    location = r.headers["location"]
    assert not location.startswith(("/", "http")), location  # relative: the prefix is the client's URL's
    return urljoin(url, location)


@pytest.mark.parametrize("path, query, target", [
    ("/v1/objects/", "", "/v1/objects"),
    ("/v1/objects/", "?x=1&y=%2F", "/v1/objects?x=1&y=%2F"),
    ("/docs-assets", "", "/docs-assets/"),  # (a mount: the slash added)
])
def test_a_final_slash_redirect_stays_within_the_prefix(proxied, path, query, target):
    url = f"http://testserver{PREFIX}{path}{query}"
    assert _target(proxied, "GET", url) == f"http://testserver{PREFIX}{target}"


def test_the_redirected_request_is_answered_under_the_prefix(proxied):
    r = proxied.get(f"{PREFIX}/v1/objects/")
    assert r.status_code == 200 and str(r.url) == f"http://testserver{PREFIX}/v1/objects", (r.status_code, r.url)
    assert r.json()["objects"] == []


def test_a_post_keeps_its_method_and_the_prefix(proxied):
    url = f"http://testserver{PREFIX}/v1/objects/box/reload/"
    assert _target(proxied, "POST", url) == f"http://testserver{PREFIX}/v1/objects/box/reload"


def test_without_a_proxy_and_with_an_asgi_root_path(tmp_path):
    """Directly, and behind a proxy that keeps the prefix and tells it as ``root_path``
    (``uvicorn --root-path``): the same relative answer resolves to the route."""
    with TestClient(create_app(_settings(tmp_path))) as c:
        assert _target(c, "GET", "http://testserver/v1/objects/") == "http://testserver/v1/objects"
        assert c.get("/v1/objects/").status_code == 200
    with TestClient(create_app(_settings(tmp_path)), root_path=PREFIX) as c:
        url = f"http://testserver{PREFIX}/v1/objects/"
        assert _target(c, "GET", url) == f"http://testserver{PREFIX}/v1/objects"


def test_a_path_no_route_serves_either_way_is_still_a_404(proxied):
    for path in ("/v1/nothing/", "/v1/nothing", "/", "//", "/v1/objects//"):
        r = proxied.get(f"{PREFIX}{path}", follow_redirects=False)
        assert r.status_code == 404, (path, r.status_code, r.headers.get("location"))


def test_other_slash_escapes_the_segment():
    assert other_slash("/") is None and other_slash("///") is None and other_slash("/a//") is None
    assert other_slash("/v1/a b:c/") == ("/v1/a b:c", "../a%20b:c")
    assert other_slash("/v1/a?#") == ("/v1/a?#/", "./a%3F%23/")

"""The API's description pages (``/docs``, ``/redoc``) behind a reverse proxy that serves the
service under a path prefix (nginx's ``location /quatrack/ { proxy_pass http://quatrack/; }``).
Their URLs (the description, the assets, the OAuth2 redirect page) were absolute and left the
prefix: a blank page. Swagger UI's "Try it out" goes within the prefix when the proxy sends
``X-Forwarded-Prefix``. The proxy is the viewer's :class:`PathPrefixProxy`.
"""

from __future__ import annotations

import re
import time
from urllib.parse import urljoin

import pytest
from fastapi.testclient import TestClient

from quatrack.service.app import create_app
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings

from test_viewer import chromium
from test_viewer_prefix import PREFIX, PathPrefixProxy


class PrefixSayingProxy(PathPrefixProxy):
    """The same proxy with ``proxy_set_header X-Forwarded-Prefix /quatrack;``."""

    async def __call__(self, scope, receive, send):
        if scope["type"] in ("http", "websocket"):
            headers = [(k, v) for k, v in scope.get("headers") or [] if k != b"x-forwarded-prefix"]
            scope = {**scope, "headers": [*headers, (b"x-forwarded-prefix", self.prefix.encode())]}
        return await super().__call__(scope, receive, send)


def _settings(tmp_path) -> Settings:
    return Settings(store=tmp_path, preload=False, workers=1, threads=1, model_poll_s=0)


@pytest.fixture
def proxied(tmp_path):
    with TestClient(PathPrefixProxy(create_app(_settings(tmp_path)), PREFIX)) as c:
        yield c


@pytest.fixture
def direct(tmp_path):
    with TestClient(create_app(_settings(tmp_path))) as c:
        yield c


def _refs(html: str) -> list[str]:
    """Every URL the page loads: src/href, Swagger UI's ``url:``, ReDoc's ``spec-url``."""
    return (re.findall(r'\b(?:src|href|spec-url)="([^"]*)"', html)
            + re.findall(r"^\s*url: '([^']*)'", html, flags=re.M))


@pytest.mark.parametrize("page", ["docs", "redoc"])
def test_every_url_of_the_page_is_served_under_the_prefix(proxied, page):
    url = f"http://testserver{PREFIX}/{page}"
    html = proxied.get(url)
    assert html.status_code == 200 and html.headers["content-type"].startswith("text/html")
    refs = _refs(html.text)
    assert "./openapi.json" in refs and any("docs-assets/" in r for r in refs), refs
    for ref in refs:
        r = proxied.get(urljoin(url, ref), follow_redirects=False)
        assert r.status_code == 200 and r.content, (ref, r.status_code)
    assert proxied.get(urljoin(url, "./openapi.json")).json()["info"]["title"] == "quatrack"


@pytest.mark.parametrize("page", ["docs", "redoc"])
def test_the_same_urls_are_served_without_a_proxy(direct, page):
    url = f"http://testserver/{page}"
    for ref in _refs(direct.get(url).text):
        target = urljoin(url, ref)
        assert target.startswith("http://testserver/") and "/docs/docs-assets" not in target, target
        assert direct.get(target, follow_redirects=False).status_code == 200, target


def test_the_oauth2_redirect_page_is_named_relative_to_the_page(proxied):
    """FastAPI names it ``window.location.origin + '/docs/oauth2-redirect'`` (the host's root);
    here it is resolved against the page's URL, which a proxy's prefix is part of."""
    html = proxied.get(f"{PREFIX}/docs").text
    assert "window.location.origin" not in html
    ref = re.search(r"oauth2RedirectUrl: new URL\('([^']+)', window\.location\.href\)\.href", html)
    assert ref, html[-800:]
    target = urljoin(f"http://testserver{PREFIX}/docs", ref.group(1))
    assert target == f"http://testserver{PREFIX}/docs/oauth2-redirect"
    assert proxied.get(target).status_code == 200


@pytest.mark.parametrize("page", ["docs", "redoc"])
def test_a_final_slash_redirects_within_the_prefix(proxied, direct, page):
    """``/quatrack/docs/`` was Starlette's 307 to ``http://testserver/docs``: out of the prefix
    (and to the proxy's upstream address when it does not pass ``Host``)."""
    url = f"http://testserver{PREFIX}/{page}/"
    r = proxied.get(url, follow_redirects=False)
    assert r.status_code == 307 and urljoin(url, r.headers["location"]) == f"http://testserver{PREFIX}/{page}", \
        r.headers.get("location")
    assert proxied.get(url).status_code == 200
    r = direct.get(f"/{page}/")
    assert r.status_code == 200 and str(r.url) == f"http://testserver/{page}"


def test_forwarded_prefix_names_the_server_of_the_description(tmp_path):
    with TestClient(PrefixSayingProxy(create_app(_settings(tmp_path)), PREFIX)) as c:
        assert c.get(f"{PREFIX}/openapi.json").json()["servers"] == [{"url": PREFIX}]
        # the routes themselves are unchanged by the header
        assert c.get(f"{PREFIX}/v1/objects").status_code == 200


@pytest.mark.parametrize("value", ["", "/", "//evil.example", "https://evil.example/x", "/a//b", "a/b",
                                   "/a b", "/x\"y", "/a,/b"])
def test_a_forwarded_prefix_that_is_not_a_path_is_ignored(direct, value):
    """No ``servers``, as without the header: ``//evil.example`` would send "Try it out"'s
    requests, with the token typed in, to another host."""
    schema = direct.get("/openapi.json", headers={"X-Forwarded-Prefix": value}).json()
    assert "servers" not in schema, (value, schema.get("servers"))


def test_forwarded_prefix_with_a_final_slash(direct):
    schema = direct.get("/openapi.json", headers={"X-Forwarded-Prefix": "/a/b/"}).json()
    assert schema["servers"] == [{"url": "/a/b"}]
    assert "servers" not in direct.get("/openapi.json").json()  # (one request's prefix is not kept)


def test_swagger_ui_tries_a_request_within_the_prefix_in_a_browser(tmp_path):
    """In Chromium, through the proxy: the page renders the API, every resource it loaded came
    from under the prefix, and "Try it out" on ``GET /v1/objects`` is answered (the proxy answers
    404 outside the prefix)."""
    srv = BackgroundServer(_settings(tmp_path))
    srv.server.config.app = PrefixSayingProxy(srv.app, PREFIX)  # (uvicorn loads the app when it starts)
    with srv:
        driver = chromium(tmp_path)
        try:
            def wait(script, what):
                deadline = time.monotonic() + 120  # a bound for a hung browser, not a speed requirement
                while time.monotonic() < deadline:
                    value = driver.execute_script(script)
                    if value:
                        return value
                    time.sleep(0.2)
                raise AssertionError(f"timed out waiting for {what}")

            driver.get(f"{srv.url}{PREFIX}/docs")
            op = "document.querySelector('#operations-objects-list_objects_v1_objects_get')"  # GET /v1/objects
            wait(f"return {op} !== null", "the operations")
            servers = driver.execute_script("return [...document.querySelectorAll('.servers select option')].map(o => o.value)")
            assert servers == [PREFIX], servers
            driver.execute_script(f"{op}.querySelector('.opblock-summary-control').click()")
            for button, what in (("try-out__btn", "Try it out"), ("execute", "Execute")):
                wait(f"const b = {op}.querySelector('.{button}'); if (b) {{ b.click(); return true }} return false", what)
            url = wait("const u = document.querySelector('.request-url pre'); return u && u.textContent", "the request's URL")
            assert url.strip() == f"{srv.url}{PREFIX}/v1/objects", url
            status = wait("const s = document.querySelector('.live-responses-table tr.response .response-col_status');"
                          " return s && s.textContent.trim()", "the answer")
            assert status.startswith("200"), status
            urls = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
            urls = [u for u in urls if u != f"{srv.url}/favicon.ico"]  # (the browser's own, at the host's root)
            assert urls and all(u.startswith(f"{srv.url}{PREFIX}/") for u in urls), urls
        finally:
            driver.quit()

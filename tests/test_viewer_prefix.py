"""The viewer behind a reverse proxy that serves the service under a path prefix (nginx's
``location /quatrack/ { proxy_pass http://quatrack/; }``): the page, its script and style, the
object list, the wireframe and the WebSocket are all reached under the prefix. The page used
absolute paths (``/viewer/viewer.js``, ``/v1/…``) and ``/viewer`` redirected to ``/viewer/``:
each left the prefix. The proxy is :class:`PathPrefixProxy`, in the server's own process.
"""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import urljoin

import pytest
from fastapi.testclient import TestClient

from quatrack.service.app import create_app
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

from test_viewer import EXAMPLE, _driver, _finished, _wait, write_y4m

PREFIX = "/quatrack"
TOKEN = "viewer-prefix-token"
STATIC = Path(__file__).resolve().parent.parent / "service" / "static"


class PathPrefixProxy:
    """What the proxy above does: a path under ``prefix`` reaches the service without it, any
    other path is not the service's (404; a WebSocket is closed). The probes pass as they are:
    :class:`BackgroundServer` polls them at its own address."""

    def __init__(self, app, prefix: str) -> None:
        self.app, self.prefix = app, prefix

    async def __call__(self, scope, receive, send):
        if scope["type"] == "lifespan" or scope["path"] in ("/healthz", "/readyz"):
            return await self.app(scope, receive, send)
        if not scope["path"].startswith(self.prefix + "/"):
            if scope["type"] == "websocket":
                return await send({"type": "websocket.close", "code": 1008})
            await send({"type": "http.response.start", "status": 404, "headers": [(b"content-type", b"text/plain")]})
            return await send({"type": "http.response.body", "body": b"not behind the prefix"})
        n = len(self.prefix)
        raw = scope.get("raw_path")
        inner = {**scope, "path": scope["path"][n:], "raw_path": raw[n:] if raw else raw}
        return await self.app(inner, receive, send)


@pytest.fixture
def proxied(tmp_path):
    settings = Settings(store=tmp_path, preload=False, workers=1, threads=1, model_poll_s=0)
    with TestClient(PathPrefixProxy(create_app(settings), PREFIX)) as c:
        yield c


def test_viewer_redirects_within_the_prefix(proxied):
    """``GET /viewer`` is a 307 whose Location is relative (``viewer/``): from
    ``/quatrack/viewer`` it resolves to ``/quatrack/viewer/`` (``/viewer/`` left the prefix)."""
    page = f"http://testserver{PREFIX}/viewer"
    r = proxied.get(page, follow_redirects=False)
    assert r.status_code == 307 and r.content == b"", r.status_code
    target = urljoin(page, r.headers["location"])
    assert target == f"http://testserver{PREFIX}/viewer/", target
    html = proxied.get(target, follow_redirects=False)
    assert html.status_code == 200 and html.headers["content-type"].startswith("text/html")


def test_the_page_s_script_and_style_are_reached_under_the_prefix(proxied):
    """Every ``src``/``href`` of the page, resolved against its URL under the prefix, is served."""
    page = f"http://testserver{PREFIX}/viewer/"
    html = proxied.get(page).text
    refs = [r for r in re.findall(r'\b(?:src|href)="([^"]*)"', html) if not r.startswith("data:")]  # (data: loads nothing)
    assert sorted(refs) == ["viewer.css", "viewer.js"], refs
    for ref in refs:
        r = proxied.get(urljoin(page, ref), follow_redirects=False)
        assert r.status_code == 200 and r.content, (ref, r.status_code)


def test_the_script_names_no_absolute_path():
    """The script's requests and socket are built from its own URL (``ROOT``): no string in it
    starts with ``/`` (an absolute path such as ``/v1/objects`` leaves a proxy's prefix)."""
    js = (STATIC / "viewer.js").read_text()
    absolute = re.findall(r"""["'`]/[\w.-]""", js)
    assert absolute == [], absolute
    assert "location.host" not in js  # (the socket's URL was built from the page's host and /v1/…)
    html = (STATIC / "viewer.html").read_text()
    assert not re.findall(r'\b(?:src|href|action)="/', html)


def test_viewer_tracks_behind_the_prefix_in_a_browser(tmp_path):
    """In Chromium, through the proxy: the objects are listed, the webcam's frames tracked (poses
    drawn), and every resource the page loaded came from under the prefix."""
    y4m = tmp_path / "box.y4m"
    write_y4m(EXAMPLE / "box.mp4", y4m, 30)
    srv = BackgroundServer(Settings(store=example_store(), api_token=TOKEN))
    srv.server.config.app = PathPrefixProxy(srv.app, PREFIX)  # (uvicorn loads the app when it starts)
    with srv:
        driver = _driver(tmp_path, y4m)
        try:
            driver.get(f"{srv.url}{PREFIX}/viewer")
            assert driver.current_url == f"{srv.url}{PREFIX}/viewer/", driver.current_url
            driver.find_element("id", "token").send_keys(TOKEN)
            driver.execute_script("document.getElementById('token').dispatchEvent(new Event('change'))")
            _wait(driver, lambda: driver.execute_script("return document.getElementById('object').value") == "cookie-box",
                  "the objects")
            driver.execute_script("document.getElementById('camera').value = arguments[0]",
                                  (EXAMPLE / "camera.json").read_text())
            driver.execute_script("document.getElementById('max-frames').value = '3'")
            driver.find_element("id", "webcam").click()
            _wait(driver, lambda: _finished(driver), "the run's end with poses")
            assert driver.find_element("id", "pose-count").text == "3", driver.find_element("id", "info").text
            urls = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
            urls = [u for u in urls if u != f"{srv.url}/favicon.ico"]  # (the browser's own, at the host's root)
            assert f"{srv.url}{PREFIX}/v1/objects/cookie-box/mesh" in urls, urls
            assert all(u.startswith(f"{srv.url}{PREFIX}/") for u in urls), urls
        finally:
            driver.quit()

"""The service as a user deploys it (token on, behind nginx or exposed): what a security review
found, one test per finding (each failed before its fix). The routes' auth, the constant-time
comparison and the redaction of ``?token=`` are also covered by test_service_http.py and
test_service_ws.py."""

from __future__ import annotations

import logging

import pytest

from quatrack.service.logs import ServiceLogFilter, redact

SECRET = "s3cr3t-T0KEN"


@pytest.mark.parametrize("query", [
    f"token={SECRET}", f"TOKEN={SECRET}", f"%74oken={SECRET}", f"tok%65n={SECRET}", f"%54%4F%4B%45%4E={SECRET}",
    f"a=1&token={SECRET}", f"a=1;token={SECRET}", f"access_token={SECRET}", f"token=wrong&token={SECRET}",
    "token=ab'cd(" + SECRET + ")",
])
def test_a_token_is_redacted_however_its_key_is_written(query):
    """The server reads the query's keys percent-decoded (``?%74oken=`` is ``?token=`` to it), but
    the log filter looked for the literal ``token=``: a client that encoded the key had its token
    written in uvicorn's WebSocket line. A value with a quote or a bracket in it (left as they are
    by encodeURIComponent, which the viewer uses) was cut at the quote."""
    line = f'127.0.0.1:5000 - "WebSocket /v1/objects/cookie-box/track?{query}" [accepted]'
    clean = redact(line)
    assert SECRET not in clean and "[redacted]" in clean, clean
    record = logging.LogRecord("uvicorn.error", logging.INFO, __file__, 1, '%s - "WebSocket %s" [accepted]',
                               ("127.0.0.1:5000", f"/v1/objects/cookie-box/track?{query}"), None)
    ServiceLogFilter().filter(record)
    assert SECRET not in record.getMessage()


def test_redaction_leaves_other_parameters_and_messages_alone():
    assert redact("/v1/objects/cookie-box/pose?fx=1&fy=2&format=ros") == "/v1/objects/cookie-box/pose?fx=1&fy=2&format=ros"
    assert redact("a valid bearer token is required (the Authorization header, or the query parameter token)") == \
        "a valid bearer token is required (the Authorization header, or the query parameter token)"
    assert redact("/track?token=") == "/track?token="  # nothing to hide


# --- a server with a token, over a store holding a broken model ---------------------------------

import json  # noqa: E402
import shutil  # noqa: E402

import httpx  # noqa: E402

from quatrack.service.server import BackgroundServer  # noqa: E402
from quatrack.service.settings import Settings  # noqa: E402
from quatrack.testing.scenes import example_store  # noqa: E402
from quatrack.viewsets import store as store_mod  # noqa: E402

AUTH = {"Authorization": f"Bearer {SECRET}"}
CAMERA = {"fx": 669.7, "fy": 667.8, "cx": 320.0, "cy": 240.0}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """The example, and two broken copies (truncated arrays, a garbled manifest)."""
    dst = tmp_path_factory.mktemp("security") / "models"
    for name in ("cookie-box", "truncated", "garbled"):
        shutil.copytree(example_store() / "cookie-box", dst / name)
        m = json.loads((dst / name / store_mod.MANIFEST).read_text())
        (dst / name / store_mod.MANIFEST).write_text(json.dumps({**m, "name": name}))
    arrays = dst / "truncated" / store_mod.ARRAYS
    arrays.write_bytes(arrays.read_bytes()[:1000])
    (dst / "garbled" / store_mod.MANIFEST).write_text("{not json")
    return dst


@pytest.fixture(scope="module")
def server(store):
    with BackgroundServer(Settings(store=store, api_token=SECRET, model_poll_s=0)) as srv:
        yield srv


@pytest.fixture(scope="module")
def client(server):
    with httpx.Client(base_url=server.url, timeout=60) as c:
        yield c


def test_no_answer_shows_where_the_store_is(client, store):
    """The store's errors name their files (kept in the log for the operator); ``/readyz`` —
    open without a token — ``GET /v1/objects``, the 503 answers, ``POST /v1/pose``'s ``failed``
    and ``reload`` showed the server's paths (``/data/models/…``) to clients."""
    where = str(store.parent)
    ready = client.get("/readyz").json()
    assert set(ready["failed"]) == {"truncated", "garbled"}, ready
    answers = [json.dumps(ready)]
    answers.append(client.get("/v1/objects", headers=AUTH).text)
    for name in ("truncated", "garbled"):
        answers.append(client.get(f"/v1/objects/{name}", headers=AUTH).text)
        r = client.post(f"/v1/objects/{name}/pose", content=b"\xff\xd8\xff", params=CAMERA,
                        headers={**AUTH, "content-type": "image/jpeg"})
        answers.append(r.text)
        answers.append(client.post(f"/v1/objects/{name}/reload", headers=AUTH).text)
    assert any("model_unavailable" in a for a in answers)
    for a in answers:
        assert where not in a and "/models/" not in a, a
    # what the reasons still say: which object, which file, what is wrong
    assert "'truncated'" in ready["failed"]["truncated"] and "model.npz" in ready["failed"]["truncated"]
    assert "manifest" in ready["failed"]["garbled"]


@pytest.mark.parametrize("name", ["cookie-box%0A", "cookie-box%0A/mesh", "cookie-box%0D%0A"])
def test_a_name_with_a_line_break_is_refused(client, name):
    """``re.match`` with ``$`` matched before a trailing newline: ``cookie-box\\n`` passed the name
    check and was looked up in the store (404 unknown_object)."""
    r = client.get(f"/v1/objects/{name}", headers=AUTH)
    assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_object_name", r.text


def test_a_refused_name_is_not_echoed_whole(client):
    r = client.get("/v1/objects/" + "a" * 4000, headers=AUTH)
    assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_object_name"
    assert len(r.text) < 400, r.text


def test_pages_say_how_they_may_be_used(client):
    """No answer carried X-Content-Type-Options, and no page refused to be framed by another site
    (a page framing the viewer could click its webcam button over the user's token); the viewer
    had no Content-Security-Policy. Its policy allows what it needs (its own script, style and
    socket, the webcam, a dropped file: test_viewer.py runs it under that policy in Chromium)."""
    for path in ("/viewer/", "/viewer/viewer.html", "/docs", "/redoc"):
        r = client.get(path)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html"), path
        assert r.headers.get("x-content-type-options") == "nosniff", path
        assert r.headers.get("x-frame-options") == "DENY", path
        assert "frame-ancestors 'none'" in r.headers.get("content-security-policy", ""), path
    csp = {d.split()[0]: d.split()[1:] for d in client.get("/viewer/").headers["content-security-policy"].split("; ")}
    assert csp["default-src"] == ["'none'"] and csp["script-src"] == ["'self'"] and csp["connect-src"] == ["'self'"]
    assert "'unsafe-inline'" not in str(csp) and "'unsafe-eval'" not in str(csp)
    assert client.get("/viewer/").headers.get("referrer-policy") == "no-referrer"
    for path, headers in (("/viewer/viewer.js", {}), ("/healthz", {}), ("/v1/objects", {}), ("/v1/objects", AUTH),
                          ("/nowhere", {})):
        r = client.get(path, headers=headers)
        assert r.headers.get("x-content-type-options") == "nosniff", (path, r.status_code)
        assert "x-frame-options" not in r.headers, path  # (not a page)
    r = client.post("/v1/objects/cookie-box/pose", content=b"0" * 11_000_000, headers={**AUTH, "content-type": "image/jpeg"})
    assert r.status_code == 413 and r.headers.get("x-content-type-options") == "nosniff"


def _ws_status(url: str, **kw) -> int:
    """101 when the session is served, else the refusal's HTTP status. A browser's handshake (with
    ``origin``) is refused after its opening (test_service_errors_ws_browser.py): an error message
    then close 1008; its HTTP status is then read from the error's code."""
    import json

    from websockets.exceptions import ConnectionClosed, InvalidStatus
    from websockets.sync.client import connect

    from test_service_ws import CAM_ACK

    try:
        with connect(url, open_timeout=30, **kw) as ws:
            try:
                ws.send(CAM_ACK)
            except ConnectionClosed:  # (refused: the error message is already there to read)
                pass
            first = json.loads(ws.recv(timeout=60))
            if first["type"] == "ready":
                return 101
            return {"forbidden_origin": 403, "unauthorized": 401}[first["error"]["code"]]
    except InvalidStatus as exc:
        return exc.response.status_code


def test_another_site_cannot_open_the_websocket_of_a_server_without_a_token(store):
    """Cross-site WebSocket hijacking: the same-origin policy does not cover WebSockets, and the
    handshake's Origin was not checked: any page the user visited could open sessions on a
    tokenless server (127.0.0.1 included), holding its QUATRACK_MAX_SESSIONS and, with
    QUATRACK_LEARN_VIEWS, feeding the stored model. Now refused (403 forbidden_origin) unless the
    origin is the server's own or one of QUATRACK_CORS_ORIGINS; clients that are no browser send
    no Origin and are unaffected; with a token the token decides (no browser sends it on its own)."""
    with BackgroundServer(Settings(store=store, model_poll_s=0, cors_origins=("https://app.example",))) as srv:
        url = f"{srv.ws_url}/v1/objects/cookie-box/track"
        port = url.split(":")[2].split("/")[0]
        assert _ws_status(url, origin="https://evil.example") == 403
        assert _ws_status(url, origin="null") == 403
        assert _ws_status(url, origin=f"http://127.0.0.1:{int(port) + 1}") == 403  # another port: another site
        assert _ws_status(url) == 101  # no Origin: not a browser
        assert _ws_status(url, origin=f"http://127.0.0.1:{port}") == 101  # the viewer's own page
        assert _ws_status(url, origin="https://app.example") == 101  # allowed by QUATRACK_CORS_ORIGINS
        # a proxy that says which host the page reached
        assert _ws_status(url, origin="https://public.example", additional_headers={"X-Forwarded-Host": "public.example"}) == 101
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert 'code="forbidden_origin"' in c.get("/metrics").text


def test_what_counts_as_the_servers_own_origin():
    from quatrack.service.routes import _same_origin

    assert _same_origin("http://127.0.0.1:8000", "127.0.0.1:8000")
    assert _same_origin("https://quatrack.example", "quatrack.example:443")
    assert _same_origin("http://lb.example:8080", "lb.example")  # nginx's Host $host drops the port
    assert not _same_origin("http://lb.example:8080", "lb.example:8000")
    assert not _same_origin("http://evil.example", "lb.example")
    assert not _same_origin("http://lb.example.evil.example", "lb.example")
    assert not _same_origin("null", "lb.example") and not _same_origin("file://", "lb.example")
    assert not _same_origin("http://[::1", "lb.example")  # malformed: refused, not a 500


def test_with_a_token_the_token_decides_whatever_the_origin(server):
    url = f"{server.ws_url}/v1/objects/cookie-box/track"
    assert _ws_status(url, origin="https://evil.example") == 401
    assert _ws_status(f"{url}?token={SECRET}", origin="https://evil.example") == 101


@pytest.mark.skipif(__import__("quatrack.testing.balancer", fromlist=["find_nginx"]).find_nginx() is None,
                    reason="nginx is not installed")
def test_nginx_passes_the_token_and_its_log_format_leaves_it_out(server, tmp_path, monkeypatch):
    """deploy/nginx.conf had no access-log format to offer: turning the log on meant nginx's
    default, whose $request holds a browser's ``?token=``. Its ``quatrack`` format logs ``$uri``;
    the Authorization header is passed on to the service."""
    from websockets.sync.client import connect

    from quatrack.testing import balancer

    conf = balancer.NGINX_CONF.read_text()
    assert conf.count("access_log off;") == 1 and "log_format quatrack" in conf
    fmt = conf[conf.index("log_format quatrack"):].split(";")[0]
    assert not any(v in fmt for v in ("$request ", "$request\"", "$request_uri", "$args", "$query_string", "$http_authorization"))
    log = tmp_path / "nginx" / "logs" / "access.log"
    template = tmp_path / "nginx.conf"
    template.write_text(conf.replace("access_log off;", f"access_log {log} quatrack;"))
    port = int(server.url.rsplit(":", 1)[1])
    with balancer.Nginx(tmp_path / "nginx", [port]) as lb:
        pass  # (started with deploy/nginx.conf: valid as shipped)
    monkeypatch.setattr(balancer, "nginx_config", lambda ports, listen, _c=balancer.nginx_config: _c(ports, listen, template))
    with balancer.Nginx(tmp_path / "nginx", [port]) as lb, httpx.Client(base_url=lb.url, timeout=60) as c:
        assert c.get("/v1/objects", headers=AUTH).status_code == 200  # the header reaches the service
        assert c.get("/v1/objects", params={"token": "wrong-" + SECRET}).status_code == 401
        with connect(f"{lb.ws_url}/v1/objects/cookie-box/track?token={SECRET}", open_timeout=30):
            pass
    text = log.read_text()
    assert "/v1/objects/cookie-box/track" in text and "/v1/objects" in text
    assert SECRET not in text, text


@pytest.mark.skipif(__import__("quatrack.testing.balancer", fromlist=["find_nginx"]).find_nginx() is None,
                    reason="nginx is not installed")
def test_nginx_error_log_keeps_a_websocket_token_out(tmp_path):
    """nginx's error log writes the request line, query included, when a replica cannot be
    reached (down, restarting): a browser's ``?token=`` on the WebSocket went with it. The
    WebSocket's location logs no errors; a REST request's failure is still logged."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    from quatrack.testing import balancer
    from quatrack.testing.loopback import free_port

    dead = free_port()  # nothing listens there: every proxied request fails
    with balancer.Nginx(tmp_path / "nginx", [dead]) as lb, httpx.Client(base_url=lb.url, timeout=60) as c:
        for path in ("/v1/objects/cookie-box/track", "/v1/objects/cookie-box/track/", "/v1/objects/cookie-box/%74rack"):
            with pytest.raises(InvalidStatus) as failed:
                with connect(f"{lb.ws_url}{path}?token={SECRET}", open_timeout=30):
                    pass
            assert failed.value.response.status_code == 502, path
        assert c.get("/v1/objects", params={"probe": "rest-request-logged"}).status_code == 502
    log = lb.error_log.read_text()
    assert "rest-request-logged" in log, log[-2000:]  # the error log is on and tells of the dead replica
    assert SECRET not in log and "/track" not in log, log[-2000:]


def test_the_image_gets_no_secrets_nor_history():
    """The Dockerfile copies the whole folder (COPY . /src) and there was no .dockerignore: a
    checkout's .env (QUATRACK_API_TOKEN=…), .git and .venv went into an image layer. It runs as
    an unprivileged user."""
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    ignored = {ln.strip() for ln in (root / ".dockerignore").read_text().splitlines() if ln.strip() and not ln.startswith("#")}
    assert {".git", ".venv", ".env", "**/.env"} <= ignored
    assert not {"examples", "service", "*"} & ignored  # what the image needs stays
    docker = (root / "Dockerfile").read_text()
    assert "\nUSER quatrack" in docker and docker.index("\nUSER quatrack") < docker.index("\nENTRYPOINT")

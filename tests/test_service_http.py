"""End-to-end tests of the service's HTTP side: a real uvicorn server on a loopback port.

The example object is trained once per test process into a temporary store (≈ 3 s), shared with
the recognition tests (``quatrack.testing.scenes.example_store``).
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from quatrack.testing.scenes import example_store
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "cookie-box"
CAMERA = json.loads((EXAMPLE / "camera.json").read_text())


def video_frames(n: int, start: int = 0) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    out = []
    i = 0
    while len(out) < n:
        ok, frame = cap.read()
        if not ok:
            break
        if i >= start:
            out.append(frame)
        i += 1
    cap.release()
    return out


def jpeg(img: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()


def png_claiming(width: int, height: int) -> bytes:
    """A tiny PNG whose header claims ``width × height`` pixels (a decompression bomb's shape)."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


@pytest.fixture(scope="module")
def store():
    return example_store()


@pytest.fixture(scope="module")
def server(store):
    settings = Settings(store=store, max_body_bytes=2_000_000, max_image_pixels=2_000_000)
    with BackgroundServer(settings) as srv:
        yield srv


@pytest.fixture(scope="module")
def client(server):
    with httpx.Client(base_url=server.url, timeout=60) as c:
        yield c


@pytest.fixture(scope="module")
def frame_jpeg():
    return jpeg(video_frames(1, start=10)[0])


def assert_error(r: httpx.Response, status: int, code: str | None = None) -> dict:
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == {"error"} and set(body["error"]) == {"code", "message"}, body
    if code is not None:
        assert body["error"]["code"] == code, body
    return body


def test_health_ready_objects(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz").json()
    assert ready["ready"] and ready["models"] == ["cookie-box"] and ready["tracker"]
    objs = client.get("/v1/objects").json()["objects"]
    assert [o["name"] for o in objs] == ["cookie-box"] and objs[0]["loaded"]
    detail = client.get("/v1/objects/cookie-box").json()
    assert detail["name"] == "cookie-box" and detail["training_summary"]["viewsets"] == objs[0]["viewsets"]


def test_health_probes_answer_head(client):
    """Monitors and load balancers often probe with HEAD: /healthz and /readyz answer it as GET
    (status and headers, no body); they were 405."""
    for path in ("/healthz", "/readyz"):
        get, head = client.get(path), client.head(path)
        assert head.status_code == get.status_code == 200 and head.content == b"", (path, head.status_code)
        assert head.headers["content-type"] == get.headers["content-type"]


def _check_pose_json(body: dict) -> None:
    assert body["found"], body
    q = np.array(body["pose"]["q_wxyz"])
    assert abs(np.linalg.norm(q) - 1) < 1e-6 and q[0] >= 0
    cov = np.array(body["covariance"])
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > -1e-12)
    assert 20 < body["pose"]["t"][2] < 200  # the box is tens of cm in front of the webcam
    assert body["inliers"] >= 12 and set(body["time_ms"]) >= {"localise", "match", "pnp", "total"}


def test_pose_multipart_and_raw_agree(client, frame_jpeg):
    r = client.post("/v1/objects/cookie-box/pose", files={"image": ("f.jpg", frame_jpeg, "image/jpeg")},
                    data={"camera": json.dumps(CAMERA)})
    assert r.status_code == 200, r.text
    _check_pose_json(r.json())
    params = {k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}
    r2 = client.post("/v1/objects/cookie-box/pose", content=frame_jpeg, params=params,
                     headers={"content-type": "image/jpeg"})
    assert r2.status_code == 200, r2.text
    _check_pose_json(r2.json())
    assert np.allclose(r.json()["pose"]["t"], r2.json()["pose"]["t"], atol=1e-6)
    assert r2.headers["x-request-id"]
    # "the same JSON object as locate --json", which begins with "image": the upload's name (none raw)
    assert list(r.json())[:2] == ["image", "found"] and r.json()["image"] == "f.jpg" and r2.json()["image"] is None


def test_pose_png_and_webp(client):
    img = video_frames(1, start=10)[0]
    params = {k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}
    for ext, ctype in ((".png", "image/png"), (".webp", "image/webp")):
        data = cv2.imencode(ext, img)[1].tobytes()
        r = client.post("/v1/objects/cookie-box/pose", content=data, params=params, headers={"content-type": ctype})
        assert r.status_code == 200, (ext, r.text)
        assert r.json()["found"]


def test_no_object_in_image_is_not_an_error(client):
    blank = jpeg(np.full((480, 640, 3), 127, np.uint8))
    r = client.post("/v1/objects/cookie-box/pose", content=blank, params={k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")},
                    headers={"content-type": "image/jpeg"})
    assert r.status_code == 200 and r.json()["found"] is False and r.json()["pose"] is None


@pytest.mark.parametrize("case", ["not-image", "truncated", "empty", "bomb", "wrong-size", "tiny"])
def test_bad_images(client, frame_jpeg, case):
    q = {k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}
    data, status, code = {
        "not-image": (b"hello, this is text" * 10, 415, "unsupported_image"),
        "truncated": (frame_jpeg[: len(frame_jpeg) // 2], 400, "bad_image"),
        "empty": (b"", 400, "bad_image"),
        "bomb": (png_claiming(30000, 30000), 413, "image_too_large"),
        "wrong-size": (jpeg(cv2.resize(video_frames(1)[0], (320, 240))), 422, "bad_image"),
        "tiny": (jpeg(np.zeros((8, 8, 3), np.uint8)), 422, "bad_image"),
    }[case]
    if case == "wrong-size":
        q.update(width=640, height=480)
    r = client.post("/v1/objects/cookie-box/pose", content=data, params=q, headers={"content-type": "image/jpeg"})
    assert_error(r, status, code)


@pytest.mark.parametrize("camera, status", [
    ("{not json", 422), (json.dumps({"fx": 1}), 422), (json.dumps({**CAMERA, "fx": -5}), 422),
    (json.dumps({**CAMERA, "dist_coeffs": [1, 2, 3]}), 422), (json.dumps([1, 2]), 422),
    (json.dumps({**CAMERA, "cx": "nan"}), 422),
    # implausible: accepted with 200 (and a second of work for fx = 1e308) before
    (json.dumps({**CAMERA, "fx": 1e308}), 422), (json.dumps({**CAMERA, "fx": True}), 422),
    (json.dumps({**CAMERA, "fy": "600"}), 422), (json.dumps({**CAMERA, "fx": 3.0}), 422),
    (json.dumps({**CAMERA, "cx": 5000}), 422), (json.dumps({**CAMERA, "width": True}), 422),
    (json.dumps({**CAMERA, "dist_coeffs": [True, 0, 0, 0]}), 422), (json.dumps({**CAMERA, "fy": 20000}), 422),
])
def test_bad_cameras(client, frame_jpeg, camera, status):
    r = client.post("/v1/objects/cookie-box/pose", files={"image": ("f.jpg", frame_jpeg, "image/jpeg")},
                    data={"camera": camera})
    body = assert_error(r, status)
    assert body["error"]["code"] in ("bad_camera", "invalid_input") and "\n" not in body["error"]["message"]


def test_implausible_query_camera_and_a_huge_camera_field(client, frame_jpeg):
    url = "/v1/objects/cookie-box/pose"
    r = client.post(url, content=frame_jpeg, headers={"content-type": "image/jpeg"},
                    params={"fx": 1e300, "fy": 600, "cx": 320, "cy": 240})  # size from the image
    assert "fx" in assert_error(r, 422, "bad_camera")["error"]["message"]
    r = client.post(url, content=frame_jpeg, headers={"content-type": "image/jpeg"},
                    params={"fx": "abc", "fy": 600, "cx": 320, "cy": 240})  # a string: bad_camera (invalid_input before)
    assert "fx" in assert_error(r, 422, "bad_camera")["error"]["message"]
    huge = json.dumps({**CAMERA, "pad": "x" * 1_000_000})  # "malformed multipart body (HTTPException)" before
    r = client.post(url, files={"image": ("f.jpg", frame_jpeg, "image/jpeg")}, data={"camera": huge})
    assert "camera" in assert_error(r, 413, "too_large")["error"]["message"]


def test_missing_pieces(client, frame_jpeg):
    url = "/v1/objects/cookie-box/pose"
    assert_error(client.post(url, content=frame_jpeg, headers={"content-type": "image/jpeg"}), 422, "bad_camera")
    assert_error(client.post(url, content=frame_jpeg, params={"fx": 600}, headers={"content-type": "image/jpeg"}), 422, "bad_camera")
    assert_error(client.post(url, data={"camera": json.dumps(CAMERA)}, files={"other": ("x", b"1")}), 422, "missing_image")
    assert_error(client.post(url, content=b"{}", headers={"content-type": "application/json"}), 415)
    assert_error(client.post(url, content=b"--x\r\nbroken", headers={"content-type": "multipart/form-data; boundary=x"}), 422)


def test_unknown_and_invalid_objects(client, frame_jpeg):
    assert_error(client.get("/v1/objects/mug"), 404, "unknown_object")
    assert_error(client.get("/v1/objects/.hidden"), 400, "invalid_object_name")
    assert_error(client.get("/v1/objects/..%2F..%2Fetc"), 400, "invalid_object_name")  # never reaches the store
    r = client.post("/v1/objects/mug/pose", content=frame_jpeg, headers={"content-type": "image/jpeg"},
                    params={k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")})
    assert_error(r, 404, "unknown_object")
    assert_error(client.get("/nowhere"), 404)
    assert_error(client.delete("/v1/objects"), 405)


def test_body_limit(client):
    big = b"\xff\xd8\xff" + b"0" * 2_100_000
    assert_error(client.post("/v1/objects/cookie-box/pose", content=big, headers={"content-type": "image/jpeg"}), 413, "too_large")

    def chunks():  # no content-length: the limit is enforced while streaming
        for _ in range(30):
            yield b"0" * 100_000
    assert_error(client.post("/v1/objects/cookie-box/pose", content=chunks(), headers={"content-type": "image/jpeg"}), 413, "too_large")


def test_metrics_and_openapi(client):
    text = client.get("/metrics").text
    assert "# TYPE quatrack_http_requests_total counter" in text
    assert 'route="/v1/objects/{name}/pose"' in text and "quatrack_ws_sessions_active 0" in text
    schema = client.get("/openapi.json").json()
    assert "/v1/objects/{name}/pose" in schema["paths"]
    assert client.get("/docs").status_code == 200


def test_auth(store, frame_jpeg):
    with BackgroundServer(Settings(store=store, api_token="s3cret", cors_origins=("https://app.example",))) as srv:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.get("/healthz").status_code == 200 and c.get("/readyz").status_code == 200
            for path in ("/v1/objects", "/v1/objects/cookie-box", "/metrics"):
                r = assert_error(c.get(path), 401, "unauthorized")
                assert_error(c.get(path, headers={"Authorization": "Bearer wrong"}), 401)
            assert c.get("/v1/objects", headers={"Authorization": "Bearer s3cret"}).status_code == 200
            r = c.post("/v1/objects/cookie-box/pose", content=frame_jpeg, headers={"content-type": "image/jpeg"},
                       params={k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")})
            assert_error(r, 401)
            pre = c.options("/v1/objects", headers={"Origin": "https://app.example", "Access-Control-Request-Method": "GET"})
            assert pre.headers.get("access-control-allow-origin") == "https://app.example"


def test_docs_are_served_locally_and_what_is_open_without_a_token(store):
    """/docs loaded Swagger UI from a CDN (blank offline). With a token set, the health checks and
    the API's description are open; everything that shows objects, poses or traffic is not."""
    with BackgroundServer(Settings(store=store, api_token="t0k")) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        for page, asset in (("/docs", "swagger-ui-bundle.js"), ("/redoc", "redoc.standalone.js")):
            html = c.get(page)
            assert html.status_code == 200 and f"/docs-assets/{asset}" in html.text, html.text[:300]
            assert "cdn." not in html.text and "https://" not in html.text.replace("https://fastapi", "")
            js = c.get(f"/docs-assets/{asset}")
            assert js.status_code == 200 and len(js.content) > 100_000
        assert c.get("/docs-assets/swagger-ui.css").status_code == 200
        for path in ("/healthz", "/openapi.json", "/docs"):
            assert c.get(path).status_code == 200, path
        assert c.get("/readyz").status_code in (200, 503)
        for path in ("/metrics", "/v1/objects", "/v1/objects/cookie-box"):
            assert_error(c.get(path), 401, "unauthorized")
        assert_error(c.post("/v1/objects/cookie-box/reload"), 401, "unauthorized")
        assert c.get("/metrics", headers={"Authorization": "Bearer t0k"}).status_code == 200


def test_both_pose_endpoints_refuse_work_beyond_max_pending(store):
    """Admission is one rule for ``/v1/objects/{name}/pose`` and ``/v1/pose``: with
    ``max_pending_requests`` in progress a request is 503 ``busy`` with Retry-After, and once
    the pool has room it is served. (The pending count is set directly: no race with the pool.)"""
    cam = {"fx": 669.7, "fy": 667.8, "cx": 320.0, "cy": 240.0}
    image = jpeg(video_frames(1)[0])
    with BackgroundServer(Settings(store=store, max_pending_requests=1)) as srv, \
            httpx.Client(base_url=srv.url, timeout=120) as c:
        state = srv.app.state.quatrack
        state.pending = 1  # one request in progress
        for path in ("/v1/objects/cookie-box/pose", "/v1/pose"):
            r = c.post(path, content=image, params=cam, headers={"content-type": "image/jpeg"})
            assert r.status_code == 503 and r.json()["error"]["code"] == "busy", (path, r.text)
            assert int(r.headers["retry-after"]) > 0
        assert state.pending == 1  # a refused request does not count
        state.pending = 0
        r = c.post("/v1/objects/cookie-box/pose", content=image, params=cam, headers={"content-type": "image/jpeg"})
        assert r.status_code == 200 and r.json()["found"] is True, r.text
        assert state.pending == 0


def test_an_endless_request_head_is_refused(server, client):
    """A header line that never ends: uvicorn's parser kept every byte (one client, 200 MB sent:
    +313 MB in the worker); past 64 KiB the server answers 431 and closes the connection."""
    import socket

    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: ")
        got = b""
        try:
            for _ in range(64):  # 4 MiB at most; the server stops reading long before
                s.sendall(b"a" * 65536)
            while True:
                part = s.recv(65536)
                if not part:
                    break
                got += part
        except (ConnectionResetError, BrokenPipeError):  # closed with our bytes unread: refused all the same
            pass
        except socket.timeout:
            pytest.fail("the server neither answered nor closed the connection")
    assert got == b"" or got.startswith(b"HTTP/1.1 431"), got[:200]
    if got:
        assert json.loads(got.split(b"\r\n\r\n", 1)[1])["error"]["code"] == "too_large"
    assert client.get("/healthz").status_code == 200  # the server goes on
    big_cookie = {"cookie": "a=" + "b" * 8000}  # a long but reasonable head still passes
    assert client.get("/healthz", headers=big_cookie).status_code == 200


def _head_answer(port: int, head: bytes) -> bytes:
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        got = b""
        try:
            s.sendall(head)
            while True:
                part = s.recv(65536)
                if not part:
                    break
                got += part
        except (ConnectionResetError, BrokenPipeError):
            pass
    return got


def test_a_whole_request_head_over_64_kib_is_refused(server, client):
    """A complete head over the bound, arriving in one piece, is refused too (it was passed to the
    app: only the bytes of a head not yet ended were counted); one just under it still passes, and
    so does the second request of a kept-alive connection, whose head is counted afresh."""
    def head(n: int, close: bool = True) -> bytes:
        line = b"GET /healthz HTTP/1.1\r\nHost: x\r\n" + (b"Connection: close\r\n" if close else b"")
        return line + b"X-Big: " + b"a" * (n - len(line) - 11) + b"\r\n\r\n"

    for n in (70_000, 100_000, 200_000):
        got = _head_answer(server.port, head(n))
        assert got == b"" or got.startswith(b"HTTP/1.1 431"), (n, got[:200])
    assert _head_answer(server.port, head(60_000)).startswith(b"HTTP/1.1 200")
    both = _head_answer(server.port, head(40_000, close=False) + head(40_000))
    assert both.count(b"HTTP/1.1 200") == 2, both[:300]
    assert client.get("/healthz").status_code == 200


def test_a_client_leaving_mid_upload_is_not_a_server_error(server, client):
    """A raw-body upload the client abandons (a timeout, a dropped mobile link): the server logged
    "unexpected error" with a traceback and counted a 500 — alerts on 5xx fired for the clients'
    aborts. Now it is 499 (nginx's "client closed request"), as for a multipart upload."""
    import socket

    from conftest import wait_until

    def count(status: str) -> float:
        total = 0.0
        for line in client.get("/metrics").text.splitlines():
            if line.startswith("quatrack_http_requests_total{") and f'status="{status}"' in line and "pose" in line:
                total += float(line.split()[-1])
        return total

    before = count("499"), count("500")
    query = "fx=669.7&fy=667.8&cx=320&cy=240"
    for path, ctype, start in ((f"/v1/objects/cookie-box/pose?{query}", "image/jpeg", b"\xff\xd8\xff"),
                               (f"/v1/pose?{query}", "image/jpeg", b"\xff\xd8\xff"),
                               ("/v1/objects/cookie-box/pose", "multipart/form-data; boundary=XX",
                                b'--XX\r\nContent-Disposition: form-data; name="image"; filename="a.jpg"\r\n'
                                b"Content-Type: image/jpeg\r\n\r\n\xff\xd8\xff")):
        with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:
            s.sendall(f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: {ctype}\r\nContent-Length: 100000\r\n\r\n".encode()
                      + start + b"a" * 1000)
    assert wait_until(lambda: count("499") == before[0] + 3), (count("499"), count("500"), before)
    assert count("500") == before[1]


def test_a_camera_file_with_a_byte_order_mark_is_read(client, frame_jpeg):
    """A camera JSON saved with a UTF-8 byte order mark (Windows editors), uploaded as the
    multipart field ``camera`` (a file or a text field): read, as ``quatrack`` reads camera files
    (it was 422 bad_camera "Invalid JSON"); the field's order does not matter either."""
    text = "\ufeff" + json.dumps(CAMERA)
    for camera in ((None, text), ("camera.json", text.encode("utf-8"), "application/json")):
        files = [("camera", camera), ("image", ("f.jpg", frame_jpeg, "image/jpeg"))]  # (the camera first)
        r = client.post("/v1/objects/cookie-box/pose", files=files)
        assert r.status_code == 200 and r.json()["found"], r.text[:300]


def test_a_misspelt_camera_field_is_refused_with_a_suggestion(client, frame_jpeg):
    cam = {k: v for k, v in CAMERA.items() if k != "dist_coeffs"} | {"dist_coeff": [0.1, 0, 0, 0]}
    r = client.post("/v1/objects/cookie-box/pose", files={"image": ("f.jpg", frame_jpeg, "image/jpeg")},
                    data={"camera": json.dumps(cam)})
    assert "did you mean 'dist_coeffs'" in assert_error(r, 422, "bad_camera")["error"]["message"]

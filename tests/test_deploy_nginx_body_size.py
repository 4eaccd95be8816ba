"""deploy/nginx.conf gives the server's body limit headroom and answers its own 413 in JSON: with
``client_max_body_size`` equal to ``QUATRACK_MAX_BODY_BYTES``, a multipart upload of an image
just under the limit (the body is a few hundred bytes more) got nginx's HTML 413 page, not the
contract's error body."""

from __future__ import annotations

import httpx
import pytest

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.balancer import Nginx, find_nginx
from quatrack.testing.scenes import example_store

pytestmark = pytest.mark.skipif(find_nginx() is None, reason="nginx is not installed (Debian: apt-get install nginx)")


def test_large_uploads_get_the_json_error_through_nginx(tmp_path):
    limit = Settings(store=example_store()).max_body_bytes
    with BackgroundServer(Settings(store=example_store(), workers=1, threads=1)) as srv, \
            Nginx(tmp_path / "nginx", [srv.port]) as lb:
        for size, who in ((limit - 100, "server"), (limit + 2 * 1024 * 1024, "nginx")):
            r = httpx.post(f"{lb.url}/v1/objects/cookie-box/pose", timeout=60,
                           files={"image": ("big.jpg", b"\xff\xd8\xff" + b"0" * (size - 3), "image/jpeg")})
            assert r.status_code == 413 and r.headers["content-type"].startswith("application/json"), (who, r.text[:200])
            assert r.json()["error"]["code"] == "too_large", (who, r.text)
            if who == "nginx":
                assert "client_max_body_size" in r.json()["error"]["message"]
            else:
                assert "client_max_body_size" not in r.json()["error"]["message"]

"""An object name with an encoded ``/`` is 400 ``invalid_object_name``, as the Security section
lists it: the path is routed decoded, so ``a%2fb`` split into two segments and no route matched
(404 ``not_found``), or another route did (``cookie-box%2fpose``)."""

from __future__ import annotations

import json

import httpx
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store())) as srv:
        yield srv


def _raw(srv, method: str, path: str) -> httpx.Response:
    """The request with its path exactly as written (no client normalising ``..`` or ``%2f``)."""
    with httpx.Client() as c:
        req = c.build_request(method, srv.url)
        req.url = req.url.copy_with(raw_path=path.encode())
        return c.send(req)


@pytest.mark.parametrize("method, path", [("GET", "/v1/objects/a%2fb"), ("GET", "/v1/objects/a%2Fb/mesh"),
                                          ("POST", "/v1/objects/..%2f..%2fetc/pose"),
                                          ("POST", "/v1/objects/cookie-box%2fpose?fx=1")])
def test_an_encoded_slash_in_a_name_is_an_invalid_name(server, method, path):
    r = _raw(server, method, path)
    assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_object_name", (r.status_code, r.text)
    assert "invalid object name" in r.json()["error"]["message"]


def test_a_real_slash_is_still_routed(server):
    assert _raw(server, "GET", "/v1/objects/cookie-box/nothing").json()["error"]["code"] == "not_found"
    assert _raw(server, "GET", "/v1/objects/cookie-box").status_code == 200


def test_on_the_websocket_too(server):
    with pytest.raises(InvalidStatus) as err:
        connect(server.ws_url + "/v1/objects/..%2f..%2fetc/track", open_timeout=20)
    assert err.value.response.status_code == 400
    assert json.loads(err.value.response.body)["error"]["code"] == "invalid_object_name"

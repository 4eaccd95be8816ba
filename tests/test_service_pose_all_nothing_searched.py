"""``POST /v1/pose`` on a server that can search nothing (user report, session 73): an empty
store answered 200 ``{"found": false, "objects": []}`` — a robot reads an empty shelf from a
server without a model, where ``quatrack locate --object all`` refuses the store. It is a 503
now, as is a store whose every model is broken; an object searched and not found says why."""

from __future__ import annotations

import httpx

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.viewsets import store as store_mod
from test_service_http import CAMERA
from test_service_models import copy_store, frames  # noqa: F401 - a fixture

QUERY = {k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}


def _post(srv, frame):
    with httpx.Client(base_url=srv.url, timeout=60) as c:
        return c.post("/v1/pose", content=frame, params=QUERY, headers={"content-type": "image/jpeg"})


def test_an_empty_store_is_503_not_nothing_found(tmp_path, frames):  # noqa: F811
    (tmp_path / "store").mkdir()
    with BackgroundServer(Settings(store=tmp_path / "store", model_poll_s=0)) as srv:
        r = _post(srv, frames[0])
    assert r.status_code == 503 and r.json()["error"]["code"] == "no_objects", r.text
    assert "no trained object" in r.json()["error"]["message"]


def test_a_store_of_broken_models_is_503_naming_them(tmp_path, frames):  # noqa: F811
    store = copy_store(tmp_path, ("broken",))
    arrays = store / "broken" / store_mod.ARRAYS
    arrays.write_bytes(arrays.read_bytes()[:1000])
    with BackgroundServer(Settings(store=store, model_poll_s=0)) as srv:
        r = _post(srv, frames[0])
    assert r.status_code == 503 and r.json()["error"]["code"] == "model_unavailable", r.text
    assert "broken" in r.json()["error"]["message"]


def test_an_object_not_found_says_why(tmp_path, frames):  # noqa: F811
    import cv2
    import numpy as np

    store = copy_store(tmp_path, ("cookie-box",))
    blank = cv2.imencode(".jpg", np.full((480, 640, 3), 128, np.uint8))[1].tobytes()
    with BackgroundServer(Settings(store=store, model_poll_s=0)) as srv:
        found, empty = _post(srv, frames[0]).json(), _post(srv, blank).json()
    assert found["found"] and found["not_found"] == {}
    assert not empty["found"] and list(empty["not_found"]) == ["cookie-box"] and empty["not_found"]["cookie-box"]

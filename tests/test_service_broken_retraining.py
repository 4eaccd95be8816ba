"""A retraining that leaves broken files for an object already served takes it out of service
(the contract: a model that cannot be read is 503 ``model_unavailable``): ``/readyz``,
``GET /v1/objects``, ``reload`` and the pose route agree. The previous model had been served
while ``/readyz`` listed it under both ``models`` and ``failed`` and ``/v1/objects`` said
``loaded: true`` with an ``error``."""

from __future__ import annotations

import os

import httpx

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.viewsets import store as store_mod
from test_service_http import CAMERA
from test_service_models import copy_store


def _pose(c: httpx.Client, frame: bytes) -> httpx.Response:
    return c.post("/v1/objects/cookie-box/pose", content=frame, headers={"content-type": "image/jpeg"},
                  params={k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")})


def test_a_broken_retraining_takes_the_object_out_of_service_coherently(tmp_path):
    from test_service_http import jpeg, video_frames

    frame = jpeg(video_frames(1, start=10)[0])
    store = copy_store(tmp_path, ("cookie-box",))
    with BackgroundServer(Settings(store=store, model_poll_s=0)) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        assert _pose(c, frame).status_code == 200
        # a retraining whose arrays came out truncated: new files (a new stamp), unreadable
        arrays = store / "cookie-box" / store_mod.ARRAYS
        data = arrays.read_bytes()
        tmp = arrays.with_name("new.npz")
        tmp.write_bytes(data[:1000])
        os.replace(tmp, arrays)
        reload = c.post("/v1/objects/cookie-box/reload").json()
        assert reload["status"] == "failed" and "previous model" not in (reload["message"] or ""), reload
        ready = c.get("/readyz").json()
        assert ready["models"] == [] and set(ready["failed"]) == {"cookie-box"}, ready
        obj = c.get("/v1/objects").json()["objects"][0]
        assert obj["loaded"] is False and obj["error"], obj
        r = _pose(c, frame)
        assert r.status_code == 503 and r.json()["error"]["code"] == "model_unavailable", r.text

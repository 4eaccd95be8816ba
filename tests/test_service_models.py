"""The service and its model store: a corrupt model is that object's error, retrained and deleted
models are picked up live, running sessions keep the model they started with."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil

import httpx
import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from quatrack.testing.scenes import example_store
from quatrack.cli import main
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.viewsets import store as store_mod
from quatrack.viewsets.mesh import Mesh
from quatrack.viewsets.store import load_model, save_model
from conftest import wait_until
from test_service_http import CAMERA, jpeg, video_frames

CAM_ACK = json.dumps({**CAMERA, "ack": True})


@pytest.fixture(scope="module")
def frames():
    return [jpeg(f) for f in video_frames(6)]


def copy_store(tmp_path, names=("cookie-box",)):
    """A private store holding the example under each of ``names``."""
    src = example_store() / "cookie-box"
    dst = tmp_path / "store"
    for name in names:
        shutil.copytree(src, dst / name)
        m = json.loads((dst / name / store_mod.MANIFEST).read_text())
        (dst / name / store_mod.MANIFEST).write_text(json.dumps({**m, "name": name}))
    return dst


class Records(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record):
        self.records.append(record)


def first_pose(srv, name, frame, **kw) -> dict:
    with connect(f"{srv.ws_url}/v1/objects/{name}/track", open_timeout=20, **kw) as ws:
        ws.send(json.dumps(CAMERA))
        ws.send(frame)
        return json.loads(ws.recv(timeout=60))


def test_a_corrupt_model_is_that_objects_error(tmp_path, frames):
    store = copy_store(tmp_path, ("broken", "cookie-box"))
    arrays = store / "broken" / store_mod.ARRAYS
    arrays.write_bytes(arrays.read_bytes()[:1000])  # truncated: BadZipFile → 500 and /readyz 503 forever before
    logs = Records()
    server = BackgroundServer(Settings(store=store, model_poll_s=0))  # configures logging: add ours after it
    logging.getLogger("quatrack.service").addHandler(logs)
    try:
        with server as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
            ready = c.get("/readyz")
            assert ready.status_code == 200, ready.text
            body = ready.json()
            assert body["models"] == ["cookie-box"] and set(body["failed"]) == {"broken"}
            assert "'broken'" in body["failed"]["broken"] and "unreadable" in body["failed"]["broken"]
            r = c.post("/v1/objects/broken/pose", content=frames[0], params={k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")},
                       headers={"content-type": "image/jpeg"})
            assert r.status_code == 503 and r.json()["error"]["code"] == "model_unavailable", r.text
            msg = r.json()["error"]["message"]
            assert "'broken'" in msg and msg.count("retrain it") == 1, msg  # (said once, not twice)
            with pytest.raises(InvalidStatus) as err:
                connect(f"{srv.ws_url}/v1/objects/broken/track", open_timeout=20)
            assert err.value.response.status_code == 503
            assert json.loads(err.value.response.body)["error"]["code"] == "model_unavailable"
            objs = {o["name"]: o for o in c.get("/v1/objects").json()["objects"]}
            assert objs["broken"]["error"] and not objs["broken"]["loaded"] and objs["cookie-box"]["error"] is None
            assert first_pose(srv, "cookie-box", frames[0])["status"] == "init"  # the other object is served
            # the failure was logged once, at error level, however often it was asked for
            failures = [r for r in logs.records if r.levelno == logging.ERROR and "broken" in r.getMessage()]
            assert len(failures) == 1, [r.getMessage() for r in failures]
            # fixed by retraining (an atomic rename), then the admin call: served at once
            save_model(store, dataclasses.replace(load_model(store, "cookie-box"), name="broken"))
            assert c.post("/v1/objects/broken/reload").json() == {"name": "broken", "status": "loaded", "message": None}
            assert c.post("/v1/objects/broken/reload").json()["status"] == "unchanged"
            assert c.get("/readyz").json()["failed"] == {}
            assert first_pose(srv, "broken", frames[0])["status"] == "init"
            # deleted: out of service at the admin call
            assert main(["models", "delete", "broken", "--store", str(store)]) == 0
            assert c.post("/v1/objects/broken/reload").json()["status"] == "removed"
            assert c.post("/v1/objects/broken/reload").status_code == 404
            assert c.get("/readyz").json()["models"] == ["cookie-box"]
    finally:
        logging.getLogger("quatrack.service").removeHandler(logs)


def scaled(model, k: float):
    """The same object at k times the size: the same image then gives k times the distance."""
    vs = [dataclasses.replace(v, points3d=v.points3d * k, pose=type(v.pose)(v.pose.q_wxyz, v.pose.t * k))
          for v in model.viewsets]
    photos = [dataclasses.replace(r, pose=type(r.pose)(r.pose.q_wxyz, r.pose.t * k)) for r in model.appearance]
    return dataclasses.replace(model, viewsets=vs, mesh=Mesh(model.mesh.vertices * k, model.mesh.faces), appearance=photos)


def test_retrained_and_deleted_models_are_picked_up_live(tmp_path, frames):
    store = copy_store(tmp_path)
    settings = Settings(store=store, model_poll_s=0.1, max_sessions=4)
    with BackgroundServer(settings) as srv:
        def loads_ok() -> float:
            for line in httpx.get(f"{srv.url}/metrics").text.splitlines():
                if line.startswith('quatrack_model_loads_total{result="ok"}'):
                    return float(line.split()[-1])
            return 0.0

        assert loads_ok() == 1
        with connect(f"{srv.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as old:
            old.send(CAM_ACK)
            assert json.loads(old.recv(timeout=60))["type"] == "ready"
            old.send(frames[0])
            before = json.loads(old.recv(timeout=60))
            assert before["status"] == "init"
            save_model(store, scaled(load_model(store, "cookie-box"), 2.0))  # `quatrack train` replacing it
            assert wait_until(lambda: loads_ok() == 2)  # the watcher loaded it, no request needed
            new = first_pose(srv, "cookie-box", frames[0])
            assert new["status"] == "init"
            t0 = np.array(before["pose"]["t"])
            assert np.linalg.norm(np.array(new["pose"]["t"]) - 2 * t0) < 0.05 * np.linalg.norm(2 * t0)
            old.send(frames[1])  # the running session still tracks with the model it started with
            after = json.loads(old.recv(timeout=60))
            assert after["status"] in ("init", "tracking")
            assert np.linalg.norm(np.array(after["pose"]["t"]) - t0) < 0.05 * np.linalg.norm(t0)  # not 2× away
            assert main(["models", "delete", "cookie-box", "--store", str(store)]) == 0

            def refused() -> bool:
                try:
                    with connect(f"{srv.ws_url}/v1/objects/cookie-box/track", open_timeout=20):
                        pass
                except InvalidStatus as exc:
                    return exc.response.status_code == 404
                return False

            assert wait_until(refused)  # out of service for new sessions within seconds
            assert httpx.get(f"{srv.url}/readyz").json()["models"] == []
            old.send(frames[2])  # ... while the running one finishes
            assert json.loads(old.recv(timeout=60))["type"] == "pose"


def test_without_polling_a_deleted_model_leaves_every_worker_at_its_next_request(tmp_path):
    """QUATRACK_MODEL_POLL_S=0 with several worker processes: `reload` reaches one worker only, and
    the others served a deleted object forever (a stamp of None was left to a poll that never runs)."""
    from quatrack.service.errors import ApiError
    from quatrack.service.registry import ModelRegistry

    store = copy_store(tmp_path, ("gone", "cookie-box"))
    registry = ModelRegistry(store)  # no start_watching: as with model_poll_s=0
    registry.load_all()
    assert registry.loaded() == ["cookie-box", "gone"]
    assert main(["models", "delete", "gone", "--store", str(store)]) == 0
    with pytest.raises(ApiError) as err:
        registry.get("gone")
    assert err.value.status_code == 404 and err.value.code == "unknown_object"
    assert registry.loaded() == ["cookie-box"] and not registry.is_known("gone")
    assert registry.get("cookie-box")[0].name == "cookie-box"

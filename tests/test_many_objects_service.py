"""Several objects in one store, over the service (trial 7): ``POST /v1/pose?format=ros`` takes
each object's mesh unit (a store mixing meshes in mm and m got one unit for all, and the other
objects' metres were silently wrong), found objects carry ``rivals``, and ``Client.pose_all`` /
``AsyncClient.pose_all`` call the endpoint.

Two zoo objects of different units (a 10 cm cube in metres, a flat box in millimetres) are
trained once for the module (one photo each, no synthetic views) and rendered side by side.
"""

from __future__ import annotations

import asyncio
import json

import cv2
import numpy as np
import pytest

from quatrack.client import AsyncClient, Client
from quatrack.recognition.trackio import UNIT_METRES, pose_from_ros
from quatrack.service.schemas import LocateAllOut
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing import zoo as Z
from quatrack.tracking.pose import Pose
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.store import save_model
from quatrack.viewsets.train import TrainParams, train_object

CAM = Z.zoo_camera()
CAMERA = {"width": CAM.width, "height": CAM.height, "fx": CAM.fx, "fy": CAM.fy, "cx": CAM.cx, "cy": CAM.cy}
UNITS = {"cube-m": "m", "flat-box-mm": "mm"}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    bgs = Z.real_backgrounds()
    base = tmp_path_factory.mktemp("many")
    trained = {}
    for name in UNITS:
        cv2.setRNGSeed(0)
        spec = load_spec(Z.write_spec(name, base / name, 1, backgrounds=bgs))
        model = train_object(spec, TrainParams(novel=None))
        save_model(base / "store", model)
        trained[name] = (model, [spec.views[0].pose])
    image, truths = Z.two_object_scene(np.random.default_rng(3), "cube-m", "flat-box-mm", trained, CAM, bgs)
    ok, png = cv2.imencode(".png", image)
    with BackgroundServer(Settings(store=base / "store")) as srv:
        yield srv, png.tobytes()


def _post(srv, png, **query):
    import httpx

    files = {"image": ("two.png", png, "image/png"), "camera": (None, json.dumps(CAMERA))}
    return httpx.post(f"{srv.url}/v1/pose", files=files, params=query, timeout=120)


def _metres_right(o, unit):
    """``o``'s ``ros`` is its pose with the position in metres from ``unit``."""
    pose, _ = pose_from_ros(o["ros"], unit)
    return pose.allclose(Pose(o["pose"]["q_wxyz"], o["pose"]["t"]), atol=1e-9)


def test_each_object_gets_its_own_mesh_unit(served):
    srv, png = served
    r = _post(srv, png, format="ros", mesh_unit="cube-m:m,flat-box-mm:mm")
    assert r.status_code == 200, r.text
    objs = {o["object"]: o for o in r.json()["objects"]}
    assert sorted(objs) == sorted(UNITS)
    for name, o in objs.items():
        assert _metres_right(o, UNITS[name]) and "ros_note" not in o
        position = o["ros"]["pose"]["pose"]["position"]
        assert position["z"] == pytest.approx(o["pose"]["t"][2] * UNIT_METRES[UNITS[name]])
    # a bare unit among them is every other object's; one unit alone is still every object's
    r = _post(srv, png, format="ros", mesh_unit="mm,cube-m:m")
    assert all(_metres_right(o, UNITS[o["object"]]) for o in r.json()["objects"])
    r = _post(srv, png, format="ros", mesh_unit="mm")
    assert all(_metres_right(o, "mm") for o in r.json()["objects"])


def test_an_object_found_without_its_unit_has_a_note_instead_of_wrong_metres(served):
    srv, png = served
    r = _post(srv, png, format="ros", mesh_unit="cube-m:m")
    objs = {o["object"]: o for o in r.json()["objects"]}
    assert _metres_right(objs["cube-m"], "m")
    flat = objs["flat-box-mm"]
    assert "ros" not in flat and "flat-box-mm:mm" in flat["ros_note"] and flat["pose"] is not None


@pytest.mark.parametrize("mesh_unit, says", [("cube:m", "'cube': no such object"), ("cube-m:km", "'cube-m:km'"),
                                              ("cm,m", "bare unit is given twice"), ("cube-m:m,cube-m:m", "twice"),
                                              ("cube-m:m,", "NAME:UNIT")])
def test_a_bad_unit_list_is_refused_before_the_search(served, mesh_unit, says):
    srv, png = served
    r = _post(srv, png, format="ros", mesh_unit=mesh_unit)
    assert r.status_code == 422 and r.json()["error"]["code"] == "bad_format", r.text
    assert says in r.json()["error"]["message"] and "\n" not in r.json()["error"]["message"]


def test_plain_json_has_rivals_and_no_ros_keys(served):
    srv, png = served
    body = _post(srv, png).json()
    assert len(body["objects"]) == 2
    for o in body["objects"]:
        assert o["rivals"] == [] and "ros" not in o and "ros_note" not in o and o["image"] == "two.png"
    LocateAllOut.model_validate(body)


def test_clients_call_pose_all(served):
    srv, png = served
    with Client(srv.url) as client:
        out = client.pose_all(png, CAMERA)
        ros = client.pose_all(png, CAMERA, ros_mesh_unit=UNITS)
    assert isinstance(out, LocateAllOut) and out.found and sorted(out.searched) == sorted(UNITS)
    assert sorted(o.object for o in out.objects) == sorted(UNITS) and out.failed == {}
    assert all(_metres_right(o.model_dump(), UNITS[o.object]) for o in ros.objects)

    async def run():
        async with AsyncClient(srv.url) as client:
            return await client.pose_all(png, CAMERA, ros_mesh_unit="mm")

    got = asyncio.run(run())
    assert sorted(o.object for o in got.objects) == sorted(UNITS) and all(o.ros is not None for o in got.objects)


def test_objects_chooses_which_are_searched(served):
    """``objects=NAME,...``: only those are searched (each costs ~30–40 ms of a 640×480 image);
    a name the store does not hold is a 422, and the per-object endpoint has no such parameter."""
    import httpx

    srv, png = served
    r = _post(srv, png, objects="cube-m")
    assert r.status_code == 200, r.text
    assert r.json()["searched"] == ["cube-m"] and [o["object"] for o in r.json()["objects"]] == ["cube-m"]
    both = _post(srv, png, objects="flat-box-mm, cube-m").json()
    assert sorted(both["searched"]) == ["cube-m", "flat-box-mm"] and len(both["objects"]) == 2
    assert sorted(_post(srv, png).json()["searched"]) == ["cube-m", "flat-box-mm"]  # (default: all)
    for bad in ("nothing", "cube-m,,flat-box-mm", ""):
        r = _post(srv, png, objects=bad)
        assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_input", (bad, r.text)
    files = {"image": ("two.png", png, "image/png"), "camera": (None, json.dumps(CAMERA))}
    r = httpx.post(f"{srv.url}/v1/objects/cube-m/pose", files=files, params={"objects": "cube-m"}, timeout=120)
    assert r.status_code == 422 and "unknown query parameter 'objects'" in r.json()["error"]["message"], r.text

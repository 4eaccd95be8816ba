"""Look-alikes of different sizes in one store (trial 7): ``locate_all`` reports one answer per
place, and the object suppressed there is named in the found one's ``rivals`` (it was marked
not found silently, and the wrong size was picked by a confidence margin of 0.003).

The look-alike is the zoo cube's own spec at 1.5× the size: the mesh and the photo's pose scaled
by 1.5 (the same pixels: a 1.5× larger cube 1.5× farther away), trained as ``cube-m-big``.
"""

from __future__ import annotations

import json
import re
import shutil

import cv2
import numpy as np
import pytest

from quatrack.cli import main
from quatrack.recognition.locate import locate_all
from quatrack.testing import zoo as Z
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.store import save_model
from quatrack.viewsets.train import train_object

CAM = Z.zoo_camera()
SCALE = 1.5


def _scaled_spec(path, out_dir, name: str, scale: float):
    """A copy of the spec at ``path`` for the same print ``scale`` times larger."""
    import trimesh

    shutil.copytree(path.parent, out_dir)
    spec = json.loads((out_dir / "object.json").read_text())
    mesh = trimesh.load(str(out_dir / spec["mesh"]), process=False)
    trimesh.Trimesh(mesh.vertices * scale, mesh.faces, process=False).export(str(out_dir / spec["mesh"]))
    for v in spec["views"]:
        v["pose"]["t"] = [scale * x for x in v["pose"]["t"]]
    spec["name"] = name
    (out_dir / "object.json").write_text(json.dumps(spec))
    return out_dir / "object.json"


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    bgs = Z.real_backgrounds()
    cv2.setRNGSeed(0)
    base = tmp_path_factory.mktemp("twins")
    small = load_spec(Z.write_spec("cube-m", base / "small", 1, backgrounds=bgs))
    big = load_spec(_scaled_spec(small.path, base / "big", "cube-m-big", SCALE))
    obj = Z.textured("cube-m")
    scene = Z.random_scene(np.random.default_rng(21), obj, CAM, small.views[0].pose, bgs, 5.0, 0.0, False)
    return [train_object(small), train_object(big)], scene


def test_the_suppressed_look_alike_is_named_in_the_found_one_s_rivals(twins):
    models, scene = twins
    results = locate_all(scene.image, CAM, models)
    found = [r for r in results if r.found]
    lost = [r for r in results if not r.found]
    assert len(found) == 1 and len(lost) == 1, [r.reason for r in results]
    winner, rival = found[0], lost[0]
    assert rival.t is not None and rival.rivals is None  # it had a pose: suppressed, not unseen
    assert winner.rivals == [{"object": rival.object, "confidence": pytest.approx(rival.verification["confidence"], abs=1e-4),
                              "pose": {"t": list(rival.t), "q_wxyz": list(rival.q_wxyz)}}]
    assert repr(winner.object) in rival.reason
    # the two poses differ by the scale: the camera cannot tell them apart, the caller may
    ratio = np.linalg.norm(rival.t) / np.linalg.norm(winner.t)
    assert ratio == pytest.approx(SCALE if rival.object == "cube-m-big" else 1 / SCALE, rel=0.05)
    out = winner.to_json()
    assert out["rivals"][0]["object"] == rival.object and "rivals" not in rival.to_json()


def test_locate_object_all_json_carries_the_rivals(twins, tmp_path, capsys):
    models, scene = twins
    store = tmp_path / "store"
    for m in models:
        save_model(store, m)
    cam_file = tmp_path / "camera.json"
    cam_file.write_text(json.dumps({"width": CAM.width, "height": CAM.height, "fx": CAM.fx, "fy": CAM.fy,
                                    "cx": CAM.cx, "cy": CAM.cy}))
    cv2.imwrite(str(tmp_path / "scene.png"), scene.image)
    args = ["locate", "--object", "all", "--camera", str(cam_file), "--store", str(store), str(tmp_path / "scene.png")]
    assert main(args + ["--json"]) == 0
    line = json.loads(capsys.readouterr().out)
    (obj,) = line["objects"]
    assert [r["object"] for r in obj["rivals"]] == [({"cube-m", "cube-m-big"} - {obj["object"]}).pop()]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "rival" in text and obj["rivals"][0]["object"] in text
    shown = re.search(r"found \S+ .* confidence (\S+) .*\(rival: \S+ confidence (\S+)\)", text).groups()
    assert [len(c.split(".")[1]) for c in shown] == [3, 3]  # (the margin is thousandths: both to 0.001)

"""Several objects in one store, on the command line (trial 7): ``locate --object all --json``
says which objects it searched and which models it skipped (as ``POST /v1/pose`` does), the name
``all`` is refused for new training (``--object all`` could not reach it alone), and ``track
--object all`` says that track follows one object."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from quatrack.cli import main
from quatrack.testing import zoo as Z
from quatrack.viewsets.errors import SpecError, StoreError
from quatrack.viewsets.names import check_object_name
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.store import load_model, model_path, save_model
from quatrack.viewsets.train import TrainParams, train_object

CAM = Z.zoo_camera()


@pytest.fixture(scope="module")
def cube(tmp_path_factory):
    cv2.setRNGSeed(0)
    spec = load_spec(Z.write_spec("cube-m", tmp_path_factory.mktemp("cube"), 1))
    return train_object(spec, TrainParams(novel=None))


def _camera_file(tmp_path):
    path = tmp_path / "camera.json"
    path.write_text(json.dumps({"width": CAM.width, "height": CAM.height, "fx": CAM.fx, "fy": CAM.fy,
                                "cx": CAM.cx, "cy": CAM.cy}))
    return path


def test_locate_object_all_json_names_the_searched_and_the_skipped_models(cube, tmp_path, capsys):
    store = tmp_path / "store"
    save_model(store, cube)
    (store / "broken").mkdir()
    (store / "broken" / "manifest.json").write_text("{not json")
    cv2.imwrite(str(tmp_path / "empty.png"), np.full((CAM.height, CAM.width, 3), 90, np.uint8))
    code = main(["locate", "--object", "all", "--camera", str(_camera_file(tmp_path)), "--store", str(store),
                 str(tmp_path / "empty.png"), "--json"])
    out, err = capsys.readouterr()
    assert code == 0  # (unchanged: a skipped model is no failed image)
    line = json.loads(out)
    assert line["searched"] == ["cube-m"] and list(line["failed"]) == ["broken"]
    assert "broken" in line["failed"]["broken"] and "skipped" in err


def test_the_name_all_is_refused_for_training_but_a_stored_one_still_loads(cube, tmp_path):
    with pytest.raises(StoreError, match="reserved"):
        check_object_name("all", new=True)
    assert check_object_name("all") == "all" and check_object_name("all-boxes", new=True) == "all-boxes"
    spec = Z.write_spec("cube-m", tmp_path / "spec", 1)
    data = json.loads(spec.read_text())
    spec.write_text(json.dumps({**data, "name": "all"}))
    with pytest.raises(SpecError, match=r"field 'name': object name 'all' is reserved") as info:
        load_spec(spec)
    assert "\n" not in str(info.value)
    store = tmp_path / "store"  # a store from before: its "all" is listed and loaded as before
    from dataclasses import replace

    save_model(store, replace(cube, name="all"))
    assert model_path(store, "all").is_dir() and load_model(store, "all").name == "all"


def test_train_refuses_the_name_all_in_one_line(tmp_path, capsys):
    spec = Z.write_spec("cube-m", tmp_path / "spec", 1)
    data = json.loads(spec.read_text())
    data.pop("zoo")  # (the zoo's own notes: a warning line of its own)
    spec.write_text(json.dumps({**data, "name": "all"}))
    assert main(["train", str(spec), "--store", str(tmp_path / "store")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'all' is reserved" in err and not (tmp_path / "store" / "all").exists()


def test_track_object_all_says_that_track_follows_one_object(cube, tmp_path, capsys):
    store = tmp_path / "store"
    save_model(store, cube)
    args = ["track", "--object", "all", "--camera", str(_camera_file(tmp_path)), "--store", str(store),
            "--images", str(tmp_path / "*.png"), "--out", str(tmp_path / "poses.csv")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "track follows one object" in err and "no object named" not in err and err.count("\n") == 1
    assert not (tmp_path / "poses.csv").exists()

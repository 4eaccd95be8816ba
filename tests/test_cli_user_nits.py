"""Messages from a robotics engineer's trial with an object of their own (user report F8): a
binary file given as a camera, a tab-completed ``NAME/``, ``--novel-scales 0``, and the
single-object ``locate`` line without the confidence ``--object all`` gives."""

from __future__ import annotations

import shutil

import pytest

from conftest import EXAMPLE, box_frames_jpeg
from quatrack.cli import main
from quatrack.testing.scenes import example_store
from quatrack.viewsets.errors import StoreError
from quatrack.viewsets.names import check_object_name


@pytest.fixture(scope="module")
def base_store():
    return example_store()


def test_a_binary_camera_file_on_the_command_line(tmp_path, capsys):
    cam = tmp_path / "mesh.ply"
    cam.write_bytes(b"ply\nformat binary_little_endian 1.0\n\xa0\xff\x00\x81")
    frame = tmp_path / "f.jpg"
    frame.write_bytes(box_frames_jpeg(1)[0])
    assert main(["locate", "--object", "cookie-box", "--camera", str(cam), str(frame)]) == 2
    err = capsys.readouterr().err
    assert err == f"quatrack locate: error: {cam}: not a camera file (JSON or OpenCV YAML): it is not text\n"


def test_a_trailing_slash_is_hinted_and_models_commands_take_it(base_store, tmp_path, capsys):
    with pytest.raises(StoreError, match=r"drop the trailing '/'.*'cookie-box'"):
        check_object_name("cookie-box/")
    store = tmp_path / "store"
    shutil.copytree(base_store, store)
    assert main(["models", "show", "cookie-box/", "--store", str(store)]) == 0
    assert '"name"' in capsys.readouterr().out
    assert main(["models", "delete", "cookie-box/", "--store", str(store)]) == 0
    assert "deleted 'cookie-box'" in capsys.readouterr().out and not (store / "cookie-box").exists()


@pytest.mark.parametrize("option", ["--novel-scales", "--novel-views"])
def test_zero_is_refused_not_read_as_none(option, tmp_path, capsys):
    assert main(["train", str(EXAMPLE / "object.json"), "--store", str(tmp_path / "s"), option, "0"]) == 2
    err = capsys.readouterr().err
    assert option in err and "'none'" in err and not (tmp_path / "s").exists()


def test_locate_says_its_confidence(base_store, tmp_path, capsys):
    frame = tmp_path / "f.jpg"
    frame.write_bytes(box_frames_jpeg(1)[0])
    assert main(["locate", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"),
                 "--store", str(base_store), str(frame)]) == 0
    out = capsys.readouterr().out
    assert ": found" in out and (" confidence 0." in out or " confidence 1.00" in out)

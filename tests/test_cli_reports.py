"""What the command line tells its user beside its results (helper session h7): a refused
``track --init-pose``, an empty ``models list``, an object name the store does not hold, and
Python warnings raised under a command. The store is conftest's ``base_store`` (the cookie box
trained without synthetic views); frames are the box rendered on a seeded trajectory."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import EXAMPLE
from quatrack.cli import main
from quatrack.testing.scenes import Renderer
from quatrack.testing.sequences import clutter_background, compose, lively_trajectory
from quatrack.viewsets.camera import load_camera

NAME = "cookie-box"


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Three rendered frames of the box (PNG files) and its true poses."""
    root = tmp_path_factory.mktemp("frames")
    camera = load_camera(EXAMPLE / "camera.json")
    renderer = Renderer.from_spec(EXAMPLE / "object.json")
    trajectory = lively_trajectory(renderer, seed=3)
    bg, rng = clutter_background(1), np.random.default_rng(0)
    poses = [trajectory.pose(k / 30) for k in range(3)]
    for k, p in enumerate(poses):
        cv2.imwrite(str(root / f"f{k:03d}.png"), compose(renderer, camera, p, bg, rng))
    return root, poses


def _track(store, root, pose_file, out, fmt="csv"):
    return main(["track", "--object", NAME, "--camera", str(EXAMPLE / "camera.json"), "--store", str(store),
                 "--images", str(root / "*.png"), "--fps", "30", "--init-pose", str(pose_file), "--out", str(out),
                 "--format", fmt, "--quiet"])


def test_a_refused_init_pose_is_said_once_on_stderr_with_its_reason(base_store, frames, tmp_path, capsys):
    """A pose given camera → object (the inverse): the CSV said lost, stderr nothing; the reason
    was in --format jsonl rows only."""
    root, poses = frames
    R, t = poses[0].R, poses[0].t
    pose_file = tmp_path / "inverted.json"
    pose_file.write_text(json.dumps({"R": R.T.tolist(), "t": (-R.T @ t).tolist()}))
    assert _track(base_store, root, pose_file, tmp_path / "poses.jsonl", "jsonl") == 0
    first = json.loads((tmp_path / "poses.jsonl").read_text().splitlines()[0])
    assert first["status"] == "lost" and first["reason"].startswith("given pose")
    why = first["reason"].removeprefix("given pose refused: ").removeprefix("given pose: ")
    capsys.readouterr()
    assert _track(base_store, root, pose_file, tmp_path / "poses.csv") == 0
    err = [x for x in capsys.readouterr().err.splitlines() if "--init-pose" in x]
    assert len(err) == 1, err
    assert err[0].startswith(f"quatrack track: warning: --init-pose {pose_file}: the pose was refused at frame 0 ("
                             f"{why}); the object is searched for by recognition instead"), err


def test_an_accepted_init_pose_is_not_warned_of(base_store, frames, tmp_path, capsys):
    root, poses = frames
    pose_file = tmp_path / "pose.json"
    pose_file.write_text(json.dumps({"rvec": poses[0].rvec.tolist(), "tvec": poses[0].t.tolist()}))
    assert _track(base_store, root, pose_file, tmp_path / "poses.csv") == 0
    assert (tmp_path / "poses.csv").read_text().splitlines()[1].split(",")[2] == "init"
    assert "--init-pose" not in capsys.readouterr().err


@pytest.mark.parametrize("exists", [True, False])
def test_models_list_of_an_empty_store_says_so_on_stderr(tmp_path, capsys, exists):
    """It printed nothing, exit 0: an empty store and a typo in --store looked alike. Stdout
    stays empty (one row per object, for scripts)."""
    store = tmp_path / "models"
    if exists:
        store.mkdir()
    assert main(["models", "list", "--store", str(store)]) == 0
    out, err = capsys.readouterr()
    assert out == ""
    assert err == (f"quatrack models: no trained object in {store}{'' if exists else ' (no such folder)'}; "
                   f"train one with `quatrack train SPEC.json --store {store}`\n")


def test_models_list_of_a_store_with_objects_says_nothing_more(base_store, capsys):
    assert main(["models", "list", "--store", str(base_store)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"{NAME}\t") and err == ""


@pytest.mark.parametrize("command", ["locate", "track", "show", "delete"])
def test_an_unknown_object_lists_the_store_and_the_nearest_name(base_store, frames, tmp_path, capsys, command):
    """It said "no object named 'cookie-bx' in STORE" alone, for every command naming an object."""
    root, _ = frames
    common = ["--camera", str(EXAMPLE / "camera.json"), "--store", str(base_store)]
    argv = {"locate": ["locate", str(root / "f000.png"), "--object", "cookie-bx", *common],
            "track": ["track", "--images", str(root / "*.png"), "--object", "cookie-bx", "--out",
                      str(tmp_path / "poses.csv"), *common],
            "show": ["models", "show", "cookie-bx", "--store", str(base_store)],
            "delete": ["models", "delete", "cookie-bx", "--store", str(base_store)]}[command]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.endswith(f": error: no object named 'cookie-bx' in {base_store}; did you mean 'cookie-box'? "
                        f"(it holds cookie-box)\n") and err.count("\n") == 1, err
    assert not (tmp_path / "poses.csv").exists()


def test_the_unknown_object_message_says_an_empty_or_missing_store(tmp_path):
    from quatrack.viewsets.store import unknown_object

    assert str(unknown_object(tmp_path / "nowhere", "box")) == f"no object named 'box' in {tmp_path / 'nowhere'} (no such folder)"
    assert str(unknown_object(tmp_path, "box")) == f"no object named 'box' in {tmp_path} (it holds none)"


def test_the_nearest_name_is_told_apart_from_none_near():
    from quatrack.viewsets.store import names_hint

    names = ["cookie-box", "mug", "tea-tin"]
    assert names_hint("Cookie-Box", names) == "; did you mean 'cookie-box'? (it holds cookie-box, mug, tea-tin)"
    assert names_hint("mugg", names) == "; did you mean 'mug'? (it holds cookie-box, mug, tea-tin)"
    assert names_hint("gearwheel", names) == " (it holds cookie-box, mug, tea-tin)"
    many = [f"obj{k:02d}" for k in range(20)]
    assert names_hint("zzz", many, shown=3) == " (it holds obj00, obj01, obj02, ... (20 in all))"


def test_a_python_warning_under_a_command_is_one_line_naming_it(base_store, tmp_path, capsys, monkeypatch):
    """A 12-bit PNG given to `locate`: recognition.images warns (BitDepthWarning), which printed in
    Python's default format — the library's file and line, the class, and a line of its code."""
    import warnings

    from quatrack.recognition import images

    monkeypatch.setattr(images, "_depth_warned", False)  # (warned once a process)
    camera = load_camera(EXAMPLE / "camera.json")
    png = tmp_path / "raw12.png"
    pixels = np.random.default_rng(0).integers(0, 4000, (camera.height, camera.width), dtype=np.uint16)
    assert cv2.imwrite(str(png), pixels)
    before = warnings.showwarning
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # (whatever filters the test run has, the warning is shown)
        rc = main(["locate", str(png), "--object", NAME, "--camera", str(EXAMPLE / "camera.json"),
                   "--store", str(base_store)])
    assert rc == 0 and warnings.showwarning is before  # (the formatter is the command's only)
    err = capsys.readouterr().err.splitlines()
    warned = [x for x in err if "16-bit" in x]
    assert len(warned) == 1 and warned[0].startswith("quatrack locate: warning: a 16-bit image whose values all lie "
                                                     "below 4096"), err
    assert "BitDepthWarning" not in "\n".join(err) and ".py:" not in "\n".join(err), err


@pytest.mark.parametrize("exists", [True, False])
def test_locate_all_in_an_empty_or_missing_store_says_which(frames, tmp_path, capsys, exists):
    root, _ = frames
    store = tmp_path / "models"
    if exists:
        store.mkdir()
    assert main(["locate", str(root / "f000.png"), "--object", "all", "--camera", str(EXAMPLE / "camera.json"),
                 "--store", str(store)]) == 2
    assert capsys.readouterr().err == (f"quatrack locate: error: no trained object in {store}"
                                       f"{'' if exists else ' (no such folder)'}\n")


@pytest.mark.parametrize("name", ["my box", "a/b", "box?x", ".hidden"])
def test_demo_refuses_a_name_no_store_can_hold_before_any_connection(tmp_path, capsys, name):
    """With --url the name went into the WebSocket's URL: "the server refused: 403 http_error:
    HTTP 403" (or 400 "Invalid HTTP request received."). Nothing listens at this URL: the name
    is refused before any connection."""
    from quatrack.service.server import free_port

    assert main(["demo", "--url", f"http://127.0.0.1:{free_port()}", "--object", name,
                 "--out-dir", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"quatrack demo: error: --object: invalid object name {name!r}: use 1-64 letters") \
        and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_a_warning_on_a_terminal_clears_the_progress_line_first():
    """`track`'s progress line is drawn without a newline: a warning under it was appended to it."""
    import io

    from quatrack.cli import _warning_line

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    tty, log = Terminal(), io.StringIO()
    show = _warning_line("track")
    for f in (tty, log):
        f.write("\rtracking: 10 frames")
        show(UserWarning("two\nlines"), UserWarning, "x.py", 1, file=f)
    assert tty.getvalue() == "\rtracking: 10 frames\r\x1b[Kquatrack track: warning: two lines\n"
    assert log.getvalue() == "\rtracking: 10 frames" + "quatrack track: warning: two lines\n"  # (a log: no control codes)


def test_a_models_own_folder_given_as_the_store_is_said_so(base_store, frames, capsys):
    """`--store STORE/cookie-box` (the model's folder, not its store) read as an empty store:
    `models list` printed nothing, `locate` said only "no object named 'cookie-box' in ..."."""
    root, _ = frames
    folder = base_store / NAME
    note = f" (the folder of object {NAME!r} itself: its store is {base_store})"
    assert main(["models", "list", "--store", str(folder)]) == 0
    assert capsys.readouterr() == ("", f"quatrack models: no trained object in {folder}{note}\n")
    assert main(["locate", str(root / "f000.png"), "--object", NAME, "--camera", str(EXAMPLE / "camera.json"),
                 "--store", str(folder)]) == 2
    assert capsys.readouterr().err == f"quatrack locate: error: no object named {NAME!r} in {folder}{note}\n"
    assert main(["locate", str(root / "f000.png"), "--object", "all", "--camera", str(EXAMPLE / "camera.json"),
                 "--store", str(folder)]) == 2
    assert capsys.readouterr().err == f"quatrack locate: error: no trained object in {folder}{note}\n"

"""The command line as a process: how it starts and how it ends (exit status, one-line errors)."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest



def _run(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=120, **kw)


def test_python_m_quatrack_cli_reports_user_errors_in_one_line(tmp_path):
    # run as ``-m quatrack.cli`` the module is __main__, a second copy whose UserError track_cli.py
    # does not raise: the error came out as a traceback, exit 1
    r = _run("-m", "quatrack.cli", "track", "--object", "x", "--camera", "c.json", "--video", "v.mp4",
             "--out", str(tmp_path / "o.csv"), "--relocate-every", "0", cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().startswith("quatrack track: error: --relocate-every") and "\n" not in r.stderr.strip()


def test_a_reader_that_stops_reading_is_no_error():
    # ``quatrack … | head -1``: the command's output pipe closes early; it stops quietly (exit 1,
    # Python's own convention), not "error: [Errno 32] Broken pipe"
    script = ("import sys, quatrack.cli as c\n"
              "name, add, _ = c.COMMANDS['models']\n"
              "def talk(args):\n"
              "    for _ in range(10000):\n"
              "        print('x' * 1000)\n"
              "    return 0\n"
              "c.COMMANDS['models'] = (name, add, talk)\n"
              "sys.exit(c.main(['models', 'list']))\n")
    p = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.read(10)
    p.stdout.close()  # (the reader goes)
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 1 and err == "", err


def test_the_service_address_is_checked_before_anything_starts():
    from quatrack.service.cli import check_address

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ValueError, match=f"--port {port}: cannot listen there.*another server"):
            check_address("127.0.0.1", port)
    check_address("127.0.0.1", port)  # free again: no error
    with pytest.raises(ValueError, match="--host no-such-host.invalid: cannot resolve it"):
        check_address("no-such-host.invalid", port)


def test_a_store_under_a_file_is_refused_before_training(tmp_path, capsys):
    from quatrack.cli import main
    from quatrack.testing.scenes import EXAMPLE

    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    assert main(["train", str(EXAMPLE / "object.json"), "--store", str(afile / "sub")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"quatrack train: error: --store {afile / 'sub'}: {afile} is a file, not a folder", err


def test_demo_refuses_an_overlay_on_its_input_video(tmp_path, capsys):
    import shutil

    from quatrack.cli import main
    from quatrack.testing.scenes import EXAMPLE

    video = tmp_path / "in.mp4"
    shutil.copy(EXAMPLE / "box.mp4", video)
    before = video.read_bytes()
    rc = main(["demo", "--url", "http://127.0.0.1:9", "--video", str(video), "--camera", str(EXAMPLE / "camera.json"),
               "--out-dir", str(tmp_path / "out"), "--overlay", str(video), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "--overlay" in err and "is the input" in err and "\n" not in err, err
    assert video.read_bytes() == before and not (tmp_path / "out").exists()


def test_demo_refuses_an_output_in_a_missing_folder_before_streaming(tmp_path, capsys):
    # `--out sub/poses.csv`: the whole video was streamed (a server started) before the write failed
    from quatrack.cli import main
    from quatrack.testing.scenes import EXAMPLE

    rc = main(["demo", "--url", "http://127.0.0.1:9", "--camera", str(EXAMPLE / "camera.json"),
               "--out-dir", str(tmp_path / "out"), "--out", "sub/poses.csv", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("quatrack demo: error: --out sub/poses.csv: the folder") and "\n" not in err, err
    assert "does not exist" in err and "no server answers" not in err and not (tmp_path / "out").exists()


def test_library_inputs_of_the_wrong_kind_say_what_is_expected():
    import numpy as np

    from quatrack.client import Client, base_urls
    from quatrack.recognition.images import ImageError, to_bgr8
    from quatrack.recognition.locate import locate
    from quatrack.recognition.video import Tracker, TrackerParams
    from quatrack.testing.scenes import EXAMPLE, example_model
    from quatrack.viewsets.camera import load_camera
    from quatrack.viewsets.errors import StoreError

    camera, model = load_camera(EXAMPLE / "camera.json"), example_model()
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    with pytest.raises(ImageError, match="expected an image array.*cv2.imread"):
        to_bgr8("frame.png")
    with pytest.raises(TypeError, match="camera: a PinholeCamera"):
        locate(image, {"fx": 600}, model)
    with pytest.raises(TypeError, match="model: an ObjectModel"):
        locate(image, camera, "cookie-box")
    with pytest.raises(TypeError, match="camera: a PinholeCamera"):
        Tracker(model, None)
    with pytest.raises(ValueError, match="not a string"):
        TrackerParams(sources="edges")
    with pytest.raises(ValueError, match="sigma_px"):
        TrackerParams(sigma_px=0.0)
    with pytest.raises(ValueError, match="port must be a number"):
        base_urls("http://127.0.0.1:abc")
    with Client("http://127.0.0.1:9", token="t") as c:  # (no request is made: the name is refused first)
        for bad in ("../x", "a?b=1"):
            with pytest.raises(StoreError, match="invalid object name"):
                c.pose(image, camera, object=bad)


def test_library_settings_and_times_of_the_wrong_kind_name_the_argument():
    # a dict for params was AttributeError 'max_pixels' / 'motion_model' deep inside; sigma_px="1"
    # numpy's "ufunc 'isfinite' not supported"; time_s "abc" or None float()'s own message
    import numpy as np

    from quatrack.recognition.locate import LocateParams, locate, locate_all
    from quatrack.recognition.video import Tracker, TrackerParams
    from quatrack.testing.scenes import EXAMPLE, example_model
    from quatrack.viewsets.camera import load_camera

    camera, model = load_camera(EXAMPLE / "camera.json"), example_model()
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    with pytest.raises(TypeError, match="params: a LocateParams"):
        locate(image, camera, model, {"use_window": False})
    with pytest.raises(TypeError, match="params: a TrackerParams"):
        Tracker(model, camera, {"motion_model": "m1"})
    for bad in ("4000000", 0, 4e6):  # (a string: "'<=' not supported" in prepare_image; 0 shrank images to 32 px)
        with pytest.raises(ValueError, match="max_pixels must be a whole number"):
            LocateParams(max_pixels=bad)
    with pytest.raises(TypeError, match="models: a list of ObjectModels"):  # (was "has no len()")
        locate_all(image, camera, model)
    with pytest.raises(TypeError, match="model: an ObjectModel"):  # (was AttributeError 'viewsets')
        locate_all(image, camera, [model, "cookie-box"])
    for field in ("sigma_px", "relocate_interval_s"):
        with pytest.raises(ValueError, match=field):
            TrackerParams(**{field: "1"})
    tracker = Tracker(model, camera)
    for bad in ("abc", None, float("nan")):
        with pytest.raises(ValueError, match="time_s must be"):
            tracker.step(image, bad)
        with pytest.raises(ValueError, match="time_s must be"):
            tracker.skip(bad, "unreadable")
    with pytest.raises(ValueError, match="time_s must be"):
        tracker.init_pose([0, 0, 70], [1, 0, 0, 0], time_s="later")


def test_bench_zoo_options_need_zoo(capsys):
    from quatrack.cli import main

    assert main(["bench", "locate", "--zoo-scenes", "3"]) == 2
    assert "need --zoo" in capsys.readouterr().err


def test_metrics_of_a_one_worker_server(tmp_path):
    # with one worker the app runs in `quatrack serve`'s own process: prometheus_client, imported
    # there before the multiprocess directory was set, kept its counters in memory while /metrics
    # read the empty directory — every metric but one was missing
    import os

    import httpx

    from quatrack.service.server import free_port
    from quatrack.testing.loopback import wait_for_http
    from quatrack.testing.scenes import example_store

    port = free_port()
    env = {**os.environ, "XDG_DATA_HOME": str(tmp_path), "HOME": str(tmp_path)}
    proc = subprocess.Popen([sys.executable, "-m", "quatrack", "serve", "--store", str(example_store()), "--port", str(port),
                             "--workers", "1"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        url = f"http://127.0.0.1:{port}"
        wait_for_http(f"{url}/readyz", "quatrack serve", 60.0, alive=lambda: proc.poll() is None)  # (models load first)
        assert httpx.get(f"{url}/v1/objects", timeout=10).status_code == 200
        text = httpx.get(f"{url}/metrics", timeout=10).text
        for name in ("quatrack_http_requests_total", "quatrack_models_loaded", "quatrack_ws_sessions_active"):
            assert name in text, (name, text[:500])
    finally:
        proc.terminate()
        proc.wait(timeout=30)


@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_server_stopped_by_sigterm_removes_its_run_directory(tmp_path, workers):
    # uvicorn re-raises the SIGTERM it caught after shutting down: with one worker that killed
    # `quatrack serve` before its finally, and the quatrack-run-* folder stayed in the temp dir
    import os
    import signal

    from quatrack.service.server import free_port
    from quatrack.testing.loopback import wait_for_http
    from quatrack.testing.scenes import example_store

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    port = free_port()
    env = {**os.environ, "XDG_DATA_HOME": str(tmp_path), "HOME": str(tmp_path), "TMPDIR": str(tmp)}
    env.pop("QUATRACK_RUN_DIR", None)
    proc = subprocess.Popen([sys.executable, "-m", "quatrack", "serve", "--store", str(example_store()), "--port",
                             str(port), "--workers", workers], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        wait_for_http(f"http://127.0.0.1:{port}/readyz", "quatrack serve", 60.0, alive=lambda: proc.poll() is None)
        assert [p.name for p in tmp.iterdir() if p.name.startswith("quatrack-run-")], "no run directory made"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) in (0, 143, -signal.SIGTERM)  # (1 worker: 143, several: 0, as before)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
    assert not [p.name for p in tmp.iterdir() if p.name.startswith("quatrack-run-")]


def test_ctrl_c_while_trimesh_imports_is_not_swallowed(tmp_path):
    """trimesh wraps its optional imports (scipy: seconds on a cold disk) in ``except
    BaseException``: a Ctrl-C pressed meanwhile was swallowed and training went on, replacing the
    model. A stand-in trimesh that swallows the same way: loading a mesh must end interrupted."""
    fake = tmp_path / "trimesh"
    fake.mkdir()
    (fake / "__init__.py").write_text(
        "import os, signal\n"
        "try:\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    for _ in range(100000):\n"
        "        pass\n"
        "except BaseException:  # as trimesh does around its optional imports\n"
        "    pass\n")
    script = ("import sys\n"
              f"sys.path.insert(0, {str(tmp_path)!r})\n"
              "from quatrack.viewsets.mesh import load_mesh\n"
              "try:\n"
              "    load_mesh('no-such-mesh.ply')\n"
              "except KeyboardInterrupt:\n"
              "    print('interrupted')\n"
              "except ValueError as exc:\n"
              "    print('went on:', exc)\n")
    r = _run("-c", script, cwd=tmp_path)
    assert r.stdout.strip() == "interrupted", r.stdout + r.stderr


def test_ctrl_c_while_the_commands_load_is_one_line(monkeypatch, capsys):
    """Building the parser imports the commands' modules (a tenth of a second): a Ctrl-C then
    was a KeyboardInterrupt traceback, not the 'interrupted' line of a Ctrl-C a moment later."""
    import quatrack.cli as cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    try:
        status = cli.main(["models", "list"])
    except KeyboardInterrupt:
        pytest.fail("the KeyboardInterrupt left main(): a traceback")
    assert status == 130
    assert capsys.readouterr().err == "quatrack: interrupted\n"


def test_bench_serve_refuses_an_object_not_in_the_store_and_a_negative_stagger(tmp_path, capsys):
    # every stream was refused by the server: a table of NaN and exit status 0; a negative
    # --stagger-s ran as a burst
    from quatrack.cli import main

    empty = tmp_path / "store"
    empty.mkdir()
    assert main(["bench", "serve", "--store", str(empty), "--replicas", "no", "--clients", "1", "--workers", "1",
                 "--frames", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("quatrack bench: error: --object: no object named 'cookie-box' in") and "\n" not in err, err
    assert main(["bench", "serve", "--stagger-s", "-1", "--replicas", "no"]) == 2
    assert "--stagger-s" in capsys.readouterr().err
    assert main(["bench", "serve", "--rest-concurrency", "0", "--replicas", "no"]) == 2  # (reported 40 requests, none sent)
    assert "--rest-concurrency must be between 1 and 256" in capsys.readouterr().err


def test_bench_options_checked_before_the_run(tmp_path, capsys):
    # bench locate --sheet x.txt ran the whole benchmark, then cv2.imwrite's traceback; a folder
    # under a file failed after it with "[Errno 17] File exists"; --first-seed -1 was numpy's
    # "expected non-negative integer", naming no option
    from quatrack.cli import main

    (tmp_path / "f").write_text("")
    for argv, said in ((["locate", "--sheet", str(tmp_path / "x.txt")], "--sheet must name a .png file"),
                       (["locate", "--sheet", str(tmp_path / "f" / "x.png")], "is a file, not a folder"),
                       (["track", "--sheet", str(tmp_path / "f" / "x.png")], "is a file, not a folder"),
                       (["ude-cube", "--first-seed", "-1"], "--first-seed must be >= 0"),
                       (["locate", "--seed", "-1"], "--seed must be >= 0"),
                       (["locate", "--zoo", "--seed", "-1"], "--seed must be >= 0")):
        assert main(["bench", *argv]) == 2, argv
        err = capsys.readouterr().err.strip()
        assert said in err and "\n" not in err, err


@pytest.mark.parametrize("argv, said", [
    (["track-zoo", "--sequences", ""], "--sequences: give zoo object names separated by commas, got ''"),
    (["track-zoo", "--sequences", "a,,b"], "--sequences: give zoo object names"),
    (["edge-judge", "--sequences", ","], "--sequences: give zoo object names"),
    (["locate", "--zoo", "--zoo-objects", ""], "--zoo-objects: give zoo object names"),
    (["locate", "--zoo-objects", ""], "need --zoo"),
    (["serve", "--workers", "", "--replicas", "no"], "--workers: numbers between 1 and 64"),
    (["serve", "--clients", "", "--replicas", "no"], "--clients: numbers between 1 and 64"),
    (["track-ab", "nonsense"], "write NAME=JSON"),
])
def test_bench_empty_selections_are_refused(capsys, argv, said):
    # `--sequences ''` (an empty shell variable) ran all six walks, ~9 min; `serve --workers ''` the
    # default worker counts; track-ab read the video and trained the object before refusing a variant
    from quatrack.cli import main

    assert main(["bench", *argv]) == 2, argv
    err = capsys.readouterr().err.strip()
    assert said in err and "\n" not in err, err

"""``quatrack train SPEC...``: several objects in one call, in local processes and as tasks on a
Ray cluster (a real head node started by the test on loopback), each written atomically into one
store. Training uses the registered view only (``--novel-views none --novel-scales none``) to
stay cheap; what is checked is that each model lands whole and comes from its own spec."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from quatrack.cli import main
from quatrack.service.server import free_port
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.store import list_models, load_manifest, load_model

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "cookie-box"
CHEAP = ["--novel-views", "none", "--novel-scales", "none"]


def renamed_spec(tmp: Path, name: str) -> Path:
    """The example spec under another object name, its files referred to by absolute paths."""
    d = json.loads((EXAMPLE / "object.json").read_text())
    d["name"] = name
    d["mesh"] = str(EXAMPLE / d["mesh"])
    for v in d["views"]:
        for key in ("image", "mask"):
            if v.get(key):
                v[key] = str(EXAMPLE / v[key])
    path = tmp / f"{name}.json"
    path.write_text(json.dumps(d))
    return path


def check_store(store: Path, specs: list[Path]) -> None:
    assert sorted(list_models(store)) == sorted(load_spec(s).name for s in specs)
    for s in specs:
        spec = load_spec(s)
        assert load_manifest(store, spec.name)["spec"]["sha256"] == spec.checksum
        assert len(load_model(store, spec.name).viewsets) >= 1
    assert not [p for p in store.iterdir() if p.name.startswith(".")]  # no temporary left behind


def test_several_specs_in_parallel_processes(tmp_path, capsys):
    specs = [EXAMPLE / "object.json", renamed_spec(tmp_path, "box-two"), renamed_spec(tmp_path, "box-three")]
    store = tmp_path / "store"
    assert main(["train", *map(str, specs), "--store", str(store), "--jobs", "2", *CHEAP]) == 0
    check_store(store, specs)
    out = capsys.readouterr().out
    assert "3 of 3 objects trained locally" in out
    # the same call again with --skip-existing trains nothing
    assert main(["train", *map(str, specs), "--store", str(store), "--skip-existing", *CHEAP]) == 0
    out = capsys.readouterr().out
    assert out.count("nothing to do") == 3  # (and not counted as trained: "3 of 3 objects trained")
    assert "0 of 3 objects trained locally" in out and "; 3 already trained from their spec (--skip-existing)\n" in out, out


def test_a_bad_spec_stops_the_batch_before_any_training(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    store = tmp_path / "store"
    assert main(["train", str(EXAMPLE / "object.json"), str(bad), "--store", str(store), *CHEAP]) == 2
    err = capsys.readouterr().err
    assert "bad.json" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not store.exists() or list_models(store) == []
    # two specs of one object name are refused too
    assert main(["train", str(EXAMPLE / "object.json"), str(EXAMPLE / "object.json"), "--store", str(store)]) == 2
    assert "both define object" in capsys.readouterr().err
    # a spec whose mesh (or photo) path has a typo stops the batch as well (it trained the others)
    for field in ("mesh", "image"):
        typo = renamed_spec(tmp_path, f"typo-{field}")
        d = json.loads(typo.read_text())
        if field == "mesh":
            d["mesh"] = str(tmp_path / "no_such_mesh.ply")
        else:
            d["views"][0]["image"] = str(tmp_path / "no_such_photo.jpg")
        typo.write_text(json.dumps(d))
        assert main(["train", str(EXAMPLE / "object.json"), str(typo), "--store", str(store), *CHEAP]) == 2
        err = capsys.readouterr().err
        assert "no_such_" in err and "file not found" in err and len(err.strip().splitlines()) == 1, err
        assert not store.exists() or list_models(store) == []


def test_several_specs_warn_as_one_does(tmp_path, capsys):
    """A registered rotation transposed is warned of when trained with other specs too (the
    warnings of training and of the registered poses were dropped in the worker processes),
    naming the spec; the good spec gets none."""
    import cv2
    import numpy as np

    bad = renamed_spec(tmp_path, "box-transposed")
    d = json.loads(bad.read_text())
    pose = d["views"][0]["pose"]
    R = cv2.Rodrigues(np.array(pose["rvec"], float))[0]
    d["views"][0]["pose"] = {"R": R.T.tolist(), "t": pose["tvec"]}
    bad.write_text(json.dumps(d))
    store = tmp_path / "store"
    assert main(["train", str(EXAMPLE / "object.json"), str(bad), "--store", str(store), "--jobs", "2", *CHEAP]) == 0
    err = [x for x in capsys.readouterr().err.splitlines() if "warning" in x]
    assert len(err) == 1 and str(bad) in err[0], err
    assert "view 0: the mesh's edges at its pose lie on the photo's edges for" in err[0]


@pytest.fixture()
def ray_head():
    """A Ray head node on loopback, started for this test and stopped after it."""
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'quatrack[ray]')")
    ray_bin = Path(sys.executable).with_name("ray")
    port = free_port()
    temp = tempfile.mkdtemp(prefix="qt-ray-")  # short: Ray's unix socket paths must stay < 108 bytes
    proc = subprocess.Popen(
        [str(ray_bin), "start", "--head", "--port", str(port), "--num-cpus", "2", "--include-dashboard=false",
         "--node-ip-address", "127.0.0.1", "--object-store-memory", str(100 * 1024 * 1024), "--temp-dir", temp,
         "--block", "--disable-usage-stats"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    address = f"127.0.0.1:{port}"
    probe = "import ray, sys; ray.init(address=sys.argv[1], logging_level='ERROR'); ray.shutdown()"
    deadline = time.monotonic() + 240  # generous: a busy machine
    try:
        while subprocess.run([sys.executable, "-c", probe, address], capture_output=True).returncode != 0:
            assert proc.poll() is None, "ray start exited"
            assert time.monotonic() < deadline, "the Ray head did not come up"
            time.sleep(1)
        yield address
    finally:
        proc.send_signal(signal.SIGTERM)  # ray start stops its own processes in order
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # whatever is left of that process group
        except ProcessLookupError:
            pass
        proc.wait(timeout=30)


@pytest.mark.slow
def test_specs_as_tasks_on_a_ray_cluster(tmp_path, ray_head):
    specs = [EXAMPLE / "object.json", renamed_spec(tmp_path, "box-ray")]
    store = tmp_path / "shared-store"
    r = subprocess.run([sys.executable, "-m", "quatrack", "train", *map(str, specs), "--store", str(store),
                        "--ray", ray_head, *CHEAP], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"2 of 2 objects trained on Ray ({ray_head})" in r.stdout
    check_store(store, specs)


def test_an_unreachable_ray_address_is_one_line(tmp_path, capsys):
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'quatrack[ray]')")
    port = free_port()  # nobody listens there
    assert main(["train", str(EXAMPLE / "object.json"), "--store", str(tmp_path / "s"), "--ray", f"127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err.strip()
    assert f"--ray 127.0.0.1:{port}" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "s").exists() or list_models(tmp_path / "s") == []


def test_ctrl_c_ends_the_worker_processes_and_trains_nothing_queued(tmp_path, monkeypatch):
    """Ctrl-C while several specs train: the parent stopped waiting, but leaving the pool waited
    for every spec, queued ones too, each trained and stored after the user's Ctrl-C (and the
    workers, taking the Ctrl-C themselves, printed their tracebacks). Now the workers ignore it
    and the parent ends them: nothing is stored after the Ctrl-C."""
    import quatrack.viewsets.batch as batch
    from quatrack.viewsets.train import TrainParams

    def ctrl_c(futures):
        raise KeyboardInterrupt
        yield  # (a generator, as as_completed)

    monkeypatch.setattr(batch, "as_completed", ctrl_c)
    specs = [str(renamed_spec(tmp_path, f"box-{i}")) for i in range(3)]
    store = tmp_path / "store"
    store.mkdir()
    t0 = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        batch._local(specs, str(store), TrainParams(novel=None), True, 2, None)
    assert time.perf_counter() - t0 < 5
    time.sleep(2)  # (a worker left running would store a model meanwhile)
    assert list_models(store) == []

"""``quatrack serve --workers 2``: real worker processes, a session limit that holds for the whole
server, metrics merged over the workers (parsed by prometheus-client's own parser), and the
settings table of the README generated from the Settings class."""

from __future__ import annotations

import json
import multiprocessing
import os
import re
import signal
import time
from pathlib import Path

import httpx
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from conftest import box_frames_jpeg, metric_samples, sessions_active
from quatrack.testing.scenes import example_store
from quatrack.service.server import BackgroundServer, ServeProcess
from quatrack.service.settings import Settings, env_name, settings_table
from quatrack.service.workers import ReadyBoard, SlotLimiter

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "cookie-box"
CAMERA = json.loads((EXAMPLE / "camera.json").read_text())


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    log = tmp_path_factory.mktemp("serve") / "serve.log"
    srv = ServeProcess(example_store(), workers=2, env={env_name("max_sessions"): "2", env_name("threads"): "1"},
                       log_path=log)
    with srv:
        yield srv


def test_workers_are_processes_with_a_global_session_limit(server):
    assert len(server.worker_pids()) == 2  # two uvicorn worker processes under one supervisor
    frames = box_frames_jpeg(3)
    url = f"{server.ws_url}/v1/objects/cookie-box/track"
    answers = 0
    # the limit (2) holds for the whole server, whichever workers the kernel gave the connections to
    with connect(url, open_timeout=60) as a, connect(url, open_timeout=60) as b:
        for ws in (a, b):
            ws.send(json.dumps(CAMERA))
        for k, data in enumerate(frames):
            for ws in (a, b):
                ws.send(json.dumps({"type": "frame", "time_s": k / 30}))
                ws.send(data)
                msg = json.loads(ws.recv(timeout=120))
                assert msg["type"] == "pose" and msg["frame"] == k, msg
                answers += 1
        with pytest.raises(InvalidStatus) as exc:
            with connect(url, open_timeout=60):
                pass
        assert exc.value.response.status_code == 503
        assert sessions_active(server.url) == 2
    # frames of both sessions are counted, whichever worker served them (multiprocess mode)
    m = metric_samples(httpx.get(f"{server.url}/metrics", timeout=60).text)
    assert m[("quatrack_ws_frames_total", frozenset({("result", "processed")}))] == answers
    statuses = sum(v for (name, labels), v in m.items() if name == "quatrack_track_frames_total")
    assert statuses == answers
    assert any(name == "quatrack_track_stage_seconds_count" for name, _ in m)
    assert m[("quatrack_models_loaded", frozenset())] == 1
    # each worker loaded the model once; the counters of both are summed
    assert m[("quatrack_model_loads_total", frozenset({("result", "ok")}))] == 2
    assert m.get(("quatrack_model_loads_total", frozenset({("result", "failed")})), 0) == 0
    # the sessions are gone: their slots are free again (bounded wait: closing is asynchronous)
    deadline = time.monotonic() + 30
    while sessions_active(server.url) != 0:
        assert time.monotonic() < deadline, "sessions still counted after their sockets closed"
        time.sleep(0.1)


def test_health_answers_while_tracking(server):
    """/healthz and /readyz are answered (by either worker) while both sessions track."""
    frames = box_frames_jpeg(2)
    url = f"{server.ws_url}/v1/objects/cookie-box/track"
    with connect(url, open_timeout=60) as ws:
        ws.send(json.dumps(CAMERA))
        for k, data in enumerate(frames):
            ws.send(data)
            for _ in range(3):
                assert httpx.get(f"{server.url}/healthz", timeout=60).status_code == 200
            assert json.loads(ws.recv(timeout=120))["frame"] == k


def _hold_slot(directory: str, conn) -> None:
    lim = SlotLimiter(Path(directory), 2)
    conn.send(lim.try_open() is not None)
    time.sleep(120)  # until killed (no multiprocessing.Event: a process killed inside its wait()
    # would leave the parent's set() waiting forever for its acknowledgement)


def test_slots_are_freed_when_a_worker_dies(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    parent, child_end = ctx.Pipe()
    child = ctx.Process(target=_hold_slot, args=(str(tmp_path), child_end), daemon=True)
    child.start()
    try:
        assert parent.poll(120) and parent.recv() is True
        lim = SlotLimiter(tmp_path, 2)
        assert lim.count() == 1
        sid = lim.try_open()
        assert sid is not None and lim.count() == 2
        assert lim.try_open() is None  # full: one slot here, one in the other process
        os.kill(child.pid, signal.SIGKILL)  # a crashed worker...
        child.join(60)
        assert lim.count() == 1  # ...holds nothing: the kernel dropped its lock
        assert lim.try_open() is not None
    finally:
        if child.is_alive():
            child.kill()
            child.join(60)


def _ready_worker(directory: str, conn) -> None:
    ReadyBoard(Path(directory), 2).mark_ready()
    conn.send(True)
    time.sleep(120)  # until killed


def _wait(pred, what: str, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def test_readyz_waits_for_every_worker(tmp_path):
    """With 2 workers, /readyz says ready only when both have loaded their models, whichever one
    answers: here one real worker (the app, in a thread) and a stand-in for the other (a process
    that reports ready through the run directory, then dies)."""
    run = tmp_path / "run"
    board = ReadyBoard(run / "ready", 2)
    settings = Settings(store=example_store(), workers=2, threads=1, run_dir=run, model_poll_s=0)
    with BackgroundServer(settings, wait_ready=False) as srv:
        _wait(lambda: board.count() == 1, "this worker to load its models")
        r = httpx.get(f"{srv.url}/readyz", timeout=60)
        assert r.status_code == 503 and r.json()["ready"] is False and r.json()["models"] == ["cookie-box"]
        ctx = multiprocessing.get_context("spawn")
        parent, child_end = ctx.Pipe()
        other = ctx.Process(target=_ready_worker, args=(str(run / "ready"), child_end), daemon=True)
        other.start()
        try:
            assert parent.poll(120) and parent.recv() is True
            r = httpx.get(f"{srv.url}/readyz", timeout=60)
            assert r.status_code == 200 and r.json()["ready"] is True
            os.kill(other.pid, signal.SIGKILL)  # a worker that dies (uvicorn restarts it) is not ready
            other.join(60)
            r = httpx.get(f"{srv.url}/readyz", timeout=60)
            assert r.status_code == 503 and board.count() == 1
        finally:
            if other.is_alive():
                other.kill()
                other.join(60)


def test_settings_from_environment(monkeypatch):
    monkeypatch.setenv("QUATRACK_MAX_SESSIONS", "7")
    monkeypatch.setenv("QUATRACK_CORS_ORIGINS", "https://a.example, https://b.example")
    s = Settings.from_env(port=9001)
    assert s.max_sessions == 7 and s.port == 9001 and s.cors_origins == ("https://a.example", "https://b.example")
    assert Settings.from_env(**{}).to_env()[env_name("max_sessions")] == "7"
    monkeypatch.setenv("QUATRACK_WORKERS", "zero")
    with pytest.raises(ValueError, match="QUATRACK_WORKERS"):
        Settings.from_env()
    monkeypatch.delenv("QUATRACK_WORKERS")
    with pytest.raises(ValueError, match="threads=0"):
        Settings.from_env(threads=0)


def test_readme_documents_every_setting():
    readme = (ROOT / "README.md").read_text()
    for name in Settings.model_fields:
        assert re.search(rf"\|\s*`{env_name(name)}`\s*\|", readme), f"README's settings table lacks {env_name(name)}"
    assert settings_table() in readme, "README's settings table is stale: python -m quatrack.service.settings"

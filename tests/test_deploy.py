"""The deployment, for real: Debian's nginx with deploy/nginx.conf in front of two ``quatrack serve``
replicas on loopback sharing one model store. Sessions stream through the balancer; one replica
is stopped mid-run (SIGTERM): its sessions get a clean close (1012), the others go on, new
sessions land on the live replica, and the balancer answers no REST request with a 5xx (it
retries the dead replica's requests on the live one; see the comments in deploy/nginx.conf).

No timing assertions: every wait is bounded by a generous timeout and only outcomes are checked.
"""

from __future__ import annotations

import asyncio
import json
import re
import time
from pathlib import Path

import httpx
import pytest

from conftest import box_frames_jpeg, sessions_active
from quatrack.testing.balancer import Nginx, find_nginx
from quatrack.testing.scenes import example_store
from quatrack.service.server import ServeProcess

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy"
EXAMPLE = ROOT / "examples" / "cookie-box"
CAMERA = json.loads((EXAMPLE / "camera.json").read_text())
NGINX = find_nginx()


def test_manifests_describe_replicas_with_readiness():
    yaml = pytest.importorskip("yaml")
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    q = compose["services"]["quatrack"]
    assert q["deploy"]["replicas"] >= 2 and "/readyz" in " ".join(q["healthcheck"]["test"])
    assert any(v.startswith("models:") for v in q["volumes"]) and "models" in compose["volumes"]
    docs = {d["kind"]: d for d in yaml.safe_load_all((DEPLOY / "kubernetes.yaml").read_text())}
    dep = docs["Deployment"]["spec"]
    assert dep["replicas"] >= 2
    (c,) = dep["template"]["spec"]["containers"]
    assert c["readinessProbe"]["httpGet"]["path"] == "/readyz"
    claim = dep["template"]["spec"]["volumes"][0]["persistentVolumeClaim"]["claimName"]
    assert docs["PersistentVolumeClaim"]["metadata"]["name"] == claim
    assert "ReadWriteMany" in docs["PersistentVolumeClaim"]["spec"]["accessModes"]


def test_the_training_job_may_write_the_model_claim():
    """The image runs as an unprivileged user; a fresh claim's root belongs to root, so the training
    Job failed with "Permission denied" until its pod says whose group the volume is (fsGroup)."""
    yaml = pytest.importorskip("yaml")
    uid = int(re.search(r"useradd[^\n]*--uid (\d+)", (ROOT / "Dockerfile").read_text()).group(1))
    docs = {d["kind"]: d for d in yaml.safe_load_all((DEPLOY / "kubernetes.yaml").read_text())}
    pod = docs["Job"]["spec"]["template"]["spec"]
    (c,) = pod["containers"]
    assert any(m["mountPath"] == "/data/models" and not m.get("readOnly") for m in c["volumeMounts"])
    assert pod.get("securityContext", {}).get("fsGroup") == uid


def test_the_image_health_check_follows_quatrack_port(tmp_path):
    """The Dockerfile's HEALTHCHECK asks the port the server listens on: `docker run -e
    QUATRACK_PORT=9000` (a documented setting) left the container unhealthy, its check asking 8000."""
    import http.server
    import subprocess
    import sys
    import threading

    line = next(x for x in (ROOT / "Dockerfile").read_text().splitlines() if x.strip().startswith("CMD [\"python\""))
    argv = json.loads(line.strip()[len("CMD"):])
    assert argv[:2] == ["python", "-c"]

    class Healthz(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200 if self.path == "/healthz" else 404)
            self.end_headers()

        def log_message(self, *args):
            pass

    with http.server.ThreadingHTTPServer(("127.0.0.1", 0), Healthz) as srv:
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        try:
            env = {"PATH": "/usr/bin:/bin", "QUATRACK_PORT": str(srv.server_address[1])}
            done = subprocess.run([sys.executable, *argv[1:]], env=env, capture_output=True, timeout=60)
            assert done.returncode == 0, done.stderr.decode()[-500:]
        finally:
            srv.shutdown()


class Session:
    """A tracking client until stopped or closed by the server: lock-step (one frame, one answer),
    or ``push``: frames at 30 fps without waiting for answers, as a camera sends them, so that
    frames are in flight whenever the server stops."""

    def __init__(self, url: str, frames: list[bytes], push: bool = False) -> None:
        self.url, self.frames, self.push = url, frames, push
        self.answers = 0
        self.close_code: int | None = None
        self.stop = asyncio.Event()
        self.started = asyncio.Event()

    async def _send(self, ws, k: int) -> None:
        await ws.send(json.dumps({"type": "frame", "time_s": k / 30}))
        await ws.send(self.frames[k % len(self.frames)])

    async def _pusher(self, ws) -> None:
        k = 0
        while not self.stop.is_set():
            await self._send(ws, k)
            k += 1
            await asyncio.sleep(1 / 30)
        await ws.close()

    async def run(self) -> None:
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed

        pusher = None
        try:
            async with connect(self.url, open_timeout=60, max_size=None) as ws:
                await ws.send(json.dumps({**CAMERA, "ack": True}))
                assert json.loads(await asyncio.wait_for(ws.recv(), 120))["type"] == "ready"
                if self.push:
                    pusher = asyncio.create_task(self._pusher(ws))
                k = 0
                while not self.stop.is_set() or pusher is not None:
                    if not self.push:
                        await self._send(ws, k)
                    msg = json.loads(await asyncio.wait_for(ws.recv(), 120))
                    assert msg["type"] == "pose", msg
                    self.answers += 1
                    self.started.set()
                    k += 1
        except ConnectionClosed as exc:
            # 1006 (abnormal): the connection dropped without a close frame reaching the client
            self.close_code = exc.rcvd.code if exc.rcvd is not None else 1006
        finally:
            self.started.set()
            if pusher is not None:
                pusher.cancel()


async def wait_for(pred, what: str, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.05)


@pytest.mark.slow
@pytest.mark.skipif(NGINX is None, reason="nginx is not installed (Debian: apt-get install nginx; .ci/apt-packages lists it)")
def test_two_replicas_behind_nginx_survive_one_stopping(tmp_path):
    store = example_store()
    env = {"QUATRACK_MAX_SESSIONS": "8", "QUATRACK_THREADS": "1"}
    a = ServeProcess(store, workers=1, env=env, log_path=tmp_path / "a.log")
    b = ServeProcess(store, workers=1, env=env, log_path=tmp_path / "b.log")
    with a, b, Nginx(tmp_path / "nginx", [a.port, b.port]) as lb:
        base = lb.url
        ws_url = f"{lb.ws_url}/v1/objects/cookie-box/track"
        frames = box_frames_jpeg(4)
        statuses: list[int] = []

        async def rest(stop: asyncio.Event) -> None:
            async with httpx.AsyncClient(timeout=120) as client:
                while not stop.is_set():
                    for path in ("/healthz", "/v1/objects", "/readyz"):
                        statuses.append((await client.get(base + path)).status_code)
                    await asyncio.sleep(0.02)

        async def scenario() -> None:
            stop_rest = asyncio.Event()
            rest_task = asyncio.create_task(rest(stop_rest))
            old = [Session(ws_url, frames) for _ in range(4)]
            tasks = []
            for s in old:  # one after the other: least_conn spreads them over both replicas
                tasks.append(asyncio.create_task(s.run()))
                await asyncio.wait_for(s.started.wait(), 180)
            assert all(s.answers > 0 for s in old)
            on_a = await asyncio.to_thread(sessions_active, a.url)
            on_b = await asyncio.to_thread(sessions_active, b.url)
            assert on_a + on_b == 4 and on_a >= 1 and on_b >= 1, (on_a, on_b)
            await asyncio.to_thread(a.stop)  # SIGTERM, mid-stream
            await wait_for(lambda: sum(t.done() for t in tasks) >= on_a, "the stopped replica's sessions to close")
            before = {id(s): s.answers for s in old}
            # the survivors keep tracking on the live replica
            await wait_for(lambda: all(s.answers > before[id(s)] + 2 for s in old if s.close_code is None),
                           "the other sessions to go on")
            closed = [s for s in old if s.close_code is not None]
            # the stopped replica closes each of its sessions with 1012 (service restart) and waits
            # for the closing handshake before it exits, so nginx passes the close frame on (a
            # dropped connection, 1006, was seen once in five runs before service/shutdown.py);
            # and no survivor on the live replica is among them
            assert len(closed) == on_a and all(s.close_code == 1012 for s in closed), [s.close_code for s in old]
            # new sessions go to the live replica
            new = [Session(ws_url, frames) for _ in range(2)]
            new_tasks = [asyncio.create_task(s.run()) for s in new]
            await wait_for(lambda: all(s.answers >= 3 for s in new), "new sessions through the balancer")
            assert await asyncio.to_thread(sessions_active, b.url) == on_b + 2
            for s in old + new:
                s.stop.set()
            await asyncio.wait_for(asyncio.gather(*tasks, *new_tasks), 180)
            stop_rest.set()
            await rest_task

        asyncio.run(scenario())
        assert statuses and all(code == 200 for code in statuses), sorted(set(statuses))
        error_log = lb.error_log.read_text()
        # the balancer did see the dead replica, and retried on the live one (passive health check).
        # How nginx words it depends on when the replica died: a refused connect, or a kept-alive
        # upstream connection closed or reset under it; each line names the upstream address.
        seen = re.search(rf"(connect\(\) failed|upstream prematurely closed|recv\(\) failed|reset by peer)"
                         rf"[^\n]*127\.0\.0\.1:{a.port}", error_log)
        assert seen, error_log[-2000:]


@pytest.mark.slow
def test_stopping_a_server_closes_every_session_with_1012(tmp_path):
    """SIGTERM to ``quatrack serve --workers 2`` while three clients push frames at camera rate
    (so frames are in flight when it stops): every session is closed with 1012 (service restart),
    none dropped (1006): each connection stays open until the client's closing reply is back
    (service/shutdown.py). Without that, 1 run in 3 here saw [1012, 1006, 1006]."""
    srv = ServeProcess(example_store(), workers=2, env={"QUATRACK_MAX_SESSIONS": "4", "QUATRACK_THREADS": "1"},
                       log_path=tmp_path / "serve.log")
    frames = box_frames_jpeg(4)
    with srv:
        async def scenario() -> None:
            sessions = [Session(f"{srv.ws_url}/v1/objects/cookie-box/track", frames, push=True) for _ in range(3)]
            # opened at the same instant (session 24 opened them one after another while three
            # opened together sometimes waited a minute for a handshake: the shared listening
            # socket left blocking, session 25; tests/test_workers.py checks its mode)
            tasks = [asyncio.create_task(s.run()) for s in sessions]
            await wait_for(lambda: all(s.answers >= 2 for s in sessions), "every session to track")
            await asyncio.to_thread(srv.stop)  # SIGTERM to the supervisor and its workers
            await asyncio.wait_for(asyncio.gather(*tasks), 120)
            assert [s.close_code for s in sessions] == [1012] * 3, (tmp_path / "serve.log").read_text()[-3000:]

        asyncio.run(scenario())


@pytest.mark.slow
def test_stop_ends_the_workers_of_a_supervisor_that_died(tmp_path):
    """The supervisor of ``quatrack serve --workers 2`` killed (SIGKILL: no time to stop its
    workers): ``ServeProcess.stop`` still ends the workers — they kept the port and a benchmark's
    next server could not bind it — by signalling the whole process group."""
    import os
    import signal

    srv = ServeProcess(example_store(), workers=2, env={"QUATRACK_THREADS": "1"}, log_path=tmp_path / "serve.log")
    with srv:
        workers = srv.worker_pids()
        assert len(workers) == 2
        os.kill(srv.proc.pid, signal.SIGKILL)
        srv.proc.wait(timeout=30)

        def alive(pid: int) -> bool:
            try:
                with open(f"/proc/{pid}/stat") as f:
                    return f.read().rsplit(")", 1)[1].split()[0] != "Z"
            except OSError:
                return False

        assert any(alive(p) for p in workers)  # (the workers outlived it)
    deadline = time.monotonic() + 30
    while any(alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(alive(p) for p in workers)

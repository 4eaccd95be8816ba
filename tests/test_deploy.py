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
from prometheus_client.parser import text_string_to_metric_families

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


def frames_jpeg(n: int) -> list[bytes]:
    import cv2

    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    out = []
    while len(out) < n:
        ok, img = cap.read()
        if not ok:
            break
        out.append(cv2.imencode(".jpg", img)[1].tobytes())
    cap.release()
    return out


def sessions_active(url: str) -> float:
    for family in text_string_to_metric_families(httpx.get(f"{url}/metrics", timeout=60).text):
        for s in family.samples:
            if s.name == "quatrack_ws_sessions_active":
                return s.value
    raise AssertionError("no quatrack_ws_sessions_active in /metrics")


class Session:
    """A lock-step tracking client: one frame, one answer, until stopped or closed by the server."""

    def __init__(self, url: str, frames: list[bytes]) -> None:
        self.url, self.frames = url, frames
        self.answers = 0
        self.close_code: int | None = None
        self.stop = asyncio.Event()
        self.started = asyncio.Event()

    async def run(self) -> None:
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed

        try:
            async with connect(self.url, open_timeout=60, max_size=None) as ws:
                await ws.send(json.dumps({**CAMERA, "ack": True}))
                assert json.loads(await asyncio.wait_for(ws.recv(), 120))["type"] == "ready"
                k = 0
                while not self.stop.is_set():
                    await ws.send(json.dumps({"type": "frame", "time_s": k / 30}))
                    await ws.send(self.frames[k % len(self.frames)])
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
        frames = frames_jpeg(4)
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
            # uvicorn closes every session with 1012 (service restart) on SIGTERM; on a loaded machine
            # the replica's exit sometimes drops the connection first and the client sees 1006 (one
            # CI run in five). Either way the session ends and the client may reconnect; what must
            # not happen is a survivor on the live replica among them.
            assert len(closed) == on_a and all(s.close_code in (1012, 1006) for s in closed), \
                [s.close_code for s in old]
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

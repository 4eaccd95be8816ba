"""Every answer comes in the order of what it answers, as the README promises ("each frame is
answered by one message, in frame order"): a refusal on arrival (``unsupported_image``,
``rate_limited``) or a header's ``out_of_order``, sent at once, overtook the pose answers of
earlier frames still being tracked, and a client counting answers filed them under the wrong
frames. The first frame's step is held until the server has received everything (its metrics),
so the order does not depend on the machine's speed."""

from __future__ import annotations

import json

import pytest
from websockets.sync.client import connect

from conftest import wait_until
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store
from test_service_ws import CAM_ACK, gate_the_steps, metric, recv
from test_service_http import jpeg, video_frames


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store(), max_fps=2.0)) as srv:
        yield srv


def errors(srv) -> float:
    return metric(srv, 'quatrack_ws_frames_total{result="error"}') or 0.0


def rate_limited(srv) -> float:
    return metric(srv, 'quatrack_ws_frames_total{result="rate_limited"}') or 0.0


def test_refusals_wait_for_the_answers_of_earlier_frames(server, monkeypatch):
    gate, _ = gate_the_steps(monkeypatch)
    f0, f1, f2 = (jpeg(f) for f in video_frames(3))
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
        ws.send(CAM_ACK)
        assert recv(ws)["type"] == "ready"
        e0, r0 = errors(server), rate_limited(server)
        ws.send(json.dumps({"type": "frame", "time_s": 1.0, "id": "a"}))
        ws.send(f0)  # frame 0: tracked (held at the gate)
        ws.send(json.dumps({"type": "frame", "time_s": 0.5, "id": "b"}))  # out_of_order
        ws.send(f1)  # frame 1: answered dropped, untracked
        ws.send(json.dumps({"type": "frame", "time_s": 2.0, "id": "c"}))
        ws.send(b"notimage")  # refused on arrival
        ws.send(json.dumps({"type": "frame", "time_s": 2.5, "id": "d"}))
        ws.send(f2)  # a third frame within the 2 frames/s, frame 0 unanswered: refused on arrival
        assert wait_until(lambda: errors(server) == e0 + 2 and rate_limited(server) == r0 + 1, timeout=60)
        gate.set()
        got = [recv(ws) for _ in range(5)]
    seen = [(m["type"], m.get("frame"), m.get("error", {}).get("code"), m.get("id")) for m in got]
    assert seen == [("pose", 0, None, "a"), ("error", None, "out_of_order", "b"), ("pose", 1, None, "b"),
                    ("error", None, "unsupported_image", "c"), ("error", None, "rate_limited", "d")], seen
    assert got[2]["dropped"] is True


def test_lock_step_refusals_are_answered_at_once(server):
    """Nothing owed: a refusal goes out at once, as before (the lock-step client's only frame)."""
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
        ws.send(CAM_ACK)
        assert recv(ws)["type"] == "ready"
        ws.send(b"notimage")
        assert recv(ws)["error"]["code"] == "unsupported_image"
        ws.send(json.dumps({"type": "dance"}))
        assert recv(ws)["error"]["code"] == "bad_message"

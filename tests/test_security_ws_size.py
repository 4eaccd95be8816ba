"""A WebSocket frame too large to be read (over twice ``QUATRACK_MAX_BODY_BYTES``: uvicorn's
``ws_max_size``) ends the session with its own outcome, ``too_large``, in the session's log line
and in ``quatrack_ws_sessions_total``: it was counted ``closed``, as if the client had closed."""

from __future__ import annotations

import json

import httpx
from conftest import metric_samples, wait_until
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

CAMERA = {"width": 640, "height": 480, "fx": 669.7, "fy": 667.8, "cx": 320.0, "cy": 240.0}


def test_a_frame_over_twice_the_limit_ends_the_session_as_too_large(capfd):
    limit = 50_000
    with BackgroundServer(Settings(store=example_store(), max_body_bytes=limit, model_poll_s=0), log_level="info") as srv:
        url = srv.url.replace("http://", "ws://") + "/v1/objects/cookie-box/track"
        with connect(url, open_timeout=60, max_size=None) as ws:
            ws.send(json.dumps({**CAMERA, "ack": True}))
            assert json.loads(ws.recv(timeout=60))["type"] == "ready"
            try:
                ws.send(b"\x89PNG" + bytes(3 * limit))
                while True:  # (whatever close code reaches the client: see the README)
                    ws.recv(timeout=60)
            except ConnectionClosed:
                pass

        def outcomes():
            text = httpx.get(f"{srv.url}/metrics", timeout=30).text
            return {dict(labels)["outcome"]: v for (name, labels), v in metric_samples(text).items()
                    if name == "quatrack_ws_sessions_total"}

        assert wait_until(lambda: outcomes(), 60), "the session never ended"
        assert outcomes() == {"too_large": 1.0}, outcomes()
    ended = [json.loads(x) for x in capfd.readouterr().err.splitlines() if '"session ended"' in x]
    assert [e["outcome"] for e in ended] == ["too_large"], ended


def test_a_frame_far_over_the_limit_gets_its_1009_close_frame():
    """uvicorn closed the socket as soon as the frame's header said it was too large, while the
    client was still sending it: the kernel reset the connection and the close frame was often
    lost (a trial saw 1006 for a 30 MB frame with the default limit, 1009 for 25 MB; which ones
    varies from run to run). The connection now stays open, discarding what still comes, until the
    client has read the close frame: every size gets 1009."""
    with BackgroundServer(Settings(store=example_store(), model_poll_s=0)) as srv:  # (the default limit: 10 MiB)
        url = srv.url.replace("http://", "ws://") + "/v1/objects/cookie-box/track"
        limit = 2 * srv.settings.max_body_bytes
        for size in (limit + 1_000_000, limit + 9_000_000, 3 * limit):
            with connect(url, open_timeout=60, max_size=None) as ws:
                ws.send(json.dumps({**CAMERA, "ack": True}))
                assert json.loads(ws.recv(timeout=60))["type"] == "ready"
                try:
                    ws.send(b"\x89PNG" + bytes(size))
                    while True:
                        ws.recv(timeout=60)
                except ConnectionClosed as closed:
                    assert closed.rcvd is not None and closed.rcvd.code == 1009, (size, closed)

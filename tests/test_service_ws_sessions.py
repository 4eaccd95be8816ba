"""WebSocket sessions as an integrator meets them: frame times a camera repeats, lock-step
pacing, the idle close, the stream's token and the session's log lines."""

from __future__ import annotations

import json

import pytest
from starlette.websockets import WebSocketState
from websockets.sync.client import connect

from quatrack.testing.scenes import example_store
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from test_service_http import jpeg, video_frames
from test_service_ws import CAM_ACK, CAMERA, recv


class ScriptedSocket:
    """A session's WebSocket, in process: it receives ``messages`` (text), then the client leaves;
    what the session sends is dropped."""

    client_state = WebSocketState.DISCONNECTED

    def __init__(self, *messages: str) -> None:
        self.inbox = list(messages)

    async def receive(self) -> dict:
        if self.inbox:
            return {"type": "websocket.receive", "text": self.inbox.pop(0)}
        return {"type": "websocket.disconnect"}

    async def send_text(self, text: str) -> None:
        pass


@pytest.fixture(scope="module")
def store():
    return example_store()


@pytest.fixture(scope="module")
def frames():
    return [jpeg(f) for f in video_frames(10)]


@pytest.fixture(scope="module")
def server(store):
    with BackgroundServer(Settings(store=store, max_sessions=2)) as srv:
        yield srv


def answers_of(ws, fid) -> list[dict]:
    """Every message about frame ``fid`` up to its pose message (an error may come first)."""
    out = []
    while not out or out[-1]["type"] != "pose":
        out.append(recv(ws))
        assert out[-1].get("id") == fid, out
    return out


def test_a_repeated_time_is_refused_alone_and_later_frames_keep_the_clients_times(server, frames):
    """Frame 5 repeats frame 4's time_s: it is refused (``out_of_order``) and answered ``dropped``
    at the client's time, untracked; the session's clock stays at frame 4's time, so frames 6..9,
    correctly timed, are tracked with no error, each answer at the client's time. (Frame 5 was
    tracked at previous time + arrival gap, which became the baseline: every later frame was
    refused, and answered at a time the server made up.)"""
    times = [i / 30 for i in range(10)]
    times[5] = times[4]
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
        ws.send(CAM_ACK)
        assert recv(ws)["type"] == "ready"
        got = []
        for i, t in enumerate(times):
            ws.send(json.dumps({"type": "frame", "time_s": t, "id": i}))
            ws.send(frames[i])
            got.append(answers_of(ws, i))
    for i, msgs in enumerate(got):
        *errors, pose = msgs
        assert pose["frame"] == i and pose["time_s"] == times[i], msgs
        if i == 5:
            assert [e["error"]["code"] for e in errors] == ["out_of_order"], msgs
            assert pose["dropped"] is True and pose["pose"] is None and "not after" in pose["reason"], pose
        else:
            assert errors == [] and not pose.get("dropped"), msgs
            assert pose["status"] == ("init" if i == 0 else "tracking"), msgs


def test_a_lock_step_client_is_paced_not_refused(store, frames):
    """QUATRACK_MAX_FPS=5: a client that sends each frame after the previous one's answer is never
    refused (lock-step ran faster than the default 60 frames/s and lost ~11 % of its frames as
    ``rate_limited``); its frames wait for their token, so the limit still holds: 10 frames
    (5 of them the bucket's burst) take at least 1 s."""
    import time

    with BackgroundServer(Settings(store=store, max_sessions=1, max_fps=5.0)) as srv:
        with connect(f"{srv.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
            ws.send(CAM_ACK)
            assert recv(ws)["type"] == "ready"
            t0 = time.perf_counter()
            got = []
            for i in range(10):
                ws.send(json.dumps({"type": "frame", "time_s": i / 30}))
                ws.send(frames[i])
                got.append(recv(ws))
            elapsed = time.perf_counter() - t0
            assert [(m["type"], m["frame"], m["time_s"]) for m in got] == [("pose", i, i / 30) for i in range(10)], got
            assert elapsed >= 0.95, elapsed  # (5 held frames, 0.2 s each, less the bucket's refill meanwhile)


def test_frames_sent_ahead_of_the_answers_are_refused_over_the_rate(store, frames):
    """QUATRACK_MAX_FPS=0.25 (a bucket of one token, one more every 4 s): of three frames sent at
    once, the first takes the token and a later one is refused ``rate_limited`` — read while an
    earlier frame is in flight, or, if that one was answered already, needing a hold over
    ``MAX_HOLD_S`` (1 s) for its token. Either way, whatever the machine's speed, unless the server
    read each frame 3 s after the one before (the rule held at QUATRACK_MAX_FPS=5 too, where it
    hung on the server reading the next frame within the first one's 0.2 s hold: a loaded CI
    machine did not)."""
    with BackgroundServer(Settings(store=store, max_sessions=1, max_fps=0.25)) as srv:
        with connect(f"{srv.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
            ws.send(CAM_ACK)
            assert recv(ws)["type"] == "ready"
            for i in range(3):
                ws.send(json.dumps({"type": "frame", "time_s": i / 30}))
                ws.send(frames[i])
            msgs = [recv(ws, timeout=60) for _ in range(3)]
            codes = [m["error"]["code"] for m in msgs if m["type"] == "error"]
            assert [m["frame"] for m in msgs if m["type"] == "pose"][:1] == [0], msgs  # (refusals may come first)
            assert "rate_limited" in codes, msgs


def test_an_idle_timeout_close_carries_its_code_and_the_client_raises_it(store, frames):
    """A session idle for QUATRACK_IDLE_TIMEOUT_S is closed with 1001 and the reason
    ``idle_timeout`` (was 1000 without a reason), and ``Client.track`` whose next frame comes too
    late raises ``QuatrackError.code == "idle_timeout"`` (was ``"closed"``: the server's code lost)."""
    import time

    from websockets.exceptions import ConnectionClosed

    from quatrack.client import Client, QuatrackError

    with BackgroundServer(Settings(store=store, max_sessions=2, idle_timeout_s=0.5)) as srv:
        with connect(f"{srv.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
            ws.send(CAM_ACK)
            assert recv(ws)["type"] == "ready"
            assert recv(ws, timeout=30)["error"]["code"] == "idle_timeout"
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=30)
        assert (closed.value.rcvd.code, closed.value.rcvd.reason) == (1001, "idle_timeout"), closed.value

        def slow():
            yield frames[0]
            time.sleep(2.0)  # (4 × the idle timeout: the server closes meanwhile)
            yield frames[1]

        with Client(srv.url, object="cookie-box", timeout=30) as c, pytest.raises(QuatrackError) as e:
            for _ in c.track(slow(), CAMERA):
                pass
        assert e.value.code == "idle_timeout", e.value


def test_stream_reads_the_token_from_the_environment_as_client_does(store, frames, monkeypatch):
    """``quatrack.client.stream()`` without ``token=`` sends ``$QUATRACK_API_TOKEN``, as
    ``Client`` does (it sent none: refused ``unauthorized`` where ``Client`` was let in); an
    explicit token still wins."""
    import asyncio

    from quatrack.client import QuatrackError, stream

    monkeypatch.setenv("QUATRACK_API_TOKEN", "sekret")
    with BackgroundServer(Settings(store=store, max_sessions=1, api_token="sekret")) as srv:
        url = f"{srv.ws_url}/v1/objects/cookie-box/track"
        res = asyncio.run(stream(url, CAMERA, [(0, 0.0, frames[0])], timeout=30.0))
        assert sorted(res.poses) == [0] and res.errors == [], res
        with pytest.raises(QuatrackError) as e:
            asyncio.run(stream(url, CAMERA, [(0, 0.0, frames[0])], token="wrong", timeout=30.0))
        assert e.value.code == "unauthorized"
    from quatrack.client import api_token  # (the one reader of the variable: Client's and stream's)

    assert api_token() == "sekret" and api_token("other") == "other" and api_token("") is None


def test_a_session_logs_its_start_end_and_errors_with_its_id_as_a_field(tmp_path):
    """Log lines of a session carry ``session_id`` as a field (as requests carry ``request_id``):
    one as it opens, one as it ends (outcome, frames, duration), and its errors; the id was only
    inside some messages' text, and a session's start and end were not logged."""
    import asyncio
    import logging
    from concurrent.futures import ThreadPoolExecutor

    from quatrack.service import sessions
    from quatrack.service.logs import JsonFormatter
    from quatrack.service.metrics import Metrics

    seen: list[logging.LogRecord] = []
    tap = logging.Handler(logging.DEBUG)
    tap.emit = seen.append
    logger = logging.getLogger("quatrack.service")
    logger.addHandler(tap)
    level, disabled = logger.level, logger.disabled  # (an earlier server's log configuration may have disabled it)
    logger.setLevel(logging.INFO)
    logger.disabled = False
    try:
        with ThreadPoolExecutor(1) as pool:
            # the camera, a message of no known type, then the client leaves
            session = sessions.TrackSession(ScriptedSocket(json.dumps(CAMERA), '{"type": "dance"}'), "abc123", "cookie-box", None, Settings(store=tmp_path), pool,
                                            Metrics())
            outcome = asyncio.run(asyncio.wait_for(session.run(), 30))
    finally:
        logger.removeHandler(tap)
        logger.setLevel(level)
        logger.disabled = disabled
    lines = [json.loads(JsonFormatter().format(r)) for r in seen]
    assert lines and all(ln.get("session_id") == "abc123" for ln in lines), lines
    assert lines[0]["msg"] == "session opened" and lines[0]["object"] == "cookie-box", lines
    assert [ln["code"] for ln in lines if "code" in ln] == ["bad_message"], lines
    end = lines[-1]
    assert end["msg"] == "session ended" and (end["outcome"], end["frames"]) == (outcome, 0), end
    assert end["duration_s"] >= 0, end


def test_a_frame_of_the_cameras_aspect_at_another_size_says_the_camera_to_send(server, frames):
    """A frame half the camera's size (its own images, resized): ``bad_image`` says the camera to
    send for that size in the message's terms (fx=…, width=…), as the REST pose route does, not
    the library's ``camera.scaled(…)``; the session goes on."""
    import cv2
    import numpy as np

    small = cv2.imdecode(np.frombuffer(frames[0], np.uint8), cv2.IMREAD_COLOR)
    small = jpeg(cv2.resize(small, (small.shape[1] // 2, small.shape[0] // 2), interpolation=cv2.INTER_AREA))
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
        ws.send(CAM_ACK)
        assert recv(ws)["type"] == "ready"
        ws.send(json.dumps({"type": "frame", "time_s": 0.0, "id": "a"}))
        ws.send(small)
        err = recv(ws)  # (a refused frame's one answer)
        assert err["type"] == "error" and err["error"]["code"] == "bad_image" and err["id"] == "a", err
        msg = err["error"]["message"]
        w, h = CAMERA["width"], CAMERA["height"]
        assert msg.startswith(f"the camera is for {w}×{h} px images but the image is {w // 2}×{h // 2} px"), msg
        assert f"fx={CAMERA['fx'] / 2:.6g}" in msg and f"width={w // 2}" in msg and "scaled(" not in msg, msg
        ws.send(json.dumps({"type": "frame", "time_s": 0.1, "id": "b"}))
        ws.send(frames[1])
        assert answers_of(ws, "b")[-1]["status"] == "init"

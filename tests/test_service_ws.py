"""End-to-end tests of the WebSocket tracking sessions on a real server (loopback)."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import threading
from pathlib import Path

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from quatrack.testing.scenes import example_store
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from conftest import metric_samples, wait_until
from test_service_http import CAMERA, jpeg, video_frames

CAM_TEXT = json.dumps(CAMERA)
CAM_ACK = json.dumps({**CAMERA, "ack": True})  # asks for the {"type": "ready"} handshake


@pytest.fixture(scope="module")
def store():
    return example_store()


@pytest.fixture(scope="module")
def frames():
    return [jpeg(f) for f in video_frames(24)]


@pytest.fixture(scope="module")
def server(store):
    with BackgroundServer(Settings(store=store, max_sessions=3, max_body_bytes=2_000_000)) as srv:
        yield srv


@pytest.fixture(scope="module")
def strict(store):
    """Tight limits and a token: one session, 2 s idle timeout, 5 frames/s."""
    settings = Settings(store=store, api_token="tok", max_sessions=1, idle_timeout_s=2.0, max_fps=5.0)
    with BackgroundServer(settings) as srv:
        yield srv


def recv(ws, timeout=60.0) -> dict:
    return json.loads(ws.recv(timeout=timeout))


@contextlib.contextmanager
def open_session(srv, name="cookie-box", **kw):
    with connect(f"{srv.ws_url}/v1/objects/{name}/track", open_timeout=20, **kw) as ws:
        ws.send(CAM_ACK)
        ready = recv(ws)
        assert ready["type"] == "ready" and ready["object"] == name, ready
        yield ws


def send_frame(ws, data: bytes, time_s: float | None = None) -> None:
    if time_s is not None:
        ws.send(json.dumps({"type": "frame", "time_s": time_s}))
    ws.send(data)


def metric(srv, name: str, token: str | None = None) -> float:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    for line in httpx.get(f"{srv.url}/metrics", headers=headers).text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    return 0.0


def check_pose_message(m: dict) -> None:
    assert m["type"] == "pose" and m["status"] in ("init", "tracking", "lost")
    assert m["latency_ms"] > 0 and m["time_s"] >= 0  # "skipped" is checked by the tests that know its value
    if m["status"] == "lost":
        assert m["pose"] is None
        return
    q = np.array(m["pose"]["q_wxyz"])
    assert abs(np.linalg.norm(q) - 1) < 1e-6 and q[0] >= 0 and len(m["pose"]["t"]) == 3
    cov = np.array(m["covariance"])
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T, atol=1e-9)
    assert len(m["velocity"]["v"]) == 3 and len(m["velocity"]["omega"]) == 3


def test_contract_exchange_is_one_message_per_frame(server, frames):
    """The contract's plain exchange: a camera text message, then binary frames; each frame is
    answered by exactly one pose message, and nothing else is sent."""
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
        ws.send(CAM_TEXT)
        for i, data in enumerate(frames[:3]):
            ws.send(data)
            msg = recv(ws)
            assert msg["frame"] == i and msg["skipped"] == 0, msg
            check_pose_message(msg)  # values: unit quaternion, 3-vectors, symmetric 6×6 covariance
            assert msg["status"] == ("init" if i == 0 else "tracking") and msg["inliers"] >= 12, msg
        with pytest.raises(TimeoutError):
            ws.recv(timeout=1.0)


def test_tracked_stream(server, frames):
    with open_session(server) as ws:
        out = []
        for i, f in enumerate(frames[:20]):
            send_frame(ws, f, i / 30)
            out.append(recv(ws))
    for i, m in enumerate(out):
        check_pose_message(m)
        assert m["frame"] == i and m["skipped"] == 0 and m["time_s"] == pytest.approx(i / 30)
    assert out[0]["status"] == "init"
    assert sum(m["status"] == "tracking" for m in out) >= 15
    t = np.array([m["pose"]["t"] for m in out if m["pose"]])
    assert np.all(np.abs(np.diff(t, axis=0)) < 5.0)  # cm per frame: a hand-held box, not jumps


def test_bad_messages_keep_the_session_usable(server, frames):
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track") as ws:
        ws.send(frames[0])
        assert recv(ws)["error"]["code"] == "camera_required"
        ws.send(json.dumps({"type": "reset"}))
        assert recv(ws)["error"]["code"] == "camera_required"
        for bad in ({**CAMERA, "fx": -1}, {"fx": 600}, {**CAMERA, "dist_coeffs": "x"}, {**CAMERA, "ack": "yes"}):
            ws.send(json.dumps(bad))
            assert recv(ws)["error"]["code"] == "bad_camera"
        ws.send(CAM_ACK)
        assert recv(ws)["type"] == "ready"
        for text, code in (("{oops", "bad_message"), ("[1, 2]", "bad_message"), ('{"type": "dance"}', "bad_message"),
                           ('{"type": "frame", "time_s": -1}', "bad_message"),
                           ('{"type": "frame", "time_s": "soon"}', "bad_message"),
                           ('{"type": "frame", "time_s": 1' + "0" * 400 + "}", "bad_message"),  # (OverflowError: session ended)
                           ('{"fx": 1' + "0" * 400 + ', "fy": 600, "cx": 320, "cy": 240}', "bad_camera"),
                           ('{"type": "init", "pose": {"foo": 1}}', "bad_pose"),
                           ('{"type": "init", "pose": {"q_wxyz": [0, 0, 0, 0], "t": [0, 0, 50]}}', "bad_pose")):
            ws.send(text)
            m = recv(ws)
            assert m["type"] == "error" and m["error"]["code"] == code, (text, m)
        ws.send(b"\xff\xd8\xff" + b"0" * 2_100_000)  # over max_body_bytes: refused, session goes on
        assert recv(ws)["error"]["code"] == "too_large"
        ws.send(b"\x00garbage")
        assert recv(ws)["error"]["code"] == "unsupported_image"
        ws.send(frames[0][: len(frames[0]) // 3])  # truncated JPEG
        m = recv(ws)
        assert m["error"]["code"] == "bad_image" and m["frame"] == 0
        import cv2
        small = jpeg(cv2.resize(video_frames(1)[0], (320, 240)))
        ws.send(small)
        m = recv(ws)
        assert m["error"]["code"] == "bad_image" and "640" in m["error"]["message"]
        send_frame(ws, frames[1], 1.0)
        good = recv(ws)
        check_pose_message(good)
        assert good["status"] == "init"
        ws.send(json.dumps({"type": "frame", "time_s": 0.5}))  # before the previous frame
        assert recv(ws)["error"]["code"] == "out_of_order"
        ws.send(json.dumps({"type": "frame", "time_s": 2.0}))
        ws.send(json.dumps({"type": "frame", "time_s": 2.1}))  # two headers in a row
        assert recv(ws)["error"]["code"] == "out_of_order"
        # reset, then init from the pose just found: the session still tracks
        ws.send(json.dumps({"type": "reset"}))
        ws.send(json.dumps({"type": "init", "pose": good["pose"]}))
        send_frame(ws, frames[2], 3.0)
        m = recv(ws)
        check_pose_message(m)
        assert m["status"] in ("init", "tracking") and m["frame"] == 3


def frames_received(srv) -> float:
    return metric(srv, 'quatrack_ws_frames_total{result="received"}')


def gate_the_steps(monkeypatch) -> tuple[threading.Event, list[float]]:
    """The sessions' trackers step only once the returned event is set (the test sets it when
    the server has received what it sent: independent of the machine's speed); the list gets
    the time each step was given."""
    from quatrack.service import sessions

    gate, times = threading.Event(), []
    real = sessions.make_tracker

    def gated(*args, **kw):
        tracker = real(*args, **kw)
        step = tracker.step

        def step_waits(image, time_s, *a, **k):
            assert gate.wait(60), "the test never opened the gate"
            times.append(time_s)
            return step(image, time_s, *a, **k)

        tracker.step = step_waits
        return tracker

    monkeypatch.setattr(sessions, "make_tracker", gated)
    return gate, times


def test_back_pressure_processes_the_newest(server, frames, monkeypatch):
    """While a frame is being tracked, newer ones replace each other: the newest is processed
    next. Made independent of the machine's speed: the first tracked frame's step waits until the
    server has received every frame (read from its metrics). Which frame that first one is
    depends on when the worker thread started on it (it takes the newest then, usually frame 0);
    whatever it is, every frame after it but the last is skipped."""
    gate, _ = gate_the_steps(monkeypatch)
    n = 15
    with open_session(server) as ws:
        before = frames_received(server)
        for i, f in enumerate(frames[:n]):
            send_frame(ws, f, i / 30)
        assert wait_until(lambda: frames_received(server) == before + n, timeout=60)
        gate.set()
        msgs = []
        while not msgs or msgs[-1]["frame"] != n - 1:
            msgs.append(recv(ws))
    # one message per frame, in frame order (the contract); the replaced frames' say so
    assert [m["frame"] for m in msgs] == list(range(n))
    got = [m for m in msgs if not m.get("dropped")]
    assert all(m["status"] == "lost" and m["pose"] is None and m["reason"] for m in msgs if m.get("dropped"))
    k = got[0]["frame"]
    assert len(got) == (1 if k == n - 1 else 2)
    assert got[0]["skipped"] == k  # the frames before it, replaced before a thread took one
    if k < n - 1:
        assert (got[1]["frame"], got[1]["skipped"]) == (n - 1, n - 2 - k)
    assert got[-1]["time_s"] == pytest.approx((n - 1) / 30)  # the newest frame's own time


def test_a_frame_waiting_for_a_busy_pool_is_replaced_by_a_newer_one(store, frames):
    """Every CPU thread busy (here: the only one, held by a gated job) while frames arrive: the
    frame processed when a thread frees up is the newest, not the first one that arrived and
    queued for the thread (the mailbox is emptied by the thread, not when the job is queued).
    Independent of the machine's speed: the gate opens once the server has received all."""
    n = 6
    with BackgroundServer(Settings(store=store, threads=1)) as srv, open_session(srv) as ws:
        gate = threading.Event()
        srv.app.state.quatrack.executor.submit(gate.wait, 60)
        before = frames_received(srv)
        for i, f in enumerate(frames[:n]):
            send_frame(ws, f, i / 30)
        assert wait_until(lambda: frames_received(srv) == before + n, timeout=60)
        gate.set()
        msgs = [recv(ws) for _ in range(n)]
    assert [m["frame"] for m in msgs] == list(range(n)) and all(m.get("dropped") for m in msgs[:-1])
    first = msgs[-1]  # the first tracked: the newest
    assert (first["frame"], first["skipped"], first.get("dropped")) == (n - 1, n - 1, None), first


def test_two_sessions_one_fed_garbage(server, frames):
    bad: list[dict] = []

    def garbage():
        with open_session(server) as ws:
            for i in range(12):  # each message answered before the next is sent: nothing is skipped
                ws.send([b"\xff\xd8\xff\xe0 not really", frames[i][:500], b"junk"][i % 3])
                ws.send("{not json" if i % 2 else json.dumps({"type": "nope"}))
                bad.extend([recv(ws), recv(ws)])
            with pytest.raises(TimeoutError):  # and nothing more
                ws.recv(timeout=0.5)

    t = threading.Thread(target=garbage)
    t.start()
    with open_session(server) as ws:
        good = []
        for i, f in enumerate(frames[:12]):
            send_frame(ws, f, i / 30)
            good.append(recv(ws))
    t.join(60)
    assert not t.is_alive()
    assert [m["frame"] for m in good] == list(range(12))
    assert all(m["type"] == "pose" for m in good) and sum(m["status"] == "tracking" for m in good) >= 8
    codes = [m["error"]["code"] for m in bad if m["type"] == "error"]
    assert all(m["type"] == "error" for m in bad)  # garbage never yields a pose
    assert codes.count("bad_message") == 12 and codes.count("unsupported_image") == 4
    assert codes.count("bad_image") == 8 and len(codes) == 24  # the 8 JPEG-looking frames, each decoded


def test_disconnect_mid_stream_leaks_nothing(server, frames):
    for abrupt in (False, True):
        with contextlib.suppress(ConnectionClosed, OSError), open_session(server) as ws:
            for i, f in enumerate(frames[:6]):
                send_frame(ws, f, i / 30)
            if abrupt:  # no closing handshake: the TCP connection just goes away
                ws.socket.shutdown(socket.SHUT_RDWR)
                ws.socket.close()
    assert wait_until(lambda: metric(server, "quatrack_ws_sessions_active") == 0)
    with open_session(server) as ws:  # the server is still fine
        send_frame(ws, frames[0], 0.0)
        check_pose_message(recv(ws))


def test_unknown_object_and_bad_name(server):
    for name, status in (("mug", 404), (".secret", 400)):
        with pytest.raises(InvalidStatus) as err:
            connect(f"{server.ws_url}/v1/objects/{name}/track")
        assert err.value.response.status_code == status
        assert "error" in json.loads(err.value.response.body)


def test_auth_limits_and_idle(strict, frames, monkeypatch):
    url = f"{strict.ws_url}/v1/objects/cookie-box/track"
    monkeypatch.setattr(strict.app.state.quatrack, "clock", lambda: 1000.0)  # injected: a frozen clock
    with pytest.raises(InvalidStatus) as err:
        connect(url)
    assert err.value.response.status_code == 401
    with open_session(strict, additional_headers={"Authorization": "Bearer tok"}) as ws:
        with pytest.raises(InvalidStatus) as err:  # one session at most
            connect(url + "?token=tok")
        assert err.value.response.status_code == 503 and err.value.response.headers["Retry-After"]
        refused = metric_samples(httpx.get(f"{strict.url}/metrics", headers={"Authorization": "Bearer tok"}).text)
        for code in ("unauthorized", "too_many_sessions"):  # the refused handshakes are counted (they were in no metric)
            assert refused[("quatrack_ws_refused_total", frozenset({("code", code)}))] == 1.0, code
        for i in range(10):  # 5 frames/s allowed, and the session's clock stands still: exactly 5 refused
            send_frame(ws, frames[i], i / 30)
        msgs = [recv(ws)]
        while sum(m["type"] == "error" for m in msgs) < 5:  # refusals are immediate; poses may come in between
            msgs.append(recv(ws))
        codes = [m["error"]["code"] for m in msgs if m["type"] == "error"]
        assert codes == ["rate_limited"] * 5
        assert all(m["type"] == "pose" and m["frame"] < 5 for m in msgs if m["type"] != "error")  # only 0-4 accepted
    assert wait_until(lambda: metric(strict, "quatrack_ws_sessions_active", "tok") == 0)
    with connect(url + "?token=tok") as ws:  # idle: closed after 2 s without a message
        ws.send(CAM_ACK)
        assert recv(ws)["type"] == "ready"
        m = recv(ws, timeout=10)
        assert m["error"]["code"] == "idle_timeout"
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=10)


def test_demo_and_bench_commands(store, tmp_path, capsys):
    """``quatrack demo`` writes the track CSV and an overlay; ``quatrack bench serve`` runs (tiny)."""
    from quatrack.cli import main

    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    video = str(Path(__file__).resolve().parent.parent / "examples" / "cookie-box" / "box.mp4")
    camera = str(Path(video).with_name("camera.json"))
    assert main(["demo", "--store", str(store), "--video", video, "--camera", camera, "--max-frames", "8",
                 "--out-dir", str(tmp_path), "--out", str(out), "--overlay", str(overlay)]) == 0
    rows = out.read_text().splitlines()
    assert rows[0] == "frame,time_s,status,tx,ty,tz,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,inliers"
    assert len(rows) == 9 and all(len(r.split(",")) == 17 for r in rows)
    assert rows[1].split(",")[2] == "init" and rows[-1].split(",")[2] == "tracking"
    assert overlay.stat().st_size > 1000
    assert main(["bench", "serve", "--store", str(store), "--video", video, "--camera", camera, "--clients", "1",
                 "--frames", "6", "--workers", "1", "--replicas", "no", "--rest-requests", "2", "--json"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    (run,) = report["setups"]  # one set-up: 1 worker process
    assert run["websocket"][0]["frames_sent"] == 6 and run["rest"]["ok"] == 2


def test_deep_or_huge_json_is_a_typed_error_and_the_session_goes_on(server, frames):
    """'[' * 100000 closed the session silently before (RecursionError taken for a disconnect)."""
    with open_session(server) as ws:
        for text, code in (("[" * 100_000, "too_large"), ("[" * 5_000, "bad_message"), ('{"a":' * 3_000, "bad_message"),
                           (json.dumps({"type": ["x"] * 10_000}), "bad_message")):
            ws.send(text)
            m = recv(ws)
            assert m["type"] == "error" and m["error"]["code"] == code, (text[:20], m)
            assert len(m["error"]["message"]) < 200
        send_frame(ws, frames[0], 0.0)
        m = recv(ws)
        check_pose_message(m)
        assert m["frame"] == 0 and m["status"] == "init"


def test_logs_hold_no_token_and_refusals_are_info(store, frames, capfd):
    secret = "s3cr3t-Token-value"
    settings = Settings(store=store, api_token=secret, max_sessions=1)
    server = BackgroundServer(settings, log_level="info")
    seen: list[logging.LogRecord] = []  # what uvicorn's logger lets through, whatever handlers are configured
    tap = logging.Handler(logging.DEBUG)
    tap.emit = seen.append
    logging.getLogger("uvicorn.error").addHandler(tap)
    with server as srv:
        url = f"{srv.ws_url}/v1/objects/cookie-box/track"
        with connect(f"{url}?token={secret}", open_timeout=20) as ws:
            ws.send(CAM_ACK)
            assert recv(ws)["type"] == "ready"
            with pytest.raises(InvalidStatus) as err:  # full: 503
                connect(f"{url}?token={secret}")
            assert err.value.response.status_code == 503
        refused = {}
        for u, status in ((f"{url}?token=wrong-{secret}", 401), (f"{srv.ws_url}/v1/objects/mug/track?token={secret}", 404)):
            with pytest.raises(InvalidStatus) as err:
                connect(u)
            refused[status] = err.value.response.status_code
        assert refused == {401: 401, 404: 404}
        assert wait_until(lambda: metric(srv, "quatrack_ws_sessions_active", secret) == 0)
    lines = [json.loads(ln) for ln in capfd.readouterr().err.splitlines() if ln.startswith("{")]
    assert lines, "no log lines captured"
    text = "\n".join(json.dumps(ln) for ln in lines)
    assert secret not in text and "token=[redacted]" in text
    assert [ln for ln in lines if ln["level"] in ("error", "critical")] == []
    denials = [ln for ln in lines if ln["msg"] == "websocket refused"]
    assert {(d["status"], d["code"]) for d in denials} == {(503, "too_many_sessions"), (401, "unauthorized"),
                                                           (404, "unknown_object")}
    assert all(d["level"] == "info" and d["reason"] for d in denials)
    logging.getLogger("uvicorn.error").removeHandler(tap)
    assert seen and not [r for r in seen if r.levelno >= logging.ERROR or secret in r.getMessage()]


def test_no_permessage_deflate(server):
    """The server declines permessage-deflate, which clients (websockets, browsers) offer by
    default: the frames are JPEG/PNG/WebP, which deflate cannot shrink, and each one would be
    inflated on the event loop (and deflated by the client) for nothing."""
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=60) as ws:
        assert ws.response.headers.get("Sec-WebSocket-Extensions") is None


def test_stream_lock_step_goes_on_after_a_refused_frame(server, frames):
    # the server refuses "xx" on arrival without numbering it; the client filed the next answer
    # under the refused frame's index and waited for a frame number that never came
    import asyncio

    from quatrack.client import stream

    url = f"{server.ws_url}/v1/objects/cookie-box/track"
    res = asyncio.run(stream(url, CAMERA, [(0, 0.0, frames[0]), (1, 0.1, b"xx"), (2, 0.2, frames[1])], timeout=30.0))
    assert sorted(res.poses) == [0, 2] and [m["frame"] for _, m in sorted(res.poses.items())] == [0, 1]
    assert [e["error"]["code"] for e in res.errors] == ["unsupported_image"]
    with pytest.raises(ValueError, match="fps"):
        asyncio.run(stream(url, CAMERA, [], fps=0))


def test_frames_without_a_time_continue_from_a_client_time(server, frames):
    # after a frame at the client's 100 s, untimed frames got 100.000001, 100.000002, … (the session
    # clock from its start, bumped by 1 µs): frames 0.3 s apart must be about 0.3 s apart
    import time

    with open_session(server) as ws:
        send_frame(ws, frames[0], 100.0)
        times = [recv(ws)["time_s"]]
        for f in frames[1:3]:
            time.sleep(0.3)
            ws.send(f)
            times.append(recv(ws)["time_s"])
    assert times[0] == 100.0 and times[1] - times[0] > 0.2 and times[2] - times[1] > 0.2, times


def test_a_guessed_camera_teaches_the_model_nothing(store):
    """QUATRACK_LEARN_VIEWS on: a session whose camera is a calibration learns views; one whose
    camera says ``"guessed": true`` (the viewer's 60° field of view when none is pasted) does
    not — views lifted with wrong intrinsics would put wrong 3-D points into the stored model.
    ``ready`` says which; a non-boolean ``guessed`` is a ``bad_camera`` error."""
    with BackgroundServer(Settings(store=store, learn_views=("*",), max_sessions=2)) as srv:
        url = f"{srv.ws_url}/v1/objects/cookie-box/track"
        with connect(url, open_timeout=20) as ws:
            ws.send(CAM_ACK)
            assert recv(ws)["learns"] is True
            ws.send(json.dumps({**CAMERA, "ack": True, "guessed": True}))
            ready = recv(ws)
            assert ready["type"] == "ready" and ready["camera_replaced"] and ready["learns"] is False, ready
            ws.send(json.dumps({**CAMERA, "ack": True, "guessed": "yes"}))
            err = recv(ws)
            assert err["type"] == "error" and err["error"]["code"] == "bad_camera" and "guessed" in err["error"]["message"]
    with BackgroundServer(Settings(store=store, max_sessions=1)) as srv:  # learning off: a calibration learns nothing either
        with open_session(srv) as ws:
            ws.send(CAM_ACK)
            assert recv(ws)["learns"] is False


def test_a_rate_below_one_frame_per_second_still_lets_frames_through(tmp_path):
    """QUATRACK_MAX_FPS=0.5 (one frame every 2 s): the bucket held at most 0.5 of a token, so every
    frame of every session was refused as rate_limited."""
    from quatrack.service.sessions import TrackSession

    now = [100.0]
    session = TrackSession(None, "sid", "cookie-box", None, Settings(store=tmp_path, max_fps=0.5), None, None,
                           clock=lambda: now[0])
    assert session._take_token()  # the first frame
    assert not session._take_token()  # the next one at once: above 0.5 frames/s
    now[0] += 1.0
    assert not session._take_token()
    now[0] += 1.0
    assert session._take_token()  # 2 s later
    now[0] += 60.0
    assert session._take_token() and not session._take_token()  # a long pause saves no burst beyond one frame


def test_an_oversized_frame_counts_as_a_frame_error(server, frames):
    """/metrics counts refused frames by result (garbage, undecodable: "error"; too fast:
    "rate_limited"); a frame over QUATRACK_MAX_BODY_BYTES was refused without being counted."""
    name = 'quatrack_ws_frames_total{result="error"}'
    before = metric(server, name)
    with open_session(server) as ws:
        ws.send(b"\xff\xd8\xff" + b"0" * 2_100_000)  # over max_body_bytes
        assert recv(ws)["error"]["code"] == "too_large"
    assert metric(server, name) == before + 1


def test_a_typed_camera_message_with_ack_is_answered(server):
    """{"type": "camera", "camera": {...}, "ack": true} (the typed form the errors name: "use camera,
    frame, reset or init"): its "ack" was read inside the nested camera only, so no "ready" came and
    a client waiting for it waited forever."""
    for msg in ({"type": "camera", "camera": CAMERA, "ack": True}, {"type": "camera", "camera": {**CAMERA, "ack": True}},
                {"type": "camera", **CAMERA, "ack": True}):
        with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
            ws.send(json.dumps(msg))
            assert recv(ws, timeout=20)["type"] == "ready", msg
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
        ws.send(json.dumps({"type": "camera", "camera": CAMERA, "ack": "yes"}))
        assert recv(ws, timeout=20)["error"]["code"] == "bad_camera"


class _Outbox:
    """A stand-in for the session's socket: what it sends, as JSON."""

    def __init__(self) -> None:
        self.sent: list[dict] = []

    async def send_text(self, text: str) -> None:
        self.sent.append(json.loads(text))


def test_the_camera_message_is_checked_by_its_schema_alone(tmp_path):
    """The camera message's forms and fields, ``ack`` included, are :class:`schemas.CameraMessage`'s
    to check (``ack`` was checked by hand in the session, beside the schema's ``guessed``): the
    same answers as before, one place."""
    import ast
    import asyncio
    import inspect

    from quatrack.service import sessions

    literals = {n.value for n in ast.walk(ast.parse(inspect.getsource(sessions))) if isinstance(n, ast.Constant)}
    assert "ack" not in literals  # (no second reading of the message)

    def answers(*msgs) -> list[dict]:
        session = sessions.TrackSession(_Outbox(), "sid", "cookie-box", None, Settings(store=tmp_path), None, None)

        async def run():
            for m in msgs:
                await session._on_text(json.dumps(m))
        asyncio.run(run())
        return session.ws.sent

    cases = [({**CAMERA, "ack": "yes"}, "camera.ack: expected true or false, got 'yes'"),
             ({**CAMERA, "ack": 1}, "camera.ack: expected true or false, got 1"),
             ({"type": "camera", "camera": CAMERA, "ack": "yes"}, "camera.ack: expected true or false, got 'yes'"),
             ({"type": "camera", "camera": {**CAMERA, "ack": None}}, "camera.ack: expected true or false, got None"),
             ({**CAMERA, "guessed": "yes"}, "camera.guessed: expected true or false, got 'yes'"),
             ({"type": "camera", "camera": [1, 2]}, "camera: Input should be a valid dictionary"),
             ({**CAMERA, "fx": "600"}, "camera.fx: ")]
    for msg, message in cases:
        (err,) = answers(msg)
        assert err["type"] == "error" and err["error"]["code"] == "bad_camera", (msg, err)
        assert err["error"]["message"].startswith(message), (msg, err)
    for msg in ({**CAMERA, "ack": True}, {"type": "camera", "camera": CAMERA, "ack": True},
                {"type": "camera", "camera": {**CAMERA, "ack": True}}, {"type": "camera", **CAMERA, "ack": True}):
        (ready,) = answers(msg)
        assert ready["type"] == "ready" and ready["camera_replaced"] is False and ready["learns"] is False, (msg, ready)
    assert answers(CAMERA, {**CAMERA, "ack": False}) == []  # no ack: nothing but per-frame answers
    first, second = answers({**CAMERA, "ack": True}, {**CAMERA, "guessed": True, "ack": True})
    assert second["camera_replaced"] is True


def test_a_client_that_reads_no_answers_is_not_read_either(tmp_path, frames, monkeypatch):
    """A client that sends frames and never reads the answers: the processor's send waits for the
    socket to drain, so every later frame is replaced before its turn and owed a ``dropped``
    answer — kept, image bytes included, in a list that grew for as long as the client sent
    (memory without bound). Now the session stops reading (TCP pushes back on the client) while
    ``MAX_UNANSWERED`` answers are owed, keeps no image bytes for them, and closes a session
    whose client reads nothing for ``idle_timeout_s`` ("stalled")."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from quatrack.service import sessions
    from quatrack.service.metrics import Metrics
    from starlette.websockets import WebSocketState

    class Unread:
        client_state = WebSocketState.CONNECTED

        def __init__(self) -> None:
            self.received = 0

        async def receive(self) -> dict:
            self.received += 1
            if self.received == 1:
                return {"type": "websocket.receive", "text": CAM_TEXT}
            if self.received > 5000:  # (the client gives up: before, all of it had been read)
                return {"type": "websocket.disconnect"}
            await asyncio.sleep(0)
            return {"type": "websocket.receive", "bytes": frames[0]}

        async def send_text(self, text: str) -> None:
            await asyncio.Event().wait()  # nobody reads: the socket never drains

        async def close(self, code: int = 1000) -> None:
            await asyncio.Event().wait()  # (nor lets the close frame out)

    ws = Unread()
    with ThreadPoolExecutor(1) as pool:
        session = sessions.TrackSession(ws, "sid", "cookie-box", None,
                                        Settings(store=tmp_path, max_fps=1e6, idle_timeout_s=0.5), pool, Metrics())
        session._process = lambda item: {"type": "pose", "frame": item.number, "time_s": item.time_s}
        monkeypatch.setattr(sessions, "CLOSE_TIMEOUT_S", 0.1, raising=False)
        outcome = asyncio.run(asyncio.wait_for(session.run(), 60))  # (before: it never ended)
    assert outcome == "stalled"
    assert ws.received <= sessions.MAX_UNANSWERED + 3, ws.received
    assert len(session.dropped) <= sessions.MAX_UNANSWERED and not any(d.data for d in session.dropped)


def test_a_flood_of_controls_never_loses_the_camera(tmp_path):
    """Controls wait for the next frame, at most ``MAX_CONTROLS`` of them, the oldest dropped: a
    camera change followed by as many resets was dropped, and the frames that followed were
    tracked with the previous camera (the session's ``camera`` said the new one)."""
    from quatrack.service import sessions
    from quatrack.service.schemas import CameraMessage

    session = sessions.TrackSession(None, "sid", "cookie-box", None, Settings(store=tmp_path), None, None)
    old, new = CameraMessage(**CAMERA), CameraMessage(**{**CAMERA, "fx": CAMERA["fx"] * 1.1})
    session._control(("camera", old))
    session._control(("camera", new))
    for _ in range(2 * sessions.MAX_CONTROLS):
        session._control(("reset",))
    assert len(session.controls) == sessions.MAX_CONTROLS
    assert [c[1] for c in session.controls if c[0] == "camera"] == [new]
    # frames replaced before their turn pass their controls on to the newer one: still bounded
    merged = sessions._bounded(session.controls + [("camera", old)] + [("reset",)] * sessions.MAX_CONTROLS)
    assert len(merged) == sessions.MAX_CONTROLS and [c[1] for c in merged if c[0] == "camera"] == [old]


def test_frame_ids_are_echoed_in_every_answer_about_the_frame(server, frames, monkeypatch):
    """A frame header's ``"id"`` comes back in every message about that frame — its pose, its
    ``dropped`` answer, its refusal on arrival, an error about its header, an error tracking it —
    so a client sending faster than the tracker runs matches answers to frames without counting.
    Made independent of the machine's speed as the back-pressure test: the first tracked step
    waits until the server has received every frame."""
    gate, _ = gate_the_steps(monkeypatch)
    sent = [({"time_s": 0.0, "id": "a"}, frames[0]),
            ({"time_s": 1 / 30, "id": 1}, b"\x00garbage"),  # refused on arrival
            ({"time_s": -1, "id": 2}, frames[1]),  # the header's time refused: the frame still answered
            ({"id": 3}, frames[2]),  # an id, no time: timed as an untimed frame
            ({"time_s": 5 / 30, "id": -4}, frames[3])]
    with open_session(server) as ws:
        before = frames_received(server)
        for header, data in sent:
            ws.send(json.dumps({"type": "frame", **header}))
            ws.send(data)
        assert wait_until(lambda: frames_received(server) == before + 4, timeout=60)
        gate.set()
        msgs = []
        while not msgs or (msgs[-1].get("id"), msgs[-1]["type"]) != (-4, "pose"):
            msgs.append(recv(ws))
        ws.send(frames[4][: len(frames[4]) // 3])  # (a truncated JPEG: decoding it fails), no id
        msgs.append(recv(ws))
        ws.send(json.dumps({"type": "frame", "time_s": 100.0, "id": "t"}))
        ws.send(frames[4][: len(frames[4]) // 3])
        msgs.append(recv(ws))
        ws.send(json.dumps({"type": "frame", "time_s": 200.0, "id": "big"}))
        ws.send(b"\xff\xd8\xff" + b"0" * 2_100_000)  # over max_body_bytes
        msgs.append(recv(ws))
    by_id: dict = {}
    for m in msgs:
        by_id.setdefault(m.get("id"), []).append(m)
    kinds = {k: [(m["type"], m["error"]["code"] if m["type"] == "error" else m.get("frame")) for m in v]
             for k, v in by_id.items()}
    assert kinds["a"] == [("pose", 0)] and kinds[1] == [("error", "unsupported_image")], kinds
    assert kinds[2] == [("error", "bad_message"), ("pose", 1)] and kinds[3] == [("pose", 2)], kinds
    assert kinds[-4] == [("pose", 3)] and not by_id[-4][0].get("dropped"), kinds
    assert kinds[None] == [("error", "bad_image")] and kinds["t"] == [("error", "bad_image")], kinds
    assert by_id["t"][0]["frame"] == 5 and "id" not in by_id[None][0]  # (an error naming its frame, with its id)
    assert kinds["big"] == [("error", "too_large")], kinds
    assert by_id["a"][0]["time_s"] == 0.0 and by_id[-4][0]["time_s"] == pytest.approx(5 / 30)
    assert all(m["type"] == "pose" for k in ("a", 2, 3, -4) for m in by_id[k][-1:])


def test_without_ids_no_answer_has_one(server, frames):
    """Backward compatible: a client that sends no id gets exactly the messages of before, none
    with an ``"id"`` key (poses, refusals, header errors, tracking errors)."""
    with open_session(server) as ws:
        send_frame(ws, frames[0], 0.0)
        ws.send(b"\x00garbage")
        ws.send(json.dumps({"type": "frame", "time_s": -1}))
        ws.send(frames[1][:500])
        msgs = [recv(ws) for _ in range(4)]
    codes = sorted(m["error"]["code"] if m["type"] == "error" else m["type"] for m in msgs)
    assert codes == ["bad_image", "bad_message", "pose", "unsupported_image"], msgs
    assert not any("id" in m for m in msgs), msgs


def test_frame_ids_of_the_wrong_type_are_refused(tmp_path):
    """An id is an integer a JavaScript client reads back exactly (``|id| ≤ 2**53 - 1``, not a
    boolean) or a string of at most 64 characters; anything else is ``bad_message`` naming
    ``'id'``, and the header is ignored whole (no time, no id), as one with a bad ``time_s``."""
    import asyncio

    from quatrack.service import sessions

    def answers(*msgs) -> tuple[list[dict], sessions.TrackSession]:
        session = sessions.TrackSession(_Outbox(), "sid", "cookie-box", None, Settings(store=tmp_path), None, None)

        async def run():
            for m in (CAMERA, *msgs):
                await session._on_text(json.dumps(m))
        asyncio.run(run())
        return session.ws.sent, session

    for bad in (True, 1.5, None, [1], {"k": 1}, 2**53, -(2**53), "x" * 65):
        (err,), session = answers({"type": "frame", "time_s": 1.0, "id": bad})
        assert err["error"]["code"] == "bad_message" and "'id'" in err["error"]["message"] and "id" not in err, (bad, err)
        assert (session.header_time, session.header_id) == (None, None), bad
    for good in (0, -7, 2**53 - 1, "", "cam0/frame-12", "é" * 64):
        sent, session = answers({"type": "frame", "time_s": 1.0, "id": good})
        assert sent == [] and (session.header_time, session.header_id) == (1.0, good), (good, sent)
    sent, session = answers({"type": "frame", "id": 9})  # an id alone: an untimed frame's header
    assert sent == [] and (session.header_time, session.header_id) == (None, 9)
    (err,), _ = answers({"type": "frame"})  # neither: refused as before
    assert err["error"]["code"] == "bad_message" and "time_s" in err["error"]["message"] and "id" not in err
    (err,), session = answers({"type": "frame", "id": 1}, {"type": "frame", "time_s": 1.0, "id": 2})
    assert (err["error"]["code"], err["id"]) == ("out_of_order", 2) and session.header_id == 2, err


def test_an_untimed_frame_is_timed_at_its_arrival_not_when_tracked(server, frames, monkeypatch):
    """A frame without a time is timed by the session's clock when it arrives: one that waits in
    the mailbox while the tracker is busy, then is tracked, keeps its arrival time (and so does a
    frame replaced before its turn), whatever the clock says when a thread takes it. The clock is
    the test's: frames arrive at 10, 11 and 12 s, and are tracked at 1000 s."""
    gate, stepped = gate_the_steps(monkeypatch)
    now = [10.0]
    monkeypatch.setattr(server.app.state.quatrack, "clock", lambda: now[0])
    with open_session(server) as ws:
        before = frames_received(server)
        for k, f in enumerate(frames[:3]):
            now[0] = 10.0 + k
            ws.send(f)
            assert wait_until(lambda: frames_received(server) == before + k + 1, timeout=60)
        now[0] = 1000.0
        gate.set()
        msgs = [recv(ws) for _ in range(3)]
    assert [(m["frame"], m["time_s"]) for m in msgs] == [(0, 0.0), (1, 1.0), (2, 2.0)], msgs
    assert stepped[-1] == 2.0 and set(stepped) <= {0.0, 1.0, 2.0}, stepped  # (the tracker's times too)


def test_an_init_with_a_time_that_is_no_number_is_refused(tmp_path):
    """``{"type": "init", "pose", "time_s"}`` whose ``time_s`` is no finite number (a string, a
    boolean, a number too large for a float) was taken as an init without a time — the pose put
    at the next frame, without a word. It is ``bad_message`` and the init is not queued; a
    number, ``null`` or no ``time_s`` are taken as before."""
    import asyncio

    from quatrack.service import sessions

    pose = {"q_wxyz": [1, 0, 0, 0], "t": [0, 0, 50]}

    def answers(text: str) -> tuple[list[dict], list]:
        session = sessions.TrackSession(_Outbox(), "sid", "cookie-box", None, Settings(store=tmp_path), None, None)

        async def run():
            for t in (CAM_TEXT, text):
                await session._on_text(t)
        asyncio.run(run())
        return session.ws.sent, [c for c in session.controls if c[0] == "init"]

    for bad in ('"soon"', "true", "[1]", "1" + "0" * 400, "NaN", "Infinity"):
        (err,), inits = answers('{"type": "init", "pose": %s, "time_s": %s}' % (json.dumps(pose), bad))
        assert err["error"]["code"] == "bad_message" and "time_s" in err["error"]["message"] and not inits, (bad, err)
    for good, ts in (', "time_s": 2.5', 2.5), (', "time_s": null', None), ("", None):
        sent, inits = answers('{"type": "init", "pose": %s%s}' % (json.dumps(pose), good))
        assert sent == [] and [c[3] for c in inits] == [ts], (good, sent)


def test_a_client_that_leaves_before_the_handshake_ends_is_disconnected_not_an_error(server, monkeypatch):
    """A client giving up while the server loads the session's model (its handshake timeout):
    the server's accept then fails (uvicorn's ``ClientDisconnected``), and the session was
    counted ``outcome="error"``, a server fault on the operator's dashboards. It is
    ``"disconnected"``. The model's loading is held by the test until the client has left."""
    registry = server.app.state.quatrack.registry
    real, left = registry.get, threading.Event()

    def held(name):
        assert left.wait(60)
        return real(name)

    monkeypatch.setattr(registry, "get", held)
    name = 'quatrack_ws_sessions_total{outcome="%s"}'
    before = {o: metric(server, name % o) for o in ("error", "disconnected")}
    with pytest.raises(TimeoutError):
        connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=0.3)
    left.set()
    assert wait_until(lambda: metric(server, name % "disconnected") == before["disconnected"] + 1)
    assert metric(server, name % "error") == before["error"]


def test_a_session_ends_after_its_tracker_step_in_flight(tmp_path, frames, monkeypatch):
    """The client leaves while its frame is being tracked: the session's end stored the learned
    views (``store_session_views``) at once, reading the tracker on another thread while the
    worker still stepped it — the tracker used by two threads at once, the step's views lost.
    The end now waits for the step. Here the step waits (at most 2 s) for the store to start;
    the store says whether the step was still running."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from quatrack.service import sessions
    from quatrack.service.metrics import Metrics
    from starlette.websockets import WebSocketState

    started, stored = threading.Event(), threading.Event()
    stepping, seen = [False], []

    class Leaves:
        client_state = WebSocketState.DISCONNECTED

        def __init__(self) -> None:
            self.script = [{"type": "websocket.receive", "text": CAM_TEXT}, {"type": "websocket.receive", "bytes": frames[0]}]

        async def receive(self) -> dict:
            if self.script:
                return self.script.pop(0)
            assert await asyncio.to_thread(started.wait, 30)  # (the frame is being tracked)
            return {"type": "websocket.disconnect"}

        async def send_text(self, text: str) -> None:
            pass

    def step(item):
        stepping[0] = True
        started.set()
        stored.wait(2.0)  # (set by the store if it runs before the step ends)
        stepping[0] = False
        return {"type": "pose", "frame": item.number, "time_s": item.time_s}

    async def store(session):
        seen.append(stepping[0])
        stored.set()

    monkeypatch.setattr(sessions, "store_session_views", store)
    with ThreadPoolExecutor(2) as pool:
        session = sessions.TrackSession(Leaves(), "sid", "cookie-box", None, Settings(store=tmp_path), pool, Metrics())
        session._process = step
        assert asyncio.run(asyncio.wait_for(session.run(), 60)) == "closed"
    assert seen == [False]


def test_a_camera_with_a_misspelt_field_is_a_bad_camera(server):
    """Without "fx" the message was not taken for a camera at all: "camera_required" answered a camera."""
    with connect(f"{server.ws_url}/v1/objects/cookie-box/track", open_timeout=20) as ws:
        ws.send(json.dumps({k: v for k, v in CAMERA.items() if k != "fx"} | {"fxx": CAMERA["fx"]}))
        m = recv(ws)
        assert m["type"] == "error" and m["error"]["code"] == "bad_camera", m
        assert "did you mean 'fx'" in m["error"]["message"]
        ws.send(json.dumps({k: v for k, v in CAMERA.items() if k != "fx"}))  # a field missing: named too
        m = recv(ws)
        assert m["error"]["code"] == "bad_camera" and "fx" in m["error"]["message"], m

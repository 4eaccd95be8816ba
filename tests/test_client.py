"""The Python client (``quatrack.client``), the runnable examples in docs/examples/, ``?format=ros``
and ``quatrack demo``, against a real server on a loopback port (with a token)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from quatrack.testing.scenes import EXAMPLE, example_store
from quatrack.cli import main
from quatrack.client import Client, QuatrackError, base_urls
from quatrack.recognition import trackio
from quatrack.service.schemas import LocateOut, TrackMessage
from quatrack.service.server import BackgroundServer, free_port
from quatrack.service.settings import Settings

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "client-test-token"
CAMERA = EXAMPLE / "camera.json"


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store(), api_token=TOKEN)) as srv:
        yield srv


@pytest.fixture(scope="module")
def frames():
    with trackio.open_frames(video=str(EXAMPLE / "box.mp4"), max_frames=8) as src:
        return [(t, image) for _, t, image in src]


def test_pose_and_track_typed(server, frames):
    with Client(server.url, object="cookie-box", token=TOKEN) as c:
        assert [o.name for o in c.objects().objects] == ["cookie-box"]
        found = c.pose(frames[0][1], str(CAMERA))
        assert isinstance(found, LocateOut) and found.found and 20 < found.pose.t[2] < 200
        msgs = list(c.track(frames, CAMERA))
    assert all(isinstance(m, TrackMessage) for m in msgs)
    assert [m.frame for m in msgs] == list(range(8)) and [m.status for m in msgs] == ["init"] + ["tracking"] * 7
    assert [m.time_s for m in msgs] == pytest.approx([t for t, _ in frames])
    assert np.linalg.norm(np.array(msgs[0].pose.t) - found.pose.t) < 2.0  # the same box, the same place


def test_errors_carry_the_servers_code(server, frames):
    image = frames[0][1]
    with Client(server.url, object="no-such-box", token=TOKEN) as c:
        with pytest.raises(QuatrackError) as e:
            c.pose(image, CAMERA)
        assert (e.value.code, e.value.status) == ("unknown_object", 404)
        with pytest.raises(QuatrackError) as e:
            next(c.track([image], CAMERA))
        assert (e.value.code, e.value.status) == ("unknown_object", 404)
    with Client(server.url, object="cookie-box", token="wrong") as c:
        with pytest.raises(QuatrackError) as e:
            c.pose(image, CAMERA)
        assert (e.value.code, e.value.status) == ("unauthorized", 401)
        with pytest.raises(QuatrackError) as e:
            next(c.track([image], CAMERA))
        assert e.value.code == "unauthorized"
    with Client(server.url, object="cookie-box", token=TOKEN) as c:
        with pytest.raises(QuatrackError) as e:
            next(c.track([image], {"width": 640, "height": 480, "fx": -1, "fy": 600, "cx": 320, "cy": 240}))
        assert e.value.code == "bad_camera"
    with Client(f"http://127.0.0.1:{free_port()}", object="cookie-box") as c:
        with pytest.raises(QuatrackError) as e:
            c.objects()
        assert e.value.code == "unreachable"
    assert base_urls("ws://h:1/") == ("http://h:1", "ws://h:1") and base_urls("https://h") == ("https://h", "wss://h")
    with pytest.raises(ValueError, match="without a path"):
        base_urls("http://h:1/v1/objects")


def test_ros_format_round_trips(server, frames):
    import httpx

    from quatrack.tracking.pose import Pose

    with Client(server.url, object="cookie-box", token=TOKEN) as c:
        msgs = list(c.track(frames[:4], CAMERA, ros_mesh_unit="cm"))
    for m in msgs:
        pose, cov = trackio.pose_from_ros(m.ros, "cm")
        assert pose.allclose(Pose(m.pose.q_wxyz, m.pose.t), atol=1e-9)
        assert m.ros["pose"]["pose"]["position"]["z"] == pytest.approx(m.pose.t[2] / 100)  # metres
        if m.covariance is not None:
            assert np.allclose(cov, m.covariance)
    headers = {"Authorization": f"Bearer {TOKEN}"}
    files = {"image": ("f.jpg", _jpeg(frames[0][1])),
             "camera": (None, CAMERA.read_text())}
    r = httpx.post(f"{server.url}/v1/objects/cookie-box/pose?format=ros&mesh_unit=mm", files=files, headers=headers)
    body = r.json()
    assert r.status_code == 200 and body["found"]
    pose, _ = trackio.pose_from_ros(body["ros"], "mm")
    assert pose.allclose(Pose(body["pose"]["q_wxyz"], body["pose"]["t"]), atol=1e-9)
    r = httpx.post(f"{server.url}/v1/objects/cookie-box/pose?format=ros", files=files, headers=headers)
    assert r.status_code == 422 and r.json()["error"]["code"] == "bad_format"
    plain = httpx.post(f"{server.url}/v1/objects/cookie-box/pose", files=files, headers=headers).json()
    assert "ros" not in plain  # the contract's object unchanged without format=ros
    # POST /v1/pose (every object) takes format=ros as well: each object found carries "ros" (was ignored)
    every = httpx.post(f"{server.url}/v1/pose?format=ros&mesh_unit=mm", files=files, headers=headers).json()
    assert [o["object"] for o in every["objects"]] == ["cookie-box"], every
    pose, _ = trackio.pose_from_ros(every["objects"][0]["ros"], "mm")
    assert pose.allclose(Pose(every["objects"][0]["pose"]["q_wxyz"], every["objects"][0]["pose"]["t"]), atol=1e-9)
    r = httpx.post(f"{server.url}/v1/pose?format=ros", files=files, headers=headers)
    assert r.status_code == 422 and r.json()["error"]["code"] == "bad_format"
    assert "ros" not in httpx.post(f"{server.url}/v1/pose", files=files, headers=headers).json()["objects"][0]


def _jpeg(image) -> bytes:
    import cv2

    return cv2.imencode(".jpg", image)[1].tobytes()


def _run_example(name: str, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "QUATRACK_API_TOKEN": TOKEN}
    return subprocess.run([sys.executable, str(ROOT / "docs" / "examples" / name), *args], env=env,
                          capture_output=True, text=True, timeout=300)


def test_the_client_example_runs(server):
    p = _run_example("client_track.py", "--url", server.url, "--frames", "6")
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    assert lines[0].startswith("pose: found=True") and len(lines) == 7
    assert lines[1].startswith("frame 0 init") and all(" tracking " in x for x in lines[2:])


def test_the_ros2_example_prints_messages_without_rclpy(server):
    p = _run_example("ros2_republish.py", "--url", server.url, "--mesh-unit", "cm", "--max-frames", "3", "--dry-run")
    assert p.returncode == 0, p.stderr
    msgs = [json.loads(x) for x in p.stdout.splitlines()]
    assert len(msgs) == 3 and all(len(m["pose"]["covariance"]) == 36 for m in msgs)
    assert all(set(m["pose"]["pose"]["orientation"]) == {"x", "y", "z", "w"} for m in msgs)
    # the printed messages are what would be published: --frame-id and --now apply to them too
    p = _run_example("ros2_republish.py", "--url", server.url, "--mesh-unit", "cm", "--max-frames", "2", "--dry-run",
                     "--frame-id", "cam_optical", "--now")
    assert p.returncode == 0, p.stderr
    msgs = [json.loads(x) for x in p.stdout.splitlines()]
    assert len(msgs) == 2 and all(m["header"]["frame_id"] == "cam_optical" for m in msgs)
    assert all(m["header"]["stamp"]["sec"] > 1_000_000_000 for m in msgs)  # the clock, not the frames' 0 s


# --- quatrack demo -----------------------------------------------------------------------------

def test_demo_against_a_server_from_any_folder(server, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    empty = tmp_path / "empty-store"
    rc = main(["demo", "--url", server.ws_url, "--token", TOKEN, "--store", str(empty), "--max-frames", "6", "--quiet"])
    out = capsys.readouterr().out
    assert rc == 0 and "6 frames sent, 6 tracked answers" in out
    folder = tmp_path / "quatrack-demo"
    assert sorted(p.name for p in folder.iterdir()) == ["overlay.mp4", "plot.png", "poses.csv"]  # mesh from the server
    rows = (folder / "poses.csv").read_text().splitlines()
    assert rows[0] == trackio.CSV_HEADER and len(rows) == 7 and rows[1].split(",")[2] == "init"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["quatrack-demo"]  # nothing else written


@pytest.mark.parametrize("case, message", [
    ("unknown-object", "--object no-such-box: the server has no such object (it holds cookie-box)"),
    ("http-url-with-path", "without a path"),
    ("no-token", "needs a token"),
    ("wrong-token", "refused the token of --token"),
    ("not-a-url", "give the server's address"),
    ("nobody-there", "no server answers there"),
    ("local-untrained", "(no such folder): train it first"),
    ("camera-of-another-size", "refused every frame of --video"),
])
def test_demo_errors_are_one_line(server, tmp_path, monkeypatch, capsys, case, message):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("QUATRACK_API_TOKEN", raising=False)
    args = ["demo", "--url", server.url, "--token", TOKEN, "--store", str(tmp_path / "s"), "--max-frames", "2"]
    if case == "unknown-object":  # (the bundled video by its path: without --video another object is refused)
        args += ["--object", "no-such-box", "--video", str(EXAMPLE / "box.mp4")]
    elif case == "http-url-with-path":
        args[2] = server.url + "/v1/objects/cookie-box/track"
    elif case == "no-token":
        args = args[:3] + args[5:]
    elif case == "wrong-token":  # (said "needs a token" when one was given)
        args[4] = "not-" + TOKEN
    elif case == "not-a-url":
        args[2] = "127.0.0.1:8000"
    elif case == "nobody-there":
        args[2] = f"ws://127.0.0.1:{free_port()}"
    elif case == "local-untrained":
        args = args[:1] + args[3:]
    elif case == "camera-of-another-size":  # (every frame refused: exit 0 and a CSV of lost rows, no word why)
        cam = json.loads((EXAMPLE / "camera.json").read_text())
        cam.update(width=320, height=240, fx=cam["fx"] / 2, fy=cam["fy"] / 2, cx=cam["cx"] / 2, cy=cam["cy"] / 2)
        (tmp_path / "half.json").write_text(json.dumps(cam))
        args += ["--camera", str(tmp_path / "half.json")]
    rc = main(args)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("quatrack demo: error:") and message in err, err
    assert "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "quatrack-demo").exists()


def test_async_client_gives_the_same_answers(server, frames):
    import asyncio

    from quatrack.client import AsyncClient

    async def go():
        async with AsyncClient(server.url, object="cookie-box", token=TOKEN) as c:
            found = await c.pose(frames[0][1], CAMERA)
            msgs = [m async for m in c.track(frames[:5], CAMERA)]
            try:
                await c.pose(frames[0][1], CAMERA, object="no-such-box")
            except QuatrackError as exc:
                return found, msgs, exc.code
        return found, msgs, None

    found, msgs, code = asyncio.run(go())
    assert found.found and code == "unknown_object"
    assert [m.status for m in msgs] == ["init"] + ["tracking"] * 4 and [m.frame for m in msgs] == list(range(5))


def test_a_server_that_goes_away_or_stays_silent_is_a_quatrack_error(frames):
    # the server stops mid-stream: "closed" (was websockets' ConnectionClosedError)
    with BackgroundServer(Settings(store=example_store())) as srv:
        c = Client(srv.url, object="cookie-box")
        stream = c.track(frames, CAMERA)
        assert next(stream).frame == 0
    with pytest.raises(QuatrackError) as e:
        list(stream)
    assert e.value.code == "closed", e.value
    c.close()


def test_a_silent_server_is_a_timeout_not_unreachable(frames):
    # connected, then no answer: "timeout" (was TimeoutError "timed out in 0.0s" on the WebSocket
    # and "unreachable" over HTTP); the servers here never answer, so no machine is too fast for it
    import socket
    import threading

    from websockets.sync.server import serve

    done = threading.Event()
    with serve(lambda ws: done.wait(30), "127.0.0.1", 0) as ws_server:
        threading.Thread(target=ws_server.serve_forever, daemon=True).start()
        port = ws_server.socket.getsockname()[1]
        with Client(f"http://127.0.0.1:{port}", object="cookie-box", timeout=1.0) as c:
            with pytest.raises(QuatrackError) as e:
                next(c.track(frames, CAMERA))
        assert e.value.code == "timeout" and "1 s" in e.value.message, e.value
        done.set()
        ws_server.shutdown()
    with socket.socket() as silent:  # accepts (the kernel's backlog) and never reads nor answers
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        with Client(f"http://127.0.0.1:{silent.getsockname()[1]}", object="cookie-box", timeout=1.0) as c:
            with pytest.raises(QuatrackError) as e:
                c.objects()
        assert e.value.code == "timeout", e.value


def test_a_frame_too_large_for_the_socket_is_too_large_not_closed():
    """A frame over twice the server's ``QUATRACK_MAX_BODY_BYTES`` is not read: the server closes
    the socket with 1009 ("message too big"). It was ``"closed"``, as if the server had gone away;
    it is ``"too_large"``, as a smaller frame over the limit (an error message) and REST's 413 are."""
    import threading

    from websockets.sync.server import serve

    def handler(ws):  # as the service: the camera answered, then frames over max_size close (1009)
        ws.recv()
        ws.send(json.dumps({"type": "ready"}))
        for _ in ws:
            pass

    with serve(handler, "127.0.0.1", 0, max_size=10_000) as ws_server:
        threading.Thread(target=ws_server.serve_forever, daemon=True).start()
        port = ws_server.socket.getsockname()[1]
        with Client(f"http://127.0.0.1:{port}", object="cookie-box", timeout=30) as c:
            with pytest.raises(QuatrackError) as e:
                next(c.track([b"\xff\xd8\xff" + b"0" * 20_000], CAMERA))
        ws_server.shutdown()
    assert e.value.code == "too_large" and "exceeds" in e.value.message, e.value


def test_a_real_time_stream_cut_by_the_server_is_closed_not_complete():
    """``stream(..., fps=F)``: the server closing the socket before the last answer (a restart:
    1012) returned the answers so far as if the stream were complete, and the receiving task's
    exception went to stderr as a traceback ("Task exception was never retrieved"). It is a
    QuatrackError ``"closed"``, as in lock-step."""
    import asyncio
    import threading

    from websockets.sync.server import serve

    from quatrack.client import stream

    def handler(ws):  # the camera answered, one frame read, then the server restarts
        ws.recv()
        ws.send(json.dumps({"type": "ready"}))
        ws.recv(), ws.recv()
        ws.close(1012, "service restart")

    with serve(handler, "127.0.0.1", 0) as ws_server:
        threading.Thread(target=ws_server.serve_forever, daemon=True).start()
        url = f"ws://127.0.0.1:{ws_server.socket.getsockname()[1]}/v1/objects/cookie-box/track"
        with pytest.raises(QuatrackError) as e:
            asyncio.run(stream(url, CAMERA, [(0, 0.0, b"\xff\xd8\xff")], fps=10.0, timeout=30.0))
        ws_server.shutdown()
    assert e.value.code == "closed" and "1012" in e.value.message, e.value


def _fake_track_server(batch: bool):
    """A stand-in for the service's track socket, answering as it does with frame ids: a frame
    ``b"refused"`` is refused on arrival (no number), ``b"late"`` has its header refused
    (``out_of_order``) and is still tracked; the others are numbered in arrival order. ``batch``:
    every frame is read before any answer — a client sending faster than the tracker runs —
    and the frames between the first and the newest are replaced (``dropped``)."""
    from websockets.sync.server import serve

    def answers(got):
        out, number, good = [], 0, [k for k, (_, data) in enumerate(got) if data != b"refused"]
        for k, (header, data) in enumerate(got):
            echo = {"id": header["id"]} if "id" in header else {}
            if data == b"refused":
                out.append({"type": "error", "error": {"code": "unsupported_image", "message": "not an image"}, **echo})
                continue
            if data == b"late":
                out.append({"type": "error", "error": {"code": "out_of_order", "message": "not after"}, **echo})
            dropped = batch and k not in (good[0], good[-1])
            out.append({"type": "pose", "frame": number, "time_s": header["time_s"], "status": "lost" if dropped else "tracking",
                        "pose": None, "velocity": None, "covariance": None, "inliers": 0, "latency_ms": 1.0,
                        "skipped": 0, **({"dropped": True} if dropped else {}), **echo})
            number += 1
        return out

    def handler(ws):
        ws.recv()
        ws.send(json.dumps({"type": "ready"}))
        got = []
        for text in ws:
            got.append((json.loads(text), ws.recv()))
            if not batch:
                for m in answers(got)[len(answers(got[:-1])):]:
                    ws.send(json.dumps(m))
            elif got[-1][1] == b"last":
                for m in answers(got):
                    ws.send(json.dumps(m))

    return serve(handler, "127.0.0.1", 0)


@pytest.mark.parametrize("fps", [None, 1000.0])
def test_stream_files_every_answer_under_its_own_index(fps):
    """``stream``: answers filed by the frame id the server echoes. Counting slipped: in real
    time, a refusal read after newer frames were sent dropped the newest index, and each later
    answer went under the index of the frame before its own; in lock-step, an error about a
    frame's header was taken for the frame's answer, and the stream ended before the last one.
    Each frame's time here is its index's, so a misfiled answer shows."""
    import asyncio
    import threading

    from quatrack.client import stream

    kinds = [b"ok", b"refused", b"refused", b"ok", b"late", b"ok", b"refused", b"ok", b"last"]
    frames = [(100 + i, i / 30, data) for i, data in enumerate(kinds)]
    with _fake_track_server(batch=fps is not None) as ws_server:
        threading.Thread(target=ws_server.serve_forever, daemon=True).start()
        url = f"ws://127.0.0.1:{ws_server.socket.getsockname()[1]}/v1/objects/cookie-box/track"
        res = asyncio.run(stream(url, CAMERA, frames, fps=fps, timeout=30.0))
        ws_server.shutdown()
    tracked = [100, 108] if fps else [100 + i for i, d in enumerate(kinds) if d != b"refused"]
    assert sorted(res.poses) == tracked, res.poses
    assert all(m["time_s"] == pytest.approx((idx - 100) / 30) for idx, m in res.poses.items()), res.poses
    assert sorted(e["error"]["code"] for e in res.errors) == ["out_of_order"] + ["unsupported_image"] * 3
    assert sorted(zip(res.error_index, (e["error"]["code"] for e in res.errors))) == [
        (101, "unsupported_image"), (102, "unsupported_image"), (104, "out_of_order"), (106, "unsupported_image")]
    assert res.sent == len(kinds) and len(res.rtt_ms) == len(tracked)


def test_a_real_time_stream_through_skips_and_refusals_keeps_every_index(server, frames):
    """End to end: frames sent faster than the tracker runs, every other one refused on arrival
    (not an image): each answer filed comes with its own frame's time, and the newest is
    tracked."""
    import asyncio

    from quatrack.client import stream

    good = [_jpeg(image) for _, image in frames]
    sent = [(i, i / 30, good[i // 2] if i % 2 == 0 else b"\x00not an image") for i in range(2 * len(good) - 1)]
    url = f"{server.ws_url}/v1/objects/cookie-box/track"
    res = asyncio.run(stream(url, CAMERA, sent, fps=1000.0, token=TOKEN, timeout=60.0))
    assert res.poses and all(i % 2 == 0 for i in res.poses) and len(sent) - 1 in res.poses, sorted(res.poses)
    assert all(m["time_s"] == pytest.approx(i / 30) and m["id"] == i for i, m in res.poses.items()), res.poses
    assert sorted(e["id"] for e in res.errors) == list(range(1, len(sent), 2)), res.errors
    assert res.error_index == [e["id"] for e in res.errors]  # (here the caller's index is the frame's place)


@pytest.mark.parametrize("answer", ["<html>502 Bad Gateway</html>", "[1, 2]", '{"type": "error", "error": "boom"}'])
def test_a_message_that_is_no_json_object_is_a_protocol_error(frames, answer):
    """Something at the address that is not the service (a proxy's error page, another program)
    answering a frame with a text that is not a JSON object: ``QuatrackError("protocol")`` from
    ``Client.track`` and ``stream`` in both modes (it was json's ``JSONDecodeError`` or an
    ``AttributeError`` from inside the client); an error whose ``error`` is no object keeps its
    type, ``"error"``."""
    import asyncio
    import threading

    from websockets.sync.server import serve

    from quatrack.client import stream

    def handler(ws):
        ws.recv()
        ws.send(json.dumps({"type": "ready"}))
        for message in ws:
            if isinstance(message, bytes):
                ws.send(answer)

    with serve(handler, "127.0.0.1", 0) as ws_server:
        threading.Thread(target=ws_server.serve_forever, daemon=True).start()
        port = ws_server.socket.getsockname()[1]
        url = f"ws://127.0.0.1:{port}/v1/objects/cookie-box/track"
        codes = []
        with Client(f"http://127.0.0.1:{port}", object="cookie-box", timeout=30) as c:
            with pytest.raises(QuatrackError) as e:
                list(c.track([b"\xff\xd8\xff"], CAMERA))
            codes.append(e.value.code)
        for fps in (None, 100.0):
            if answer.startswith("{"):  # (an error message, however malformed, is no protocol error in stream)
                break
            with pytest.raises(QuatrackError) as e:
                asyncio.run(stream(url, CAMERA, [(0, 0.0, b"\xff\xd8\xff")], fps=fps, timeout=30.0))
            codes.append(e.value.code)
        ws_server.shutdown()
    assert codes == (["error"] if answer.startswith("{") else ["protocol"] * 3), codes

"""``quatrack bench serve``: the service under load, on loopback only.

Set-ups: ``quatrack serve`` with 1 worker process, with N (default: the number of cores), and —
when nginx is installed — two 1-worker replicas behind nginx with ``deploy/nginx.conf``.
``--workers 1,2,p2`` adds the other process model as a prototype (:mod:`.serve_pool`: one event
loop process with a pool of 2 tracking processes behind it), to compare the two. Against
each, S = 1, 2, 4, 8, 16 WebSocket clients stream the first frames of ``box.mp4`` at 30 fps in real
time, as cameras would; the server tracks the newest frame of each session and drops the stale
ones. Reported per run: per-stream achieved fps (answers / s), latency (send → answer) p50/p99,
frames dropped (sent but never answered: skipped by the server as stale), total frames/s
processed, ``/healthz`` p50/p99 probed every 50 ms during the run from a separate process (and
from the clients' own event loop, for comparison: that one also waits for the clients), where a
frame's latency goes (wait / step / io, see :func:`_breakdown`), the server's CPU time per processed
frame and cores used (:func:`cpu_seconds`: the measure other jobs on the machine change least),
RSS of every worker process.
Then REST ``pose`` requests/s. Frames are JPEG-encoded before the clock starts, so the clients'
own CPU use is small — but they share the machine with the server.
"""

from __future__ import annotations

import argparse


def _pct(values, q) -> float:
    import numpy as np

    return float(np.percentile(values, q)) if len(values) else float("nan")


def _rss_mb(pids: list[int]) -> list[float]:
    out = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/status") as f:
                kb = next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))
            out.append(round(kb / 1024, 1))
        except (OSError, StopIteration):
            pass
    return out


def cpu_seconds(pids: list[int]) -> float:
    """User + system CPU time the processes ``pids`` have used so far (Linux /proc/PID/stat, fields
    14 and 15, in clock ticks): the server's own cost, whatever else the machine runs meanwhile."""
    import os

    total = 0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


async def _streams(url: str, http_url: str, camera: dict, frames: list, n: int, fps: float,
                   stagger_s: float = 0.0) -> dict:
    """One run of ``n`` concurrent streams. ``stagger_s`` > 0 starts stream k at k × stagger_s
    (cameras that come online one after another) instead of all at once (a burst, e.g. cameras
    reconnecting after a restart): ``quatrack serve --workers N`` places a session by the
    sessions its workers hold *when it arrives* (service/placement.py), which a burst outruns."""
    import asyncio
    import time
    from collections import Counter

    import httpx

    from quatrack.client import stream

    probes: list[float] = []

    async def probe():  # the same probe from the clients' own event loop (it waits for them too)
        async with httpx.AsyncClient(timeout=30) as client:
            while True:
                t0 = time.perf_counter()
                await client.get(f"{http_url}/healthz")
                probes.append((time.perf_counter() - t0) * 1e3)
                await asyncio.sleep(PROBE_EVERY_S)

    lags: list[float] = []

    async def lag():  # how late the clients' own event loop wakes up: their share of "io"
        while True:
            t0 = time.perf_counter()
            await asyncio.sleep(0.01)
            lags.append((time.perf_counter() - t0 - 0.01) * 1e3)

    owners: dict[int, int] = {}

    async def placement():  # which server process holds each connection, once all are open
        await asyncio.sleep((n - 1) * stagger_s + min(1.5, len(frames) / fps / 2))
        owners.update(await _connection_owners(http_url))

    prober = asyncio.create_task(probe())
    lagger = asyncio.create_task(lag())
    placer = asyncio.create_task(placement())
    outside = _Prober(http_url)  # the server's answer time, not the clients' loop's
    t0 = time.perf_counter()
    async def one(k: int):
        if stagger_s > 0:
            await asyncio.sleep(k * stagger_s)
        return await stream(url, camera, frames, fps=fps)

    results = await asyncio.gather(*(one(k) for k in range(n)), return_exceptions=True)
    wall = time.perf_counter() - t0
    prober.cancel()
    lagger.cancel()
    placer.cancel()
    alone = outside.stop()
    refused = [r for r in results if isinstance(r, BaseException)]
    results = [r for r in results if not isinstance(r, BaseException)]
    rtt = [x for r in results for x in r.rtt_ms]
    # the same without the frames that ran recognition (each session's first, and re-finds): the
    # steady state of tracking, which a p99 over few frames per session cannot show
    rtt_tracking = [x for r in results for m, x in zip(r.poses.values(), r.rtt_ms) if m.get("status") == "tracking"]
    processed = sum(len(r.poses) for r in results)
    sent = sum(r.sent for r in results)
    per_stream = [len(r.poses) / max(r.wall_s, 1e-9) for r in results]
    return {
        "clients": n, "refused": len(refused), "frames_sent": sent, "processed": processed,
        "dropped": sent - processed, "errors": sum(len(r.errors) for r in results),
        "error_codes": dict(Counter(e.get("error", {}).get("code", "?") for r in results for e in r.errors)),
        "tracking": sum(m["status"] == "tracking" for r in results for m in r.poses.values()),
        "fps_per_stream_min": min(per_stream, default=0.0), "fps_per_stream_mean": sum(per_stream) / max(len(per_stream), 1),
        "total_fps": processed / wall,
        "latency_p50_ms": _pct(rtt, 50), "latency_p99_ms": _pct(rtt, 99),
        "latency_tracking_p50_ms": _pct(rtt_tracking, 50), "latency_tracking_p99_ms": _pct(rtt_tracking, 99),
        "healthz_p50_ms": _pct(alone, 50), "healthz_p99_ms": _pct(alone, 99), "healthz_max_ms": max(alone, default=float("nan")),
        "healthz_probes": len(alone),
        "healthz_in_client_p50_ms": _pct(probes, 50), "healthz_in_client_p99_ms": _pct(probes, 99),
        "client_loop_lag_p50_ms": _pct(lags, 50), "client_loop_lag_p99_ms": _pct(lags, 99),
        **_breakdown(results),
        # sessions per server process (largest first): which worker the kernel gave each
        "sessions_per_process": sorted(Counter(owners[r.local_port] for r in results if r.local_port in owners).values(),
                                       reverse=True),
    }


async def _connection_owners(http_url: str) -> dict[int, int]:
    """{client port: server pid} of the established connections to the server's port (Linux
    ``ss``; empty where it is missing). The kernel hands each connection to one worker process."""
    import asyncio
    import re
    from urllib.parse import urlsplit

    port = urlsplit(http_url).port
    try:
        proc = await asyncio.create_subprocess_exec("ss", "-tnpH", "state", "established", f"( sport = :{port} )",
                                                    stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
        out, _ = await proc.communicate()
    except OSError:
        return {}
    owners = {}
    for line in out.decode(errors="replace").splitlines():
        peer = re.search(r"\s\S+:(\d+)\s+users:", line)
        pid = re.search(r"pid=(\d+)", line)
        if peer and pid:
            owners[int(peer.group(1))] = int(pid.group(1))
    return owners


def _breakdown(results) -> dict:
    """Where a processed frame's latency went, from its answer: ``wait`` = frame arrival at the
    server → its step starts (the frame waiting for its session's previous step, a free thread,
    and the interpreter lock, plus JPEG decoding), ``step`` = the tracker's own ``timings_ms.total``,
    ``io`` = client send → answer received minus the server's ``latency_ms`` (socket transfer,
    both event loops, JSON). Each as p50 / p99 over all processed frames (ms)."""
    wait, step, io = [], [], []
    for r in results:
        for msg, rtt in zip(r.poses.values(), r.rtt_ms):  # both in the order the answers came
            server = float(msg.get("latency_ms") or 0.0)
            total = float((msg.get("timings_ms") or {}).get("total", 0.0))
            wait.append(max(server - total, 0.0))
            step.append(total)
            io.append(max(rtt - server, 0.0))
    return {f"{k}_{q}_ms": _pct(v, int(q[1:])) for k, v in (("wait", wait), ("step", step), ("io", io))
            for q in ("p50", "p99")}


PROBE_EVERY_S = 0.05


class _Prober:
    """``GET /healthz`` every 50 ms from a separate process (one keep-alive connection), so that
    a probe measures the server — not the bench's own event loop, busy with N clients' frames."""

    def __init__(self, http_url: str) -> None:
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        self._stop = ctx.Event()
        self._parent, child = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_probe_loop, args=(http_url, child, self._stop), daemon=True)
        self.proc.start()

    def stop(self) -> list[float]:
        self._stop.set()
        out = self._parent.recv() if self._parent.poll(30) else []
        self.proc.join(10)
        return out


def _probe_loop(http_url: str, conn, stop) -> None:
    import http.client
    import time
    from urllib.parse import urlsplit

    u = urlsplit(http_url)
    out: list[float] = []
    client = http.client.HTTPConnection(u.hostname, u.port, timeout=30)
    while not stop.is_set():
        t0 = time.perf_counter()
        try:
            client.request("GET", "/healthz")
            client.getresponse().read()
            out.append((time.perf_counter() - t0) * 1e3)
        except (OSError, http.client.HTTPException):
            client.close()
            client = http.client.HTTPConnection(u.hostname, u.port, timeout=30)
        stop.wait(PROBE_EVERY_S)
    conn.send(out)


async def _rest(url: str, name: str, camera: dict, images: list[bytes], total: int, concurrency: int) -> dict:
    import asyncio
    import time

    import httpx

    params = {k: camera[k] for k in ("fx", "fy", "cx", "cy")}
    lat, statuses = [], []
    queue = list(range(total))

    async def worker(client):
        while queue:
            k = queue.pop()
            t0 = time.perf_counter()
            r = await client.post(f"{url}/v1/objects/{name}/pose", content=images[k % len(images)], params=params,
                                  headers={"content-type": "image/jpeg"})
            lat.append((time.perf_counter() - t0) * 1e3)
            statuses.append(r.status_code)

    async with httpx.AsyncClient(timeout=120) as client:
        t0 = time.perf_counter()
        await asyncio.gather(*(worker(client) for _ in range(concurrency)))
        wall = time.perf_counter() - t0
    return {"requests": total, "concurrency": concurrency, "ok": statuses.count(200), "busy_503": statuses.count(503),
            "requests_per_s": total / wall, "latency_p50_ms": _pct(lat, 50), "latency_p99_ms": _pct(lat, 99)}


def _setups(store, workers: list[int], threads: int | None, max_sessions: int, replicas: bool, tmp):
    """(label, context manager yielding (url, ws_url, pids()))."""
    import contextlib
    from pathlib import Path

    from quatrack.service.server import ServeProcess

    env = {"QUATRACK_MAX_SESSIONS": str(max_sessions), "QUATRACK_MAX_PENDING_REQUESTS": "16"}
    if threads is not None:  # (else as quatrack serve: cores ÷ workers)
        env["QUATRACK_THREADS"] = str(threads)

    @contextlib.contextmanager
    def single(n):
        with ServeProcess(store, workers=n, env=env) as srv:
            yield srv.url, srv.ws_url, srv.worker_pids

    @contextlib.contextmanager
    def balanced():
        from quatrack.testing.balancer import Nginx

        with ServeProcess(store, workers=1, env=env) as a, ServeProcess(store, workers=1, env=env) as b, \
                Nginx(Path(tmp) / "nginx", [a.port, b.port]) as lb:
            yield lb.url, lb.ws_url, lambda: a.worker_pids() + b.worker_pids()

    @contextlib.contextmanager
    def pool(n):
        from quatrack.bench.serve_pool import PoolServer

        with PoolServer(store, n, env=env) as srv:
            yield srv.url, srv.ws_url, srv.pids

    out = [(f"{n} worker{'s' if n > 1 else ''}", lambda n=n: single(n)) if isinstance(n, int) else
           (f"1 loop + pool of {n[1:]} (prototype)", lambda n=n: pool(int(n[1:]))) for n in workers]
    if replicas:
        out.append(("2 replicas + nginx", balanced))
    return out


def _check_object(store, name: str, trained_from: str | None = None) -> None:
    """Refuse an ``--object`` the store does not hold (every stream was refused by the server: a
    table of NaN, exit 0), as the other commands say it (:func:`~quatrack.viewsets.store.unknown_object`:
    the nearest name, the objects held); ``trained_from``: the store is the run's own, trained
    from that spec, so it is named instead of its temporary folder."""
    from quatrack.viewsets.store import list_models, names_hint, unknown_object

    held = list_models(store)
    if name in held:
        return
    if trained_from is None:
        raise ValueError(f"--object: {unknown_object(store, name)}")
    raise ValueError(f"--object: no object named {name!r} in {trained_from}{names_hint(name, held)}")


def main(args: argparse.Namespace) -> int:
    import asyncio
    import json
    import os
    import tempfile
    import time
    from pathlib import Path

    from quatrack.client import video_frames
    from quatrack.viewsets.camera import camera_to_dict, load_camera

    from quatrack.examples import example_dir
    from quatrack.testing.balancer import find_nginx

    example = example_dir()  # defaults that do not depend on the working directory
    args.video = args.video or str(example / "box.mp4")
    args.camera = args.camera or str(example / "camera.json")
    args.spec = args.spec or str(example / "object.json")
    cores = os.cpu_count() or 1
    try:
        counts = [int(x) for x in args.clients.split(",") if x.strip()]
        workers = [x.strip() if x.strip().startswith("p") else int(x) for x in args.workers.split(",") if x.strip()] \
            if args.workers is not None else sorted({1, cores})  # ('' is no default: refused below)
        sizes = [int(w[1:]) if isinstance(w, str) else w for w in workers]
    except ValueError:
        raise ValueError("--clients and --workers: comma-separated whole numbers (pN: the pool prototype)") from None
    if not counts or min(counts) < 1 or max(counts) > 64:
        raise ValueError("--clients: numbers between 1 and 64")
    if not workers or min(sizes) < 1 or max(sizes) > 64:
        raise ValueError("--workers: numbers between 1 and 64")
    if not 0.5 <= args.seconds <= 600 or not 0 < args.fps <= 240 or (args.threads is not None and args.threads < 1) or args.rest_requests < 0:
        raise ValueError("--seconds must be 0.5-600, --fps 0-240, --threads ≥ 1, --rest-requests ≥ 0")
    if not 1 <= getattr(args, "rest_concurrency", 4) <= 256:  # (0: no request sent, yet "40 requests" at ~1e6/s)
        raise ValueError("--rest-concurrency must be between 1 and 256")
    if not 0 <= (getattr(args, "stagger_s", 0.0) or 0.0) <= 600:  # (NaN too: a negative one ran as a burst)
        raise ValueError("--stagger-s must be between 0 and 600 seconds")
    replicas = {"yes": True, "no": False}.get(args.replicas, find_nginx() is not None)
    if replicas and find_nginx() is None:
        raise ValueError("--replicas yes: nginx is not installed (Debian: apt-get install nginx)")
    camera = camera_to_dict(load_camera(args.camera))
    if args.frames is not None and args.frames < 1:
        raise ValueError("--frames must be at least 1")
    if args.store:
        _check_object(args.store, args.object)  # (before the video is decoded)
    frames = list(video_frames(args.video, args.frames or max(1, round(args.seconds * args.fps))))
    tmp = tempfile.TemporaryDirectory(prefix="quatrack-bench-serve-")
    store = args.store
    if not store:
        from quatrack.viewsets.spec import load_spec
        from quatrack.viewsets.store import save_model
        from quatrack.viewsets.train import train_object

        store = Path(tmp.name) / "store"
        save_model(store, train_object(load_spec(args.spec)))
        _check_object(store, args.object, f"the model trained from {args.spec}")
    report = {"cpu_count": cores, "load_average_at_start": os.getloadavg(), "threads_per_worker": args.threads,
              "frames_per_client": len(frames), "fps": args.fps, "setups": []}
    try:
        for label, setup in _setups(store, workers, args.threads, max(counts) + 1, replicas, tmp.name):
            with setup() as (url, ws_url, pids):
                rows = []
                for n in counts:
                    cpu0, wall0 = cpu_seconds(pids()), time.perf_counter()
                    row = asyncio.run(_streams(f"{ws_url}/v1/objects/{args.object}/track", url, camera, frames, n, args.fps,
                                               getattr(args, "stagger_s", 0.0) or 0.0))
                    cpu = cpu_seconds(pids()) - cpu0
                    row["server_cores_used"] = cpu / (time.perf_counter() - wall0)
                    row["server_cpu_ms_per_frame"] = 1e3 * cpu / max(row["processed"], 1)
                    row["rss_mb"] = _rss_mb(pids())
                    rows.append(row)
                rest = None
                if args.rest_requests:
                    images = [data for _, _, data in frames[:: max(1, len(frames) // 10)]]
                    rest = asyncio.run(_rest(url, args.object, camera, images, args.rest_requests, args.rest_concurrency))
            report["setups"].append({"setup": label, "websocket": rows, "rest": rest})
    finally:
        tmp.cleanup()
    report["load_average_at_end"] = os.getloadavg()
    if args.json:
        print(json.dumps(report))
        return 0
    la = report["load_average_at_start"]
    per_worker = "cores ÷ workers" if args.threads is None else args.threads
    print(f"{cores} cores, load average at start {la[0]:.2f}; {per_worker} thread(s) per worker; "
          f"each client streams {len(frames)} frames at {args.fps:g} fps")
    print("| set-up | streams | fps/stream min / mean | total fps | latency p50 / p99 (ms) | tracked frames p50 / p99 "
          "| wait / step / io p50 (ms) "
          "| wait / step / io p99 (ms) | dropped | refused | /healthz p50 / p99 (ms) | in-client p99 | server cores used "
          "| server CPU per frame (ms) | sessions per process | RSS per worker (MB) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- |")
    for s in report["setups"]:
        for r in s["websocket"]:
            print(f"| {s['setup']} | {r['clients']} | {r['fps_per_stream_min']:.1f} / {r['fps_per_stream_mean']:.1f} | "
                  f"{r['total_fps']:.1f} | {r['latency_p50_ms']:.0f} / {r['latency_p99_ms']:.0f} | "
                  f"{r['latency_tracking_p50_ms']:.0f} / {r['latency_tracking_p99_ms']:.0f} | "
                  f"{r['wait_p50_ms']:.0f} / {r['step_p50_ms']:.0f} / {r['io_p50_ms']:.0f} | "
                  f"{r['wait_p99_ms']:.0f} / {r['step_p99_ms']:.0f} / {r['io_p99_ms']:.0f} | "
                  f"{r['dropped']} of {r['frames_sent']} | {r['refused']} | {r['healthz_p50_ms']:.1f} / "
                  f"{r['healthz_p99_ms']:.1f} | {r['healthz_in_client_p99_ms']:.1f} | "
                  f"{r['server_cores_used']:.2f} | {r['server_cpu_ms_per_frame']:.1f} | "
                  f"{'+'.join(map(str, r['sessions_per_process'])) or '?'} | "
                  f"{', '.join(f'{x:.0f}' for x in r['rss_mb'])} |"
                  + (f" errors: {r['error_codes']}" if r["error_codes"] else ""))
    for s in report["setups"]:
        r = s["rest"]
        if r:
            print(f"REST pose, {s['setup']}: {r['requests']} requests at concurrency {r['concurrency']}: "
                  f"{r['requests_per_s']:.2f}/s, p50 {r['latency_p50_ms']:.0f} ms, p99 {r['latency_p99_ms']:.0f} ms, "
                  f"{r['ok']} ok, {r['busy_503']} busy (503)")
    return 0

"""``quatrack bench serve``: the service under load, on loopback only.

N WebSocket clients (N = 1, 2, 4, 8) each stream the first frames of ``box.mp4`` at 30 fps in
real time, as a camera would; the server tracks the newest frame of each session and skips the
rest. Reported per N: per-frame latency (client send → answer) p50/p99, frames processed and
skipped, tracked answers. Then REST ``pose`` requests/s at concurrency 4. Frames are JPEG-encoded
before the clock starts, so the clients' own CPU use is small — but they share the machine. The
server runs as ``quatrack serve`` in its own process (``--in-process`` runs it in a thread of this
one, as the tests do; clients and server then share one interpreter lock and figures are worse).
"""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--store", metavar="DIR", help="model store with the object (default: train the example into a temp store)")
    p.add_argument("--object", default="cookie-box", metavar="NAME")
    p.add_argument("--video", default="examples/cookie-box/box.mp4")
    p.add_argument("--camera", default="examples/cookie-box/camera.json")
    p.add_argument("--spec", default="examples/cookie-box/object.json", help="spec trained when no --store is given")
    p.add_argument("--clients", default="1,2,4,8", help="numbers of concurrent WebSocket clients (default 1,2,4,8)")
    p.add_argument("--frames", type=int, default=150, help="frames each client streams (default 150 = 5 s)")
    p.add_argument("--fps", type=float, default=30.0, help="each client's frame rate (default 30)")
    p.add_argument("--rest-requests", type=int, default=40, help="REST pose requests (default 40)")
    p.add_argument("--rest-concurrency", type=int, default=4)
    p.add_argument("--workers", type=int, default=2, help="the server's CPU worker threads (default 2)")
    p.add_argument("--in-process", action="store_true", help="run the server in a thread of the benchmark's process")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")


def _pct(values, q) -> float:
    import numpy as np

    return float(np.percentile(values, q)) if len(values) else float("nan")


async def _streams(url: str, http_url: str, camera: dict, frames: list, n: int, fps: float) -> dict:
    import asyncio
    import time

    import httpx

    from quatrack.client import stream

    probes: list[float] = []

    async def probe():  # is the server's event loop still responsive under load?
        async with httpx.AsyncClient(timeout=30) as client:
            while True:
                t0 = time.perf_counter()
                await client.get(f"{http_url}/healthz")
                probes.append((time.perf_counter() - t0) * 1e3)
                await asyncio.sleep(0.1)

    prober = asyncio.create_task(probe())
    results = await asyncio.gather(*(stream(url, camera, frames, fps=fps) for _ in range(n)))
    prober.cancel()
    rtt = [x for r in results for x in r.rtt_ms]
    server = [m["latency_ms"] for r in results for m in r.poses.values()]
    processed = sum(len(r.poses) for r in results)
    return {
        "clients": n, "frames_sent": sum(r.sent for r in results), "processed": processed,
        "skipped": sum(r.skipped for r in results), "errors": sum(len(r.errors) for r in results),
        "tracking": sum(m["status"] == "tracking" for r in results for m in r.poses.values()),
        "latency_p50_ms": _pct(rtt, 50), "latency_p99_ms": _pct(rtt, 99),
        "server_latency_p50_ms": _pct(server, 50), "server_latency_p99_ms": _pct(server, 99),
        "healthz_p50_ms": _pct(probes, 50), "healthz_max_ms": max(probes, default=float("nan")),
        "processed_fps_per_client": processed / n / max(max(r.wall_s for r in results), 1e-9),
    }


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


class _Subprocess:
    """``quatrack serve`` in a child process on a free loopback port, its limits passed by environment."""

    def __init__(self, settings) -> None:
        from quatrack.service.server import free_port

        self.settings, self.port = settings, free_port()
        self.url, self.ws_url = f"http://127.0.0.1:{self.port}", f"ws://127.0.0.1:{self.port}"

    def __enter__(self):
        import os
        import subprocess
        import sys
        import time

        import httpx

        env = {**os.environ, "QUATRACK_MAX_SESSIONS": str(self.settings.max_sessions),
               "QUATRACK_MAX_PENDING_REQUESTS": str(self.settings.max_pending_requests)}
        env.pop("QUATRACK_API_TOKEN", None)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "quatrack", "serve", "--store", str(self.settings.store), "--host", "127.0.0.1",
             "--port", str(self.port), "--workers", str(self.settings.workers), "--log-level", "warning"], env=env)
        deadline = time.monotonic() + 120
        while True:
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.__exit__()
                raise RuntimeError("quatrack serve did not become ready")
            time.sleep(0.1)

    def __exit__(self, *exc) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=15)
        except Exception:
            self.proc.kill()


def main(args: argparse.Namespace) -> int:
    import asyncio
    import json
    import os
    import tempfile
    from pathlib import Path

    from quatrack.client import video_frames
    from quatrack.service.server import BackgroundServer
    from quatrack.service.settings import Settings
    from quatrack.viewsets.camera import camera_to_dict, load_camera

    counts = [int(x) for x in args.clients.split(",") if x.strip()]
    if not counts or min(counts) < 1 or max(counts) > 32:
        raise ValueError("--clients: numbers between 1 and 32")
    if args.frames < 1 or args.fps <= 0:
        raise ValueError("--frames and --fps must be positive")
    camera = camera_to_dict(load_camera(args.camera))
    frames = list(video_frames(args.video, args.frames))
    tmp = None
    store = args.store
    if not store:
        from quatrack.viewsets.spec import load_spec
        from quatrack.viewsets.store import save_model
        from quatrack.viewsets.train import train_object

        tmp = tempfile.TemporaryDirectory(prefix="quatrack-bench-serve-")
        store = tmp.name
        save_model(store, train_object(load_spec(args.spec)))
    settings = Settings(store=Path(store), workers=args.workers, max_sessions=max(counts) + 1,
                        max_pending_requests=max(8, 2 * args.rest_concurrency)).checked()
    report = {"cpu_count": os.cpu_count(), "workers": args.workers, "frames_per_client": len(frames), "fps": args.fps,
              "websocket": [], "rest": None}
    with (BackgroundServer(settings) if args.in_process else _Subprocess(settings)) as srv:
        url = f"{srv.ws_url}/v1/objects/{args.object}/track"
        for n in counts:
            report["websocket"].append(asyncio.run(_streams(url, srv.url, camera, frames, n, args.fps)))
        images = [data for _, _, data in frames[:: max(1, len(frames) // 10)]]
        report["rest"] = asyncio.run(_rest(srv.url, args.object, camera, images, args.rest_requests, args.rest_concurrency))
    if tmp is not None:
        tmp.cleanup()
    if args.json:
        print(json.dumps(report))
        return 0
    print(f"service on loopback, {report['workers']} worker threads, {report['cpu_count']} cores; "
          f"each client streams {len(frames)} frames at {args.fps:g} fps")
    print("| clients | frames sent | processed | skipped | tracking | latency p50 (ms) | p99 (ms) | server p50 / p99 (ms) | processed fps/client | /healthz p50 / max (ms) |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in report["websocket"]:
        print(f"| {r['clients']} | {r['frames_sent']} | {r['processed']} | {r['skipped']} | {r['tracking']} | "
              f"{r['latency_p50_ms']:.0f} | {r['latency_p99_ms']:.0f} | {r['server_latency_p50_ms']:.0f} / "
              f"{r['server_latency_p99_ms']:.0f} | {r['processed_fps_per_client']:.1f} | "
              f"{r['healthz_p50_ms']:.0f} / {r['healthz_max_ms']:.0f} |")
    r = report["rest"]
    print(f"REST pose: {r['requests']} requests at concurrency {r['concurrency']}: {r['requests_per_s']:.2f} requests/s, "
          f"latency p50 {r['latency_p50_ms']:.0f} ms, p99 {r['latency_p99_ms']:.0f} ms, {r['ok']} ok, {r['busy_503']} busy (503)")
    return 0

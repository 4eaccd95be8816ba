"""A/B comparison of server settings under the same load: ``python -m quatrack.bench.serve_ab``.

Why: on a shared machine the load changes from minute to minute, so two benchmark runs of
``quatrack bench serve`` made one after the other compare the load, not the settings. Here every
variant (a set of ``QUATRACK_*`` variables) runs as its own ``quatrack serve`` at the same time,
and the runs are interleaved — for each repetition, for each stream count, each variant in turn
(the order rotating between repetitions) — so each variant sees the same mix of load. Each run
is :func:`bench.serve._streams` (real-time clients, /healthz probed from a separate process, the
latency split into wait / step / io); rows are pooled per variant and stream count.

Example::

    python -m quatrack.bench.serve_ab --store STORE --clients 2,4,8 --seconds 4 --repeats 3 \\
        "nice0=QUATRACK_THREAD_NICE=0" "nice5=QUATRACK_THREAD_NICE=5"
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import sys
import time

from quatrack.bench.serve import _pct, _streams, cpu_seconds

KEYS = ("total_fps", "fps_per_stream_min", "fps_per_stream_mean", "latency_p50_ms", "latency_p99_ms", "latency_tracking_p99_ms", "wait_p50_ms", "wait_p99_ms", "step_p50_ms", "step_p99_ms",
        "io_p50_ms", "io_p99_ms", "client_loop_lag_p50_ms", "client_loop_lag_p99_ms", "healthz_p50_ms", "healthz_p99_ms", "healthz_max_ms", "healthz_in_client_p99_ms")


def parse_variant(text: str) -> tuple[str, dict[str, str]]:
    """``label=VAR=value,VAR=value`` (or ``label=`` for the defaults); ``QUATRACK_WORKERS=N`` sets
    that variant's worker processes (else ``--workers``)."""
    label, _, rest = text.partition("=")
    env = {}
    for item in filter(None, rest.split(",")):
        k, sep, v = item.partition("=")
        if not sep or not (k.startswith("QUATRACK_") or k == "PYTHONPATH"):
            raise ValueError(f"variant {text!r}: give QUATRACK_NAME=value pairs separated by commas "
                             "(PYTHONPATH=DIR too: another version of the code, run from a directory "
                             "without a quatrack/ folder)")
        env[k] = v
    if not label:
        raise ValueError(f"variant {text!r}: starts with a label")
    return label, env


def main(argv: list[str] | None = None) -> int:
    from quatrack.client import video_frames
    from quatrack.examples import example_dir
    from quatrack.service.server import ServeProcess
    from quatrack.viewsets.camera import camera_to_dict, load_camera

    ap = argparse.ArgumentParser(prog="python -m quatrack.bench.serve_ab", description=__doc__.split("\n\n")[0])
    ap.add_argument("variants", nargs="+", help="label=QUATRACK_X=v,QUATRACK_Y=w (label= alone: the defaults; "
                                                "PYTHONPATH=DIR runs the server from another copy of the code)")
    ap.add_argument("--store", required=True, help="model store with the object")
    ap.add_argument("--object", default="cookie-box")
    ap.add_argument("--clients", default="2,4,8")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--stagger-s", type=float, default=0.0, metavar="S",
                    help="start stream k at k × S seconds instead of all at once (default 0: a burst)")
    ap.add_argument("--json", metavar="PATH", help="also write every run's row here")
    args = ap.parse_args(argv)
    try:
        variants = [parse_variant(v) for v in args.variants]
        counts = [int(x) for x in args.clients.split(",")]
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    example = example_dir()
    camera = camera_to_dict(load_camera(str(example / "camera.json")))
    frames = list(video_frames(str(example / "box.mp4"), max(1, round(args.seconds * args.fps))))
    base = {"QUATRACK_MAX_SESSIONS": str(max(counts) + 1), "QUATRACK_MAX_PENDING_REQUESTS": "16"}
    rows: list[dict] = []
    with contextlib.ExitStack() as stack:
        servers = {label: stack.enter_context(ServeProcess(args.store, workers=int(env.get("QUATRACK_WORKERS", args.workers)),
                                                           env={**base, **env}))
                   for label, env in variants}
        for rep in range(args.repeats):
            for n in counts:
                order = variants[rep % len(variants):] + variants[:rep % len(variants)]
                for label, _ in order:
                    srv = servers[label]
                    load = os.getloadavg()[0]
                    cpu0, wall0 = cpu_seconds(srv.worker_pids()), time.perf_counter()
                    row = asyncio.run(_streams(f"{srv.ws_url}/v1/objects/{args.object}/track", srv.url, camera,
                                               frames, n, args.fps, args.stagger_s))
                    cpu = cpu_seconds(srv.worker_pids()) - cpu0
                    rows.append({"variant": label, "repeat": rep, "clients": n, "load": load,
                                 **{k: row[k] for k in KEYS}, "dropped": row["dropped"], "sent": row["frames_sent"],
                                 "sessions_per_process": row["sessions_per_process"],
                                 "cores_used": cpu / (time.perf_counter() - wall0),
                                 "cpu_ms_per_frame": 1e3 * cpu / max(row["processed"], 1)})
                    r = rows[-1]
                    print(f"rep {rep} {label:>12} streams {n:2d} load {load:5.2f}: fps {r['total_fps']:5.1f}  "
                          f"lat {r['latency_p50_ms']:5.0f}/{r['latency_p99_ms']:5.0f}  wait {r['wait_p50_ms']:4.0f}/"
                          f"{r['wait_p99_ms']:4.0f}  step {r['step_p50_ms']:4.0f}/{r['step_p99_ms']:4.0f}  io "
                          f"{r['io_p50_ms']:4.0f}/{r['io_p99_ms']:5.0f}  clientlag {r['client_loop_lag_p50_ms']:4.0f}/"
                          f"{r['client_loop_lag_p99_ms']:5.0f}  healthz {r['healthz_p50_ms']:5.1f}/"
                          f"{r['healthz_p99_ms']:6.1f} (max {r['healthz_max_ms']:6.1f})  cores {r['cores_used']:.2f}  "
                          f"CPU/frame {r['cpu_ms_per_frame']:.0f} ms  sessions per process "
                          f"{'+'.join(map(str, r['sessions_per_process'])) or '?'}", flush=True)
                    time.sleep(1.0)
    print("\nmedian over repeats:")
    print("| variant | streams | load | fps/stream min / mean | total fps | latency p50 / p99 | wait p50 / p99 "
          "| step p50 / p99 | io p50 / p99 | clients' loop lag p50 / p99 | /healthz p50 / p99 / max "
          "| server cores used | server CPU per frame (ms) | sessions per process (each run) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    for label, _ in variants:
        for n in counts:
            sel = [r for r in rows if r["variant"] == label and r["clients"] == n]
            m = {k: _pct([r[k] for r in sel], 50) for k in (*KEYS, "load", "cores_used", "cpu_ms_per_frame")}
            spread = ", ".join("+".join(map(str, r["sessions_per_process"])) or "?" for r in sel)
            print(f"| {label} | {n} | {m['load']:.1f} | {m['fps_per_stream_min']:.1f} / {m['fps_per_stream_mean']:.1f} | "
                  f"{m['total_fps']:.1f} | {m['latency_p50_ms']:.0f} / "
                  f"{m['latency_p99_ms']:.0f} | {m['wait_p50_ms']:.0f} / {m['wait_p99_ms']:.0f} | {m['step_p50_ms']:.0f} / "
                  f"{m['step_p99_ms']:.0f} | {m['io_p50_ms']:.0f} / {m['io_p99_ms']:.0f} | {m['client_loop_lag_p50_ms']:.0f} / "
                  f"{m['client_loop_lag_p99_ms']:.0f} | {m['healthz_p50_ms']:.1f} / "
                  f"{m['healthz_p99_ms']:.1f} / {m['healthz_max_ms']:.0f} | {m['cores_used']:.2f} | "
                  f"{m['cpu_ms_per_frame']:.1f} | {spread} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The `quatrack` command line: a thin layer over the packages' public functions.

The subcommands are listed in ``COMMANDS``: name → ``(help, add_arguments, run)``, where
``add_arguments`` fills the subcommand's parser and ``run`` takes the parsed arguments and returns
an exit status. User errors are raised as
:class:`UserError` (or ``ValueError``/``OSError`` from the layers below) and become a one-line
message on stderr with exit status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import select
import sys
import warnings
from typing import Callable

import numpy as np

from quatrack.recognition.runtime import limit_blas_threads, tune_allocator
from quatrack.recognition.trackio import quiet_ffmpeg


class UserError(Exception):
    """Bad input from the user: reported as one line, exit status 2."""


def _zoo_options(p: argparse.ArgumentParser) -> None:
    """The zoo benchmarks' walks (track-zoo, edge-judge: the same walks) and output."""
    p.add_argument("--sequences", metavar="A,B", help="zoo objects to walk round (default: six; see testing/zoo.py)")
    p.add_argument("--seconds", type=float, default=10.0, help="length of each walk at 30 fps (default 10)")
    p.add_argument("--renderings", type=int, default=1, metavar="N",
                   help="walk round each object N times, each rendering with other seeds (backgrounds, training "
                        "photo, occluder, shake); the first is always the same (default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the report")


def _lens(text: str | None):
    """``--lens``'s distortion coefficients (OpenCV's k1, k2, p1, p2[, k3[, k4, k5, k6]]), or None."""
    if text is None:
        return None
    try:
        d = [float(x) for x in text.split(",")]
    except ValueError:
        raise UserError(f"--lens must be 4 to 8 numbers separated by commas (OpenCV's k1,k2,p1,p2[,k3...]), got {text!r}")
    if not 4 <= len(d) <= 8 or not all(abs(x) < 10 for x in d):
        raise UserError(f"--lens must be 4 to 8 numbers below 10 in size (OpenCV's k1,k2,p1,p2[,k3...]), got {text!r}")
    return d


def _passes(text: str | None, known: tuple[str, ...]) -> tuple[str, ...]:
    """``--passes``' names, in the benchmark's order (``known``; None: all of them)."""
    if text is None:
        return known
    names = [x.strip() for x in text.split(",") if x.strip()]
    unknown = sorted(set(names) - set(known))
    if not names or unknown:
        raise UserError(f"--passes takes names among {', '.join(known)}, separated by commas; got {text!r}")
    if "learned" in names and "truth" not in names:
        raise UserError("--passes: learned re-runs the walk with the views the truth pass learned; add truth")
    return tuple(k for k in known if k in names)


def _size(text: str) -> tuple[int, int]:
    """``--size``'s ``WIDTHxHEIGHT`` in pixels."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise UserError(f"--size must be WIDTHxHEIGHT in pixels (e.g. 1280x720), got {text!r}")
    if not (160 <= w <= 4096 and 120 <= h <= 4096):
        raise UserError(f"--size must be between 160x120 and 4096x4096 pixels, got {text!r}")
    return w, h


def _add_bench(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    ude = sub.add_parser(
        "ude-cube",
        help="reproduce Ude (1999), Section 5: the cube tracked by the quaternion filter",
        description="Ude (1999), Section 5, over many seeds, with Cramér–Rao bounds and timings.",
    )
    ude.add_argument("--seeds", type=int, default=20, help="Monte-Carlo runs (default 20)")
    ude.add_argument("--first-seed", type=int, default=0, help="first random seed (default 0)")
    ude.add_argument("--table-frame", type=int, default=90, help="frame whose iterations are printed as Table 1 (default 90, t = 3 s)")
    ude.add_argument(
        "--variant",
        default="paper",
        choices=["paper", "half-angle", "isotropic-noise", "silhouette-edges"],
        help="a reading of the paper to test (default: paper, as printed); see bench/RESULTS.md",
    )
    ude.add_argument("--json", action="store_true", help="print one JSON object instead of the report")
    loc = sub.add_parser(
        "locate",
        help="recognition and initial pose: accuracy on rendered scenes, negatives, box.mp4; per-stage times",
        description="Accuracy against rendered ground truth, false positives, the real video, per-stage p50/p95.",
    )
    loc.add_argument("--scenes", type=int, default=200, help="rendered scenes (default 200)")
    loc.add_argument("--seed", type=int, default=0, help="random seed of the scenes (default 0)")
    loc.add_argument("--every", type=int, default=3, help="use every N-th frame of box.mp4 (default 3)")
    loc.add_argument("--sheet", metavar="PNG", help="write a contact sheet of box.mp4 overlays")
    loc.add_argument("--zoo", action="store_true",
                     help="the object zoo instead (issue 13): other shapes, units, grey, out of frame, 1 and 4 photos, "
                          "no object and two objects")
    loc.add_argument("--zoo-objects", metavar="A,B", help="zoo objects to run (default: all; see testing/zoo.py)")
    loc.add_argument("--zoo-scenes", type=int, default=None, metavar="N", help="scenes per trained zoo model (default 12)")
    loc.add_argument("--json", action="store_true", help="print one JSON object instead of the report")
    track = sub.add_parser(
        "track",
        help="video tracking: every motion model at 1/1..1/5 frame rate on a rendered sequence, and box.mp4",
        description="Tracking accuracy against rendered ground truth at several sampling rates, timings, and box.mp4.",
    )
    track.add_argument("--seconds", type=float, default=10.0, help="length of the rendered sequence (default 10)")
    track.add_argument("--locate-frames", type=int, default=150, metavar="N",
                       help="box.mp4 frames also given to per-frame recognition, for comparison (default 150)")
    track.add_argument("--sheet", default="track_contact_sheet.png", metavar="PNG",
                       help="contact sheet of overlays (default track_contact_sheet.png, in the current folder)")
    track.add_argument("--json", action="store_true", help="print one JSON object instead of the report")
    ab = sub.add_parser(
        "track-ab",
        help="tracker settings compared in one process on one video, the trackers stepping in turn on each frame",
        description="The service's tracker settings with TrackerParams fields replaced (NAME=JSON, e.g. "
                    "'w17={\"klt\": {\"win\": 17}}') against the defaults ('base') on one video (default box.mp4): "
                    "step CPU p50/mean/p90, frames without a pose, poses' distance from base's. The variants step in turn "
                    "on every frame, so the machine's changing speed falls on all alike.",
    )
    ab.add_argument("variants", nargs="*", metavar="NAME=JSON", help="variants to compare with the defaults")
    ab.add_argument("--video", help="the video (default: the bundled box.mp4)")
    ab.add_argument("--camera", help="its camera JSON (default: the bundled example's)")
    ab.add_argument("--spec", help="the object's spec, trained first (default: the bundled example's)")
    ab.add_argument("--frames", type=int, default=300, metavar="N", help="frames of the video (default 300)")
    ab.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    tz = sub.add_parser(
        "track-zoo",
        help="tracking any object from any side: zoo objects trained from one photo, a camera walking round them",
        description="Rendered 360° walks round zoo objects (mm, cm, m) trained from ONE photo, with ground truth: "
                    "losses, errors, NEES, step times, and re-initialisation with and without learned viewsets.",
    )
    _zoo_options(tz)
    tz.add_argument("--lens", metavar="K1,K2,P1,P2[,K3...]",
                    help="render, train and track through a lens with OpenCV's distortion coefficients "
                         "(e.g. --lens=-0.15,0.05,0,0,0, with '=' as the first is negative; default: none)")
    tz.add_argument("--size", default="640x480", metavar="WxH",
                    help="the camera's image size, its field of view kept at 56° (default 640x480)")
    tz.add_argument("--grey", action="store_true",
                    help="a monochrome camera: train from a grey photo and track grey frames (default: colour)")
    tz.add_argument("--calm", action="store_true",
                    help="the walks without their hard phases (no slide out of the frame, blur, change of light "
                         "or occluder; elevation ±25° once, size ×1.5): drift round unseen sides alone")
    tz.add_argument("--passes", metavar="A,B",
                    help="which passes to run, of truth, live, recognition, learned (default: all four; "
                         "learned needs truth, whose views it uses); e.g. --passes live for the service's "
                         "settings alone")
    ej = sub.add_parser(
        "edge-judge",
        help="how well the model's edges judge a pose: false alarms at the truth, wrong poses caught",
        description="On the track-zoo walks' frames (rendered, with ground truth; nothing tracked or trained), "
                    "the edge judges' refusals at the true pose, at 0.3 and at 1.2 of the 5 %/5° criterion from it.",
    )
    _zoo_options(ej)
    ej.add_argument("--every", type=int, default=5, metavar="K", help="judge every K-th frame (default 5)")
    sm = sub.add_parser(
        "scan-mesh",
        help="a scan's mesh against the 12-face box: training, locate and tracking on dense and jittered meshes",
        description="The bundled cookie box trained on its own 12-triangle mesh, on the same box subdivided K times "
                    "(4^K x 12 triangles) and on that mesh jittered (a scan's noise): training time, synthetic "
                    "views, locate, tracking step time, and the tracked poses' distance from the 12-face box's.",
    )
    sm.add_argument("--subdivisions", type=int, default=6, metavar="K", help="subdivisions (default 6: 49 152 faces)")
    sm.add_argument("--jitter", type=float, default=0.001, metavar="F",
                    help="vertex jitter, sigma as a share of the box's diagonal (default 0.001)")
    sm.add_argument("--frames", type=int, default=150, metavar="N", help="frames of box.mp4 tracked (default 150)")
    sm.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    rg = sub.add_parser(
        "register",
        help="photos registered from clicked corners: PnP and the mesh's edges against the truth",
        description="Each zoo object's training photo rendered at a known pose; up to 8 visible corners clicked with "
                    "Gaussian noise; the pose from PnP and after quatrack register's refit to the mesh's edges, "
                    "against the truth (median / 90th percentile / max), per click noise.",
    )
    rg.add_argument("--zoo-objects", metavar="A,B,...", help="zoo objects (default: all)")
    rg.add_argument("--photos", type=int, default=4, metavar="N", help="photos (seeds) per object (default 4)")
    rg.add_argument("--noise", default="1,2,4", metavar="PX,...", help="click noise levels, px per axis (default 1,2,4)")
    rg.add_argument("--grey", action="store_true", help="grey photos")
    rg.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    serve = sub.add_parser(
        "serve",
        help="the service under load: 1..16 concurrent 30 fps streams against 1 and N workers and two replicas behind nginx",
        description="Start `quatrack serve` on loopback with 1 and N worker processes (and two replicas behind nginx "
                    "when it is installed); 1, 2, 4, 8, 16 WebSocket clients each stream box.mp4 at 30 fps: per-stream "
                    "fps, latency p50/p99, frames dropped, /healthz p99, RSS per worker; REST pose requests/s.",
    )
    serve.add_argument("--store", metavar="DIR", help="model store with the object (default: train the example into a temp store)")
    serve.add_argument("--object", default="cookie-box", metavar="NAME", help="object the clients track and the REST requests locate (default cookie-box)")
    serve.add_argument("--video", help="video streamed by every client (default: the bundled box.mp4)")
    serve.add_argument("--camera", help="its camera JSON (default: the bundled example's)")
    serve.add_argument("--spec", help="spec trained when no --store is given (default: the bundled example's)")
    serve.add_argument("--clients", default="1,2,4,8,16", help="numbers of concurrent streams (default 1,2,4,8,16)")
    serve.add_argument("--workers", default=None, metavar="N,...",
                       help="worker-process counts to compare (default 1 and the number of cores)")
    serve.add_argument("--threads", type=int, default=None, metavar="N",
                       help="CPU threads per worker process (default: as quatrack serve, cores ÷ workers)")
    serve.add_argument("--replicas", default="auto", choices=["auto", "yes", "no"],
                       help="also two 1-worker replicas behind nginx (default auto: when nginx is installed)")
    serve.add_argument("--seconds", type=float, default=5.0, help="length of each run: frames each client streams / fps (default 5)")
    serve.add_argument("--frames", type=int, default=None, metavar="N", help="frames each client streams (default: seconds × fps)")
    serve.add_argument("--fps", type=float, default=30.0, help="each client's frame rate (default 30)")
    serve.add_argument("--rest-requests", type=int, default=40, help="REST pose requests (default 40; 0 to skip)")
    serve.add_argument("--rest-concurrency", type=int, default=4, metavar="N",
                       help="REST pose requests in flight at once (default 4, 1 to 256)")
    serve.add_argument("--stagger-s", type=float, default=0.0, metavar="S",
                       help="start stream k at k × S seconds instead of all at once (default 0: a burst)")
    serve.add_argument("--json", action="store_true", help="print one JSON object instead of the tables")


def _zoo_names(text: str | None, option: str) -> list[str] | None:
    """A comma-separated list of zoo objects given to ``option`` (None: not given, the default)."""
    from quatrack.testing import zoo

    known = [o.name for o in zoo.ZOO]
    if text is None:
        return None
    names = [n.strip() for n in text.split(",")]
    if not any(names) or not all(names):  # ('' or 'a,,b': an empty selection ran every object, for minutes)
        raise UserError(f"{option}: give zoo object names separated by commas, got {text!r} "
                        f"(known: {', '.join(known)}; leave the option out for the default)")
    for n in names:
        if n not in known:
            raise UserError(f"{option}: no zoo object {n!r} (known: {', '.join(known)})")
    return names


def _zoo_walks(args: argparse.Namespace) -> list[str] | None:
    """The zoo benchmarks' ``--sequences`` (None: their default), with ``--seconds`` and
    ``--renderings`` checked."""
    names = _zoo_names(args.sequences, "--sequences")
    if not 1.0 <= args.seconds <= 60.0:
        raise UserError("--seconds must be between 1 and 60")
    if not 1 <= args.renderings <= 20:
        raise UserError("--renderings must be between 1 and 20")
    return names


def _run_bench(args: argparse.Namespace) -> int:
    if args.benchmark == "ude-cube":
        from quatrack.bench import ude_cube

        if args.seeds < 2:
            raise UserError("--seeds must be at least 2")
        if args.first_seed < 0:  # (numpy's "expected non-negative integer", naming no option)
            raise UserError("--first-seed must be >= 0")
        if not 1 <= args.table_frame <= 180:
            raise UserError("--table-frame must be between 1 and 180")
        return ude_cube.main(args.seeds, args.first_seed, args.table_frame, args.json, args.variant)
    if args.benchmark == "serve":
        from quatrack.bench import serve

        return serve.main(args)
    if args.benchmark == "track":
        from quatrack.bench import track

        if not 1.0 <= args.seconds <= 120.0:
            raise UserError("--seconds must be between 1 and 120")
        if args.locate_frames < 0:
            raise UserError("--locate-frames must be >= 0")
        _sheet(args.sheet)
        return track.main(args.json, args.seconds, args.locate_frames, args.sheet)
    if args.benchmark == "track-ab":
        from quatrack.bench import track_ab

        return track_ab.main(args.variants, args.video, args.camera, args.spec, args.frames, args.json)
    if args.benchmark == "track-zoo":
        from quatrack.bench import track_zoo

        return track_zoo.main(args.json, args.seconds, _zoo_walks(args), args.renderings, _lens(args.lens),
                              _size(args.size), args.grey, _passes(args.passes, track_zoo.PASSES), args.calm)
    if args.benchmark == "edge-judge":
        from quatrack.bench import edge_judge

        names = _zoo_walks(args)
        if args.every < 1:
            raise UserError("--every must be >= 1")
        return edge_judge.main(args.json, names, args.renderings, args.every, args.seconds)
    if args.benchmark == "scan-mesh":
        from quatrack.bench import scan_mesh

        if not 0 <= args.subdivisions <= 7:
            raise UserError("--subdivisions must be between 0 and 7")
        if not 0.0 <= args.jitter <= 0.05:
            raise UserError("--jitter must be between 0 and 0.05")
        if not 10 <= args.frames <= 300:
            raise UserError("--frames must be between 10 and 300")
        return scan_mesh.main(args.subdivisions, args.jitter, args.frames, args.json)
    if args.benchmark == "register":
        from quatrack.bench import register as bench_register

        if not 1 <= args.photos <= 50:
            raise UserError("--photos must be between 1 and 50")
        noises = _floats(args.noise, "--noise")
        if not noises or any(not 0 <= v <= 20 for v in noises):
            raise UserError("--noise: give click noise levels between 0 and 20 px, separated by commas")
        return bench_register.main(_zoo_names(args.zoo_objects, "--zoo-objects"), args.photos, noises, args.grey, args.json)
    if args.benchmark == "locate":
        from quatrack.bench import locate as bench_locate

        if args.scenes < 1 or args.every < 1:
            raise UserError("--scenes and --every must be at least 1")
        if args.seed < 0:  # (numpy's "expected non-negative integer", naming no option)
            raise UserError("--seed must be >= 0")
        if args.zoo:
            names = _zoo_names(args.zoo_objects, "--zoo-objects")
            scenes = 12 if args.zoo_scenes is None else args.zoo_scenes
            if scenes < 1:
                raise UserError("--zoo-scenes must be at least 1")
            return bench_locate.main_zoo(names, scenes, args.seed, args.json)
        if args.zoo_scenes is not None or args.zoo_objects is not None:  # (were ignored, the other benchmark ran)
            raise UserError("--zoo-scenes and --zoo-objects need --zoo")
        if args.sheet:  # (checked before the run: a .txt was a traceback, a folder under a file "File exists")
            _sheet(args.sheet)
        return bench_locate.main(args.scenes, args.seed, args.every, args.sheet, args.json)
    raise UserError(f"unknown benchmark {args.benchmark!r}")


def _nearest_folder(path, option: str):
    """The nearest existing folder above ``path`` (None if none exists), refusing a file there:
    a path under a file can never be made (checked before a run that would write to it)."""
    from pathlib import Path

    above = next((p for p in Path(path).absolute().parents if p.exists()), None)
    if above is not None and not above.is_dir():
        raise UserError(f"{option} {path}: {above} is a file, not a folder")
    return above


def _sheet(path: str) -> None:
    """A contact sheet's path: a .png whose folder exists or can be made (checked before the run)."""
    if not path.lower().endswith(".png"):
        raise UserError("--sheet must name a .png file")
    _nearest_folder(path, "--sheet")


def _floats(text: str, option: str) -> tuple[float, ...]:
    """A comma-separated list of numbers; "none" (or empty) is the empty list. ("0" is the number:
    it was "none" too, so ``--novel-scales 0`` trained without a word and ``bench register --noise 0``
    was refused.)"""
    if text.strip().lower() in ("", "none"):
        return ()
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise UserError(f"{option}: expected comma-separated numbers or 'none', got {text!r}") from None
    if any(not (v == v) or v in (float("inf"), float("-inf")) for v in values):
        raise UserError(f"{option}: numbers must be finite")
    return values


def _add_train(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", nargs="+", metavar="SPEC.json",
                        help="object spec(s) (see docs/contract.md); several are trained in parallel")
    parser.add_argument("--store", metavar="DIR", help="model store (default: $QUATRACK_STORE or the user data directory)")
    parser.add_argument("--jobs", type=int, default=2, metavar="N",
                        help="CPU budget (default 2): one spec builds N views in parallel; several specs train "
                             "min(N, specs) at once in processes, the rest of N going to their views; with --ray, "
                             "the CPUs each task asks of the cluster")
    parser.add_argument("--ray", metavar="ADDRESS", default=None,
                        help="train each spec as a task on this Ray cluster (host:port, 'auto', or 'local' for a "
                             "private one); specs and store must be on a filesystem every node shares; "
                             "needs pip install 'quatrack[ray]'")
    parser.add_argument("--no-overwrite", action="store_true", help="refuse to replace an existing model of that name")
    parser.add_argument("--drop-learned", action="store_true",
                        help="forget the views a replaced model learned while tracking (default: kept when the mesh "
                             "and the kind of descriptors are unchanged; dropped, with a warning, otherwise)")
    parser.add_argument("--skip-existing", action="store_true",
                        help="do nothing (exit 0) if the store already holds this object trained from this very spec, "
                             "the files it names and these options, and the model loads")
    parser.add_argument("--novel-views", default="20,40", metavar="DEG,...",
                        help="rotations (degrees, both signs) about each object axis for synthetic views; 'none' to disable (default 20,40)")
    parser.add_argument("--novel-axes", default="xyz", metavar="AXES", help="object axes to rotate about (default xyz)")
    parser.add_argument("--novel-scales", default="0.6,1.4", metavar="S,...",
                        help="apparent-size factors for synthetic views; 'none' to disable (default 0.6,1.4)")
    parser.add_argument("--max-features", type=int, default=1500, metavar="N", help="SIFT keypoints per view (default 1500)")
    parser.add_argument("--root-sift", action="store_true", help="store RootSIFT descriptors instead of SIFT")
    # (the defaults are RFCHParams'; told here without importing it, as a test checks)
    parser.add_argument("--rfch-clusters", type=int, default=None, metavar="N", help="RFCH cluster centres (default 32)")
    parser.add_argument("--rfch-distance", type=int, default=None, metavar="PX",
                        help="RFCH pair distance in pixels (default 8)")
    parser.add_argument("--rfch-scales", default=None, metavar="S,...", help="RFCH Gaussian scales in pixels (default 1,2)")


def _train_params(args: argparse.Namespace):
    from quatrack.viewsets.novel import NovelViewParams
    from quatrack.viewsets.rfch import RFCHParams
    from quatrack.viewsets.train import TrainParams
    from quatrack.viewsets.viewset import ViewsetParams

    if args.jobs < 1:
        raise UserError("--jobs must be at least 1")
    if not 1 <= args.max_features <= 1_000_000:  # (OpenCV's SIFT takes a C int: 2³¹ was a cv2.error traceback)
        raise UserError("--max-features must be between 1 and 1000000")
    angles = _floats(args.novel_views, "--novel-views")
    scales = _floats(args.novel_scales, "--novel-scales")
    if any(s <= 0 for s in scales):
        raise UserError("--novel-scales: factors must be positive ('none' for no synthetic scales)")
    if any(not 0 < abs(a) < 90 for a in angles):
        raise UserError("--novel-views: angles must be between 0 and 90 degrees ('none' for no synthetic views)")
    if not args.novel_axes or set(args.novel_axes) - set("xyz"):
        raise UserError("--novel-axes: use letters among x, y, z")
    novel = NovelViewParams(angles, args.novel_axes, scales) if (angles or scales) else None
    rfch = RFCHParams()
    if args.rfch_clusters is not None:
        if not 2 <= args.rfch_clusters <= 256:
            raise UserError("--rfch-clusters must be between 2 and 256")
        rfch = dataclasses.replace(rfch, n_clusters=args.rfch_clusters)
    if args.rfch_distance is not None:
        if not 1 <= args.rfch_distance <= 100:
            raise UserError("--rfch-distance must be between 1 and 100 pixels")
        rfch = dataclasses.replace(rfch, distance=args.rfch_distance)
    if args.rfch_scales is not None:
        rs = _floats(args.rfch_scales, "--rfch-scales")
        if not rs or any(not 0 < s <= 100 for s in rs):  # (beyond, OpenCV's blur fails: a traceback, or all memory)
            raise UserError("--rfch-scales: give one or more positive scales, up to 100 pixels")
        rfch = dataclasses.replace(rfch, scales=rs)
    vs = ViewsetParams(max_features=args.max_features, root_sift=args.root_sift)
    return TrainParams(rfch=rfch, viewsets=vs, novel=novel, jobs=args.jobs)


def _run_train(args: argparse.Namespace) -> int:
    import time

    from tqdm import tqdm

    from quatrack.viewsets.batch import exists_message, inputs_checksum, record_inputs, up_to_date
    from quatrack.viewsets.spec import load_spec
    from quatrack.viewsets.learn import BACKUP_DIR, save_trained
    from quatrack.viewsets.store import model_path, resolve_store, retrain_reason
    from quatrack.viewsets.train import train_object

    t0 = time.perf_counter()
    params = _train_params(args)
    store = resolve_store(args.store)
    if store.exists() and not store.is_dir():
        raise UserError(f"--store {store}: not a directory")
    # (its nearest existing folder must be one: else the model, trained first, could not be saved)
    above = _nearest_folder(store, "--store")
    for spec_path in args.spec:  # (a missing bundled example's spec: said where the installed one is)
        _bundled_spec_hint(spec_path)
    if len(args.spec) > 1 or args.ray:
        return _run_train_many(args, params, store, lambda: _writable_store(store, above))
    spec_path = args.spec[0]
    spec = load_spec(spec_path, warn=_train_warning)
    # (--skip-existing first: with nothing to do, --no-overwrite's "already exists" and a
    # read-only store's "cannot write" failed the call)
    checksum = inputs_checksum(spec, params)
    said: list[str] = []  # (--skip-existing's "…; training it again", said once --no-overwrite lets it)
    if args.skip_existing and up_to_date(spec, store, checksum, said.append):
        print(f"{spec.name!r} is already trained from {spec_path} in {store}: nothing to do")
        return 0
    if args.no_overwrite and model_path(store, spec.name).exists():
        stale = [(spec.name, retrain_reason(store, spec.name, checksum))] if args.skip_existing else []
        raise UserError(exists_message([spec.name], store, stale))
    for msg in said:
        _train_warning(msg)
    _writable_store(store, above)
    bar = tqdm(total=0, desc=f"training {spec.name}", unit="view", file=sys.stderr, disable=None, leave=False)

    def set_total(n: int) -> None:
        bar.total = n
        bar.refresh()

    def warn(msg: str) -> None:
        bar.write(f"quatrack train: warning: {msg}", file=sys.stderr)

    try:  # (the registered poses' doubts first: a wrong pose also reads as few keypoints and weak texture)
        model = train_object(spec, params, progress=bar.update, warn=warn, on_total=set_total,
                             check=lambda s, mesh: _registration_doubts(s, mesh.run_time))
    finally:
        bar.close()
    record_inputs(model, checksum)
    try:
        # (the views the replaced model learned while tracking are kept where they fit, read and
        # written under the store's lock; they were replaced, lost after a warning)
        saved = save_trained(store, model, overwrite=not args.no_overwrite, keep_learned=not args.drop_learned)
    except OSError as exc:  # (a full disk said "[Errno 28] No space left on device", naming nothing)
        raise UserError(f"cannot save {spec.name!r} in {store}: {exc.strerror or exc}") from None
    path = saved.path
    if (note := saved.note(spec.name, store)) is not None:  # (dropped unasked: the mesh or the descriptors changed)
        _train_warning(note)
    if (note := saved.backup_note(spec.name)) is not None:  # (and kept in a copy: a walk-round is expensive to repeat)
        _train_warning(note)
    s = model.manifest["training_summary"]
    counts = list(s["keypoints_per_viewset"].values())
    print(f"trained {spec.name!r} -> {path}")
    print(f"  views: {s['views']} registered, {s['synthetic_viewsets']} synthetic viewsets ({s['viewsets']} in all)")
    print(f"  keypoints per viewset: min {min(counts)}, median {int(np.median(counts))}, max {max(counts)}")
    print(f"  3-D points kept: {s['points3d_total']}")
    r = model.rfch
    print(f"  RFCH: {r.n_clusters} clusters, {r.histogram.size} bins, d = {r.distance} px, scales {list(r.scales)}")
    if saved.kept or saved.dropped:
        print(f"  views learned while tracking: {saved.kept} kept" + (f", {saved.dropped} dropped" if saved.dropped else "")
              + (" (--drop-learned)" if saved.dropped and args.drop_learned else ""))
    if saved.restored:
        print(f"  views learned while tracking: {saved.restored} carried back from {saved.path.parent / BACKUP_DIR}")
    print(f"  time: {time.perf_counter() - t0:.1f} s")
    return 0


def _bundled_spec_hint(spec_path: str) -> None:
    """Raise load_spec's "cannot read spec" with where the installed copy is, when a missing
    ``spec_path`` names a bundled example's file (``examples/cookie-box/object.json``, as the README
    writes it, outside a checkout); else nothing. The bundled examples are found as demo finds
    them (:func:`quatrack.examples.example_dir`), wherever quatrack is installed."""
    import shlex
    from pathlib import Path

    from quatrack.examples import example_dir
    from quatrack.viewsets.errors import SpecError
    from quatrack.viewsets.spec import load_spec

    path = Path(spec_path)
    if path.exists() or path.parent.name in ("", ".", ".."):
        return
    try:
        bundled = example_dir(path.parent.name) / path.name
    except FileNotFoundError:  # (not a bundled example's folder)
        return
    if not bundled.is_file():
        return
    try:
        load_spec(path)  # (its own message: the one a missing spec gives)
    except SpecError as exc:
        raise SpecError(f"{exc}; the bundled example is installed at {bundled}: "
                        f"quatrack train {shlex.quote(str(bundled))}") from None


def _writable_store(store, above) -> None:
    """Refuse a store ``train`` cannot write (``above``: its nearest existing folder), checked
    before any training: else the model, trained first, failed to save naming a temporary folder."""
    folder = store if store.exists() else above
    if folder is not None and not os.access(folder, os.W_OK | os.X_OK):
        ro = hasattr(os, "statvfs") and bool(os.statvfs(folder).f_flag & getattr(os, "ST_RDONLY", 1))
        raise UserError(f"--store {store}: cannot write in {folder} ({'read-only file system' if ro else 'permission denied'})")


def _registration_doubts(spec, mesh) -> list[str]:
    """One warning per registered view whose pose ``locate`` would not accept in its own photo:
    the mesh's visible edges there must lie on the photo's edges as a found pose's must
    (``PoseParams.min_edge_agreement``, ``min_edge_lead``). A pose given camera → object, a
    rotation transposed, ``q`` as x, y, z, w or a mesh in other units than ``t`` trained a model
    of the background without a word (the cookie box: 0.77 of its edges on the photo's, 0.22 by
    chance; transposed: 0.16, 0.21).

    A view whose ``q_wxyz`` read ``[x, y, z, w]`` fits the photo (:func:`xyzw_fits`) while the
    reading given is near chance (not :func:`plausible_edges`) is refused, a :class:`SpecError`:
    that evidence is unambiguous, and the model trained from it could not find the object even
    in that photo (user report: 30 % of the edges, 23 % by chance; read so, 95 %), with exit 0
    for a script to take. A merely doubtful pose (a thin bar on gravel: 76 %, 53 % by chance)
    is still only warned of."""
    import cv2

    from quatrack.recognition.evidence import edge_agreement, plausible_edges
    from quatrack.recognition.pose import PoseParams, edges_agree
    from quatrack.recognition.registration import xyzw_hint
    from quatrack.viewsets.errors import SpecError

    p = PoseParams()
    out = []
    for v in spec.views:
        grey = cv2.imread(str(v.image_path), cv2.IMREAD_GRAYSCALE)  # (read and checked by the training already)
        if grey is None or (grey.shape[1], grey.shape[0]) != (v.camera.width, v.camera.height):
            continue
        e = edge_agreement(grey, mesh, v.camera, v.pose)
        if e.samples < p.min_edge_samples or edges_agree(e, p):
            continue
        said = (f"view {v.index}: the mesh's edges at its pose lie on the photo's edges for {e.agreement:.0%} of "
                f"their length ({e.chance:.0%} by chance; a pose locate finds needs {p.min_edge_agreement:.0%}, "
                f"{p.min_edge_lead:.0%} above chance)")
        hint = xyzw_hint(grey, mesh, v)
        if hint and not plausible_edges(e):
            raise SpecError(f"{said}: {hint}; not trained (the model could not find the object even in this photo)")
        out.append(f"{said}: {hint or _edges_hint(e, p)}")
    return out


def _edges_hint(e, p) -> str:
    """What an edge agreement ``e`` below ``p``'s (``PoseParams``) thresholds supports. Near or
    below chance: the pose is not where the photo shows the object, so a convention or unit error
    is the first suspect. Well above chance (:func:`plausible_edges`): the pose is plausible,
    and a lead short of ``min_edge_lead`` with most edges agreeing is the background's clutter
    agreeing by chance too (the thin bar on gravel: 76 %, 53 % by chance, asked "is the pose
    object → camera, in the mesh's units?" of its true pose)."""
    from quatrack.recognition.evidence import plausible_edges

    if not plausible_edges(e):
        return "is the pose object → camera, in the mesh's units?"
    if e.agreement >= p.min_edge_agreement:
        return (f"the pose is plausible (its edges agree well above chance), but the photo's background is "
                f"cluttered ({e.chance:.0%} agree by chance), which leaves this check inconclusive (not a sign of a "
                f"convention or unit error); locate may refuse the object in this photo for the same reason "
                f"(\"no better than chance\"): a photo on a plainer background would confirm the pose")
    return ("the pose is plausible (its edges agree well above chance), but fewer lie on the photo's edges than "
            "a found pose's must: is it a little off, or the photo blurred?")


def _train_warning(msg: str) -> None:
    print(f"quatrack train: warning: {msg}", file=sys.stderr)


def _run_train_many(args: argparse.Namespace, params, store, before_training=None) -> int:
    """Several specs (or --ray): :func:`quatrack.viewsets.batch.train_many`, one line per object.
    Every spec is checked before any training; an object that fails is reported and the others
    are still trained; the exit status is 2 if any failed."""
    import time

    from quatrack.viewsets.batch import train_many
    from quatrack.viewsets.learn import BACKUP_DIR

    t0 = time.perf_counter()

    def done(r) -> None:
        for msg in r.warnings:  # (training's and the registered poses' doubts, as for one spec)
            print(f"quatrack train: warning: {r.spec}: {msg}", file=sys.stderr)
        if r.error:
            print(f"quatrack train: error: {r.spec}: {r.error}", file=sys.stderr)
        elif r.skipped:
            print(f"{r.name!r} is already trained from {r.spec} in {store}: nothing to do")
        else:
            s = r.summary
            learned = ""  # (as one spec's "views learned while tracking" line)
            if r.learned_kept or r.learned_dropped:
                learned = f", views learned while tracking: {r.learned_kept} kept" + (
                    f", {r.learned_dropped} dropped" + (" (--drop-learned)" if args.drop_learned else "")
                    if r.learned_dropped else "")
            if r.learned_restored:
                learned += f", views learned while tracking: {r.learned_restored} carried back from {store / BACKUP_DIR}"
            print(f"trained {r.name!r} -> {r.path}  ({s['viewsets']} viewsets, {s['points3d_total']} 3-D points"
                  f"{learned}, {r.seconds:.1f} s)", flush=True)

    results = train_many(args.spec, store, params, jobs=args.jobs, overwrite=not args.no_overwrite,
                         skip_existing=args.skip_existing, ray_address=args.ray, on_done=done,
                         warn=_train_warning,
                         check=_registration_doubts, keep_learned=not args.drop_learned,
                         before_training=before_training)
    failed = sum(r.error is not None for r in results)
    skipped = sum(r.skipped for r in results)  # (counted as trained: "3 of 3 objects trained" when none was)
    where = f"on Ray ({args.ray})" if args.ray else f"locally, --jobs {args.jobs}"
    print(f"{len(results) - failed - skipped} of {len(results)} objects trained {where} in {time.perf_counter() - t0:.1f} s"
          + (f"; {skipped} already trained from their spec (--skip-existing)" if skipped else ""))
    return 2 if failed else 0


def _add_models(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    for name, help_text in (("list", "list the trained objects"), ("show", "print a model's manifest"),
                            ("delete", "delete a trained object")):
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name != "list":
            p.add_argument("name", metavar="NAME")
        else:
            p.add_argument("--check", action="store_true",
                           help="exit 1 if any object is BROKEN (its model cannot be loaded, or its folder has no manifest)")
        p.add_argument("--store", metavar="DIR", help="model store (default: $QUATRACK_STORE or the user data directory)")


def _run_models(args: argparse.Namespace) -> int:
    import json
    import shlex

    from quatrack.viewsets.names import NAME_RE
    from quatrack.viewsets.learn import backup_left
    from quatrack.viewsets.store import (MANIFEST, broken_folders, delete_model, learned_points, list_models, load_manifest,
                                         load_model, remove_stale, resolve_store, store_note)

    store = resolve_store(args.store)
    if store.exists() and not store.is_dir():  # (else listed as an empty store, exit 0)
        raise UserError(f"--store {store}: not a directory")
    name = getattr(args, "name", None)
    if isinstance(name, str) and name.endswith("/") and NAME_RE.fullmatch(name.rstrip("/")):
        args.name = name.rstrip("/")  # (the object's folder, as the shell completes it in the store: `delete box/`)
    if args.action == "list":
        remove_stale(store)
        names = list_models(store)
        # folders that are not objects: one with an object's name (a copy cut short) is a BROKEN
        # row, `models delete` removes it; another (lost+found) is said on stderr, not fatal
        others = broken_folders(store)
        rows = {name: None for name in names} | {n: why for n, why in others.items() if NAME_RE.fullmatch(n)}
        for n, why in others.items():
            if n not in rows:
                print(f"quatrack models: skipped {store / n} (not an object's folder): it {why}", file=sys.stderr)
        broken = 0
        if not rows:  # (said on stderr: stdout stays the rows, none, for scripts; it printed nothing at all)
            note = store_note(store)
            train = f"; train one with `quatrack train SPEC.json{'' if args.store is None else ' --store ' + shlex.quote(str(store))}`"
            print(f"quatrack models: no trained object in {store}{note}{'' if (store / MANIFEST).is_file() else train}",
                  file=sys.stderr)  # (a model's own folder: "train one" there was the wrong advice)
        for name in sorted(rows):
            try:  # fully loaded, so that a model `locate`/`serve` cannot use is marked broken here
                if rows[name] is not None:
                    raise ValueError(f"object {name!r}: its folder {rows[name]}")
                m = load_model(store, name).manifest
            except ValueError as exc:
                print(f"{name}\tBROKEN\t{exc}")
                broken += 1
                continue
            s = m.get("training_summary", {})
            learned = f" (+{m['learned_viewsets']} learned)" if m.get("learned_viewsets") else ""  # (tracking's, not training's)
            # (training's points, then the learned views' own: they were left out, a walk-round's views adding none)
            points = f" (+{n} learned)" if (n := learned_points(m)) else ""
            print(f"{name}\t{s.get('viewsets', '?')} viewsets{learned}\t{s.get('points3d_total', '?')} points{points}\t"
                  f"{m.get('created', '?')}")
        if broken and args.check:  # (without --check: exit 0, as always)
            print(f"quatrack models: {broken} of {len(rows)} object(s) BROKEN (--check)", file=sys.stderr)
            return 1
        return 0
    if args.action == "show":
        print(json.dumps(load_manifest(store, args.name), indent=1))
        return 0
    if args.action == "delete":
        delete_model(store, args.name)
        print(f"deleted {args.name!r} from {store}")
        if (note := backup_left(store, args.name)) is not None:
            print(f"quatrack models: note: {note}", file=sys.stderr)
        return 0
    raise UserError(f"unknown action {args.action!r}")


def _add_locate(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="image files (JPEG, PNG, WebP, TIFF, ...)")
    parser.add_argument("--object", required=True, metavar="NAME",
                        help="a trained object (see `quatrack models list`), or `all`: search every trained object")
    parser.add_argument("--camera", required=True, metavar="CAMERA", help="camera file of the images (JSON, or OpenCV YAML)")
    parser.add_argument("--store", metavar="DIR", help="model store (default: $QUATRACK_STORE or the user data directory)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line, per image")
    parser.add_argument("--whole-image", action="store_true", help="skip the RFCH window: match SIFT in the whole image")
    parser.add_argument("--max-pixels", type=int, default=4_000_000, metavar="N",
                        help="larger images are downscaled to this many pixels (default 4000000)")


def _image_arguments(images: list[str]) -> list[str]:
    """``locate``'s IMAGE arguments expanded as ``track --images`` expands its own
    (:func:`~quatrack.recognition.trackio.image_paths`), one argument at a time: a glob the shell
    left alone (quoted, or in a script) is its files sorted by name (``locate 'frames/*.png'``
    said "cannot read image frames/*.png: No such file"), a list file (``.txt``, ``.lst``) the
    images it names (it was read as an image: "cannot be decoded"), a file that exists is taken
    as named (``[1].png`` is no pattern then). An argument naming no file (a missing one, a glob
    matching none, a folder) stays, to be reported on its line (:func:`_read_argument`)."""
    from quatrack.recognition.trackio import SourceError, image_paths

    out = []
    for arg in images:
        try:
            out += image_paths([arg]) or [arg]
        except SourceError as exc:  # (a list file that cannot be read: its message names track's --images)
            raise UserError(str(exc).removeprefix("--images ")) from None
    return out


def _read_argument(path: str):
    """The image an IMAGE argument (:func:`_image_arguments`) names, or an
    :class:`~quatrack.recognition.images.ImageError` for its line: a glob that matches no file
    says so, in ``track --images``' words (it said "cannot read image empty/*.png: No such file
    or directory", as if a file had that name), and a folder asks for a glob of its images, as
    ``track`` does."""
    import glob

    from quatrack.recognition.images import ImageError, read_image

    if os.path.isdir(path):
        raise ImageError(f"{path}: is a folder; give a glob of its images, e.g. {os.path.join(path, '*.png')!r}")
    if not os.path.exists(path) and glob.has_magic(path):
        raise ImageError(f"{path}: no file matches")
    return read_image(path)


def _run_locate(args: argparse.Namespace) -> int:
    """Recognition + initial pose per image. A bad image is reported on its own line (``error``
    in JSON) and the others still run; the exit status is 1 if any image failed."""
    import json

    from quatrack.recognition.images import ImageError
    from quatrack.recognition.locate import LocateParams, locate
    from quatrack.recognition.match import index_for
    from quatrack.viewsets.camera import load_camera
    from quatrack.viewsets.store import load_model, resolve_store

    if args.max_pixels < 32 * 32:
        raise UserError("--max-pixels must be at least 1024")
    args.images = _image_arguments(args.images)
    camera = load_camera(args.camera)
    params = LocateParams(use_window=not args.whole_image, max_pixels=args.max_pixels)
    if args.object == "all":
        return _locate_all(args, camera, params)
    model = load_model(resolve_store(args.store), args.object)
    index = index_for(model)
    failed = False
    said: set = set()
    for path in args.images:
        try:
            image = _read_argument(path)
            result = locate(image, _resized(camera, image, said, args.camera), model, params, index=index)
        except ImageError as exc:
            failed = True
            if args.json:
                print(json.dumps({"image": path, "found": False, "error": str(exc)}), flush=True)
            else:
                print(f"{path}: error: {_unprefixed(exc, path)}", file=sys.stderr)
            continue
        if args.json:
            print(json.dumps({"image": path, **result.to_json()}), flush=True)
        elif result.found:
            t = _position_text(result.t, model.mesh.extent)
            q = ", ".join(f"{v:.4f}" for v in result.q_wxyz)
            print(f"{path}: found  t = [{t}]  q_wxyz = [{q}]  inliers {result.inliers}/{result.matches}  "
                  f"rms {result.reprojection_rms_px:.2f} px  confidence {result.confidence:.2f}  "
                  f"viewset {result.viewset}  {result.time_ms['total']:.0f} ms")  # (confidence: as --object all's lines)
        else:
            print(f"{path}: not found ({result.reason})  {result.time_ms['total']:.0f} ms")
    return 1 if failed else 0


def _resized(camera, image, said: set, where: str = "--camera"):
    """``camera``, scaled when ``image`` is its images resized (:func:`~quatrack.viewsets.camera.
    resized_for`: the same aspect ratio), said once per size on stderr; otherwise as it is (an
    image of another aspect ratio is refused by ``locate``, as before). A camera whose numbers
    show its stated size is wrong (:func:`~quatrack.viewsets.camera.stated_size_doubt`: its
    principal point the centre of the image as it is) is refused for this image (``where``: the
    camera file): scaled, its focal length was halved and the object "not found"."""
    from quatrack.recognition.images import ImageError
    from quatrack.viewsets.camera import resized_for, stated_size_doubt

    h, w = image.shape[:2]
    fitted, note = resized_for(camera, w, h, "resized images")
    if note is not None and (doubt := stated_size_doubt(camera, w, h)) is not None:
        raise ImageError(f"{where}: {doubt} (it was not scaled to the image)")
    if note is not None and (w, h) not in said:
        said.add((w, h))
        print(f"quatrack locate: warning: {note}", file=sys.stderr)
    return fitted


def _position_text(t, extent: float) -> str:
    """A position in the mesh's units, to a thousandth of the object's diameter: a mesh in metres
    shows millimetres (``.2f`` printed a 10 cm cube's position as 0.00, -0.00, 0.36)."""
    from quatrack.recognition.overlay import resolving_decimals

    n = resolving_decimals(1e-3 * float(extent))
    return ", ".join(f"{v:.{n}f}" for v in np.round(np.asarray(t, float), n) + 0.0)  # (+0: no "-0.000")


def _locate_all(args: argparse.Namespace, camera, params) -> int:
    """``--object all``: every trained object searched in each image; one line per image,
    ``{"image", "found", "objects": [the locate object of each one found], "searched": [names],
    "not_found": {name: why}, "failed": {name: why}, "time_ms": {"total"}}`` (as ``POST /v1/pose``
    answers: a broken model is skipped, and each line says so, not only stderr once; each object
    searched and not found says why, as ``--object NAME`` would — a product hidden by its
    look-alike's window was invisible in the answer)."""
    import json
    import time

    from quatrack.recognition.images import ImageError
    from quatrack.recognition.locate import locate_all, not_found
    from quatrack.viewsets.store import list_models, load_model, resolve_store, store_note

    store = resolve_store(args.store)
    names = list_models(store)
    if not names:  # (as models list says it: a typo in --store read as an empty store)
        raise UserError(f"no trained object in {store}{store_note(store)}")
    from quatrack.viewsets.errors import StoreError

    models, skipped = [], {}
    for n in names:
        try:
            models.append(load_model(store, n))
        except StoreError as exc:  # a broken model is skipped, said once; the others are searched
            skipped[n] = str(exc)
            print(f"quatrack locate: warning: {exc}; skipped", file=sys.stderr)  # (exc names the object)
    if not models:
        raise UserError(f"no usable trained object in {store}")
    extent = {m.name: m.mesh.extent for m in models}
    failed = False
    said: set = set()
    for path in args.images:
        t0 = time.perf_counter()
        try:
            image = _read_argument(path)
            results = locate_all(image, _resized(camera, image, said, args.camera), models, params)
        except ImageError as exc:
            failed = True
            if args.json:
                print(json.dumps({"image": path, "found": False, "error": str(exc)}), flush=True)
            else:
                print(f"{path}: error: {_unprefixed(exc, path)}", file=sys.stderr)
            continue
        found = [r for r in results if r.found]
        total = (time.perf_counter() - t0) * 1e3
        if args.json:
            print(json.dumps({"image": path, "found": bool(found), "objects": [r.to_json() for r in found],
                              "searched": [m.name for m in models], "not_found": not_found(results),
                              "failed": skipped,
                              "time_ms": {"total": round(total, 3)}}), flush=True)
        elif not found:
            print(f"{path}: none of {len(models)} objects found  {total:.0f} ms")
        for r in found if not args.json else ():
            t = _position_text(r.t, extent[r.object])
            q = ", ".join(f"{v:.4f}" for v in r.q_wxyz)
            rivals = "".join(f"  (rival: {v['object']} confidence {v['confidence']:.3f})" for v in r.rivals or ())
            conf = f"{r.confidence:.3f}" if rivals else f"{r.confidence:.2f}"  # (its rivals' margin: thousandths)
            print(f"{path}: found {r.object}  t = [{t}]  q_wxyz = [{q}]  inliers {r.inliers}/{r.matches}  "
                  f"confidence {conf}  {total:.0f} ms{rivals}")
    return 1 if failed else 0


def _add_track(parser: argparse.ArgumentParser) -> None:
    from quatrack.track_cli import add_arguments

    add_arguments(parser)


def _run_track(args: argparse.Namespace) -> int:
    from quatrack.track_cli import run

    if args.object == "all":  # (locate's word for every object: track said "no object named 'all'")
        from quatrack.viewsets.store import list_models, resolve_store

        if "all" not in list_models(resolve_store(args.store)):  # (a store from before the name was reserved)
            raise UserError("--object all: track follows one object; run one track per object "
                            "(`quatrack models list` names them; `quatrack locate --object all` searches every one)")
    return run(args)


def _add_register(parser: argparse.ArgumentParser) -> None:
    from quatrack.register_cli import add_arguments

    add_arguments(parser)


def _run_register(args: argparse.Namespace) -> int:
    from quatrack.register_cli import run

    return run(args)


def _add_serve(parser: argparse.ArgumentParser) -> None:
    from quatrack.service.cli import add_serve

    add_serve(parser)


def _run_serve(args: argparse.Namespace) -> int:
    from quatrack.service.cli import run_serve

    return run_serve(args)


def _add_demo(parser: argparse.ArgumentParser) -> None:
    from quatrack.demo import add_arguments

    add_arguments(parser)


def _run_demo(args: argparse.Namespace) -> int:
    from quatrack.demo import run

    return run(args)


COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {
    "bench": ("run a benchmark and print its figures", _add_bench, _run_bench),
    "register": ("solve a spec's photo poses from clicked points, refine them on the mesh's edges, write the spec back",
                 _add_register, _run_register),
    "train": ("train an object's model (RFCH + SIFT viewsets) from its spec into the model store", _add_train, _run_train),
    "models": ("list, show or delete the trained objects in the model store", _add_models, _run_models),
    "locate": ("find a trained object in images and estimate its initial pose", _add_locate, _run_locate),
    "track": ("track a trained object through a video, camera, stream or image sequence (poses to CSV, JSON lines or BOP)", _add_track, _run_track),
    "serve": ("run the HTTP/WebSocket service (pose of an image, tracking of a stream)", _add_serve, _run_serve),
    "demo": ("stream a video through the service's WebSocket; write poses (CSV), an overlay video and a plot", _add_demo, _run_demo),
}


def build_parser() -> argparse.ArgumentParser:
    from quatrack import __version__

    parser = argparse.ArgumentParser(
        prog="quatrack",
        description="Find a known textured object, estimate its 6-DoF pose, and track it.",
    )
    parser.add_argument("--version", action="version", version=f"quatrack {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_text, add_arguments, _) in COMMANDS.items():
        add_arguments(sub.add_parser(name, help=help_text, description=help_text))
    return parser


#: the options (argparse ``dest``) of every command that name files or folders: a leading ``~`` is
#: expanded in them, as a shell does in an unquoted word. The shell leaves ``--out=~/poses.csv`` and
#: a quoted ``'~/box.mp4'`` as they are: ``track`` said "--video ~/box.mp4: no such file" and
#: "--out ~/poses.csv: the folder .../~ does not exist" (``--store`` and ``--images`` were expanded).
PATH_OPTIONS = ("video", "images", "camera", "out", "overlay", "plot", "store", "init_pose", "sheet", "spec",
                "mesh", "out_dir")


def _expand_user(args: argparse.Namespace) -> None:
    """``~`` and ``~user`` expanded in the :data:`PATH_OPTIONS` of ``args``, in place (a camera
    index, a URL or ``none`` is left as it is: they do not start with ``~``)."""
    for name in PATH_OPTIONS:
        value = getattr(args, name, None)
        if isinstance(value, str):
            setattr(args, name, os.path.expanduser(value))
        elif isinstance(value, list):
            setattr(args, name, [os.path.expanduser(v) if isinstance(v, str) else v for v in value])


def main(argv: list[str] | None = None) -> int:
    try:  # (building the parser imports the commands' modules: a Ctrl-C then is no traceback either)
        parser = build_parser()
        args = parser.parse_args(argv)
        _expand_user(args)
    except KeyboardInterrupt:
        print("quatrack: interrupted", file=sys.stderr)
        return 130
    with warnings.catch_warnings():  # (showwarning restored on return: main() may be called in-process)
        warnings.showwarning = _warning_line(args.command)
        return _run(COMMANDS[args.command][2], args)


def _warning_line(command: str):
    """A :func:`warnings.showwarning` printing ``quatrack COMMAND: warning: MESSAGE`` on one line,
    as the commands' own warnings read: Python's default format gave the library's source file,
    line number, class and a second line of code (``recognition.images.BitDepthWarning`` for a
    10- or 12-bit image given to ``locate``)."""
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = " ".join(str(message).split())  # (one line)
        file = file if file is not None else sys.stderr
        try:  # (on a terminal, a progress line being drawn is cleared first: the warning was appended to it)
            clear = "\r\x1b[K" if getattr(file, "isatty", lambda: False)() else ""
            print(f"{clear}quatrack {command}: warning: {text}", file=file)
        except (OSError, ValueError):  # (stderr gone: as warnings' own, nothing to say it on)
            pass

    return show


def _run(run, args: argparse.Namespace) -> int:
    """``run(args)`` with the errors the module docstring describes turned into one line."""
    try:
        tune_allocator()
        limit_blas_threads()  # recognition's small BLAS products: one thread (runtime.py says why)
        quiet_ffmpeg()  # no FFmpeg decoder chatter from any command reading a video (box.mp4's h264)
        return run(args)
    except KeyboardInterrupt:
        print("quatrack: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError as exc:
        if not _stdout_closed():  # (another pipe or socket broke: a real error)
            print(f"quatrack {args.command}: error: {exc}", file=sys.stderr)
            return 2
        return 1
    except (UserError, ValueError, OSError) as exc:
        print(f"quatrack {args.command}: error: {exc}", file=sys.stderr)
        return 2


def _unprefixed(exc: Exception, path: str) -> str:
    """An image's error without the file name it starts with (the line names the file already)."""
    msg = str(exc)
    return msg[len(path) + 2:] if msg.startswith(f"{path}: ") else msg


def _stdout_closed() -> bool:
    """Whether the reader of standard output has gone (``quatrack … | head``): then the command
    stops quietly, as Unix tools do, instead of reporting an error that did not happen (the work
    was done; its reader wanted no more). Standard output is pointed at the null device, so the
    interpreter's own flush at exit does not fail again (Python's documentation, *Note on
    SIGPIPE*); the exit status is 1, as that note says."""
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        pass
    except (OSError, ValueError):
        return False
    else:  # (nothing was left to flush: ask the pipe itself; its reader gone, it polls POLLERR)
        try:
            poll = select.poll()
            poll.register(sys.stdout.fileno(), select.POLLOUT)
            if not any(ev & select.POLLERR for _, ev in poll.poll(0)):
                return False
        except (AttributeError, OSError, ValueError):  # (no poll here, or no file behind stdout)
            return False
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    return True


if __name__ == "__main__":
    # ``python -m quatrack.cli``: this file runs as ``__main__``, a second copy of the module whose
    # UserError the other modules (track_cli.py) do not raise; run the one they know instead
    from quatrack.cli import main as _main

    sys.exit(_main())

"""Training several objects in one call: in local processes, or as tasks on a Ray cluster.

Every spec is loaded (and so checked) before any training starts, so a typo in the last spec
costs no work. Each object is then trained by :func:`quatrack.viewsets.train.train_object` and
written by :func:`quatrack.viewsets.learn.save_trained` (as one spec is: the replaced model's
views learned while tracking are kept where they fit) through
:func:`quatrack.viewsets.store.save_model`, which renames a complete model into place:
many trainings — on one machine or on many machines sharing the store (NFS, a cluster volume) —
never leave a half-written model, and a replica reading the store sees the old model or the new.

Locally, the CPU budget ``jobs`` is split: ``min(jobs, n_specs)`` processes train specs at once,
each building ``max(1, jobs // processes)`` views in parallel (threads, ``TrainParams.jobs``).
With one spec this is exactly the former meaning of ``--jobs``: views built in parallel.

With Ray (``pip install 'quatrack[ray]'``), each spec is one task (``num_cpus = jobs`` per task)
on an existing cluster (``ray.init(address=...)``); the spec's files and the store must be at the
same paths on every node (a shared filesystem), as they are for any shared model store.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .errors import SpecError, StoreError
from .spec import load_spec
from .learn import save_trained
from .store import NOT_STORED, model_path, retrain_reason
from .train import TrainParams, train_object


@dataclass(frozen=True)
class Trained:
    """The outcome of one spec: the model's path and training summary, or the error."""

    spec: str
    name: str
    path: str | None = None
    summary: dict | None = None
    seconds: float = 0.0
    skipped: bool = False  # already trained from this very spec (skip_existing)
    error: str | None = None
    warnings: tuple[str, ...] = ()  # training's own (weak texture, ...), ``check``'s, then the learned views' note
    learned_kept: int = 0  # views the replaced model learned while tracking, carried into the new one
    learned_dropped: int = 0  # ... and not (another mesh or descriptors, ``keep_learned=False``)
    learned_restored: int = 0  # views carried back from the object's copy in ``STORE/.learned-backup`` (learn.BACKUP_DIR)


def spec_files(spec) -> list[tuple[str, Path]]:
    """The files a spec names, each with what it is: the mesh, each view's photo and mask."""
    return [("mesh", spec.mesh_path)] + [(f"view {v.index}: image", v.image_path) for v in spec.views] \
        + [(f"view {v.index}: mask", v.mask_path) for v in spec.views if v.mask_path is not None]


def inputs_checksum(spec, params: TrainParams) -> str:
    """SHA-256 of everything a training reads: the spec file's bytes, the mesh, photos and masks
    it names (their contents), each view's camera and pose as parsed (a camera given as a file
    changes them) and the training options (``jobs`` aside: it changes the time, not the model).
    ``train --skip-existing`` compares it with the stored model's (``spec.inputs_sha256``): it
    compared the spec file's bytes only, so an edited photo, mesh or camera file, or other
    options, were "nothing to do". Files are named relative to the spec's folder, not by their
    absolute paths: the same inputs copied elsewhere (another checkout, a container's mount) were
    "changed" and trained again."""
    h = hashlib.sha256(spec.checksum.encode())
    base = Path(spec.path).resolve().parent
    options = dataclasses.asdict(dataclasses.replace(params, jobs=1))
    h.update(json.dumps(options, sort_keys=True, default=repr).encode())
    for v in spec.views:
        c = v.camera
        h.update(repr((v.index, c.fx, c.fy, c.cx, c.cy, list(map(float, c.dist_coeffs.ravel())), c.width, c.height,
                       v.pose.R.tolist(), v.pose.t.tolist())).encode())
    for what, f in spec_files(spec):
        h.update(f"{what}\0{_relative_name(f, base)}\0".encode())
        try:
            with open(f, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
        except OSError as exc:  # (a missing file: the training's own message names it)
            h.update(f"unreadable: {exc.errno}".encode())
    return h.hexdigest()


def _relative_name(path: Path, base: Path) -> str:
    """``path`` relative to ``base`` (``/``-separated), or its name alone on another drive."""
    try:
        return Path(os.path.relpath(path, base)).as_posix()
    except ValueError:  # (Windows: another drive)
        return Path(path).name


def record_inputs(model, checksum: str) -> None:
    """Write :func:`inputs_checksum` into ``model``'s manifest (``spec.inputs_sha256``), for the
    next ``--skip-existing`` to compare."""
    model.manifest["spec"] = {**(model.manifest.get("spec") or {}), "inputs_sha256": checksum}


def up_to_date(spec, store: str | Path, checksum: str, warn: Callable[[str], None] | None = None) -> bool:
    """Whether ``--skip-existing`` skips ``spec``: the store holds its object trained from these
    very inputs (``checksum``: :func:`inputs_checksum`) and it loads. A stored model that is
    trained again is said why to ``warn`` (broken, older, inputs changed)."""
    why = retrain_reason(store, spec.name, checksum)
    if why is not None and why != NOT_STORED and warn is not None:
        warn(f"{spec.name!r} in {store}: {why}; training it again")
    return why is None


def train_one(spec_path: str, store: str, params: TrainParams, overwrite: bool = True,
              skip_existing: bool = False, check: Callable | None = None, keep_learned: bool = True) -> Trained:
    """Train one spec into ``store`` (atomically). Errors of the spec's content come back in
    :attr:`Trained.error` rather than raised, so that one bad object does not stop the others.
    Warnings come back in :attr:`Trained.warnings`: training's own, then ``check(spec, mesh)``'s
    (a picklable function of the spec and the model's run-time mesh giving a list of messages:
    the CLI's doubts about a registered pose, which this layer cannot judge), then the note of
    views learned while tracking that the new model could not keep. The model is saved as one
    spec's is, by :func:`~.learn.save_trained`: the replaced model's learned views are carried
    where they fit (``keep_learned=False``, ``train --drop-learned``: none), so training several
    specs at once no longer drops them all."""
    t0 = time.perf_counter()
    name = "?"
    warnings: list[str] = []
    try:
        spec = load_spec(spec_path)
        name = spec.name
        checksum = inputs_checksum(spec, params)
        if skip_existing and up_to_date(spec, store, checksum, warnings.append):
            return Trained(spec_path, name, str(model_path(store, name)), skipped=True)
        model = train_object(spec, params, warn=warnings.append)
        record_inputs(model, checksum)
        if check is not None:
            warnings.extend(check(spec, model.mesh.run_time))
        try:
            saved = save_trained(store, model, overwrite=overwrite, keep_learned=keep_learned)
        except OSError as exc:  # (a full disk said "[Errno 28] No space left on device", naming nothing)
            raise StoreError(f"cannot save {name!r} in {store}: {exc.strerror or exc}") from None
    except (SpecError, StoreError, ValueError, OSError) as exc:
        return Trained(spec_path, name, error=str(exc), seconds=time.perf_counter() - t0, warnings=tuple(warnings))
    if (note := saved.note(name, store)) is not None:  # (dropped unasked: the mesh or the descriptors changed)
        warnings.append(note)
    if (note := saved.backup_note(name)) is not None:  # (and where they are kept: learn.BACKUP_DIR)
        warnings.append(note)
    return Trained(spec_path, name, str(saved.path), model.manifest["training_summary"], time.perf_counter() - t0,
                   warnings=tuple(warnings), learned_kept=saved.kept, learned_dropped=saved.dropped,
                   learned_restored=saved.restored)


def check_specs(spec_paths: list[str], store: Path, no_overwrite: bool, warn=None) -> list[str]:
    """Absolute paths of the specs, after loading each and finding the mesh, photos and masks it
    names (raises SpecError naming the culprit); two specs of one object name, or existing objects with ``no_overwrite`` (all named), are refused.
    ``warn``: as :func:`~.spec.load_spec`'s (fields a spec does not know)."""
    return [p for p, _, _ in _plan(spec_paths, store, no_overwrite, warn)]


def _plan(spec_paths: list[str], store: Path, no_overwrite: bool, warn=None,
          params: TrainParams | None = None) -> list[tuple[str, str, bool]]:
    """:func:`check_specs`, each absolute path with its object's name and whether it is already trained (``params``
    given: ``--skip-existing``, :func:`up_to_date`). An object up to date is not refused by
    ``no_overwrite`` (nothing is written: "already exists" failed a call with nothing to do), and
    the refusal names every existing object (it named the first)."""
    names: dict[str, str] = {}
    out, existing, stale = [], [], []
    for p in spec_paths:
        spec = load_spec(p, warn)
        # the files it names must be there too (a typo in a path is the commonest bad spec; only
        # looked up here, read when the object trains)
        for what, f in spec_files(spec):
            if not f.is_file():
                raise SpecError(f"{p}: {what}: {f}: {'not a file' if f.exists() else 'file not found'}")
        if spec.name in names:
            raise SpecError(f"{p} and {names[spec.name]} both define object {spec.name!r}")
        names[spec.name] = p
        kept = no_overwrite and model_path(store, spec.name).exists()  # (not "training it again", then refused)
        said: list[str] = []
        checksum = inputs_checksum(spec, params) if params is not None else None  # (hashes every photo: once)
        done = checksum is not None and up_to_date(spec, store, checksum, said.append)
        if kept and not done:
            existing.append(spec.name)
            if checksum is not None:
                stale.append((spec.name, retrain_reason(store, spec.name, checksum)))
        elif warn:
            for msg in said:
                warn(f"{p}: {msg}")
        out.append((str(Path(p).resolve()), spec.name, done))
    if existing:
        raise StoreError(exists_message(existing, store, stale))
    return out


def exists_message(names: list[str], store, stale: list[tuple[str, str | None]] = ()) -> str:
    """``--no-overwrite``'s refusal, naming every object that exists; ``stale``: ``(name, why)``
    of those ``--skip-existing`` found out of date (:func:`retrain_reason`), said in the same
    line (a warning "…; training it again" came first, then this refusal)."""
    if len(names) == 1:
        msg = f"object {names[0]!r} already exists in {store} (and --no-overwrite was given)"
    else:
        msg = f"objects {', '.join(map(repr, names))} already exist in {store} (and --no-overwrite was given)"
    stale = [(n, why) for n, why in stale if why]
    if stale:
        msg += "; --skip-existing would train " + ", ".join(f"{n!r} again ({why})" for n, why in stale)
    return msg


def train_many(spec_paths: list[str], store: str | Path, params: TrainParams = TrainParams(), jobs: int = 2,
               overwrite: bool = True, skip_existing: bool = False, ray_address: str | None = None,
               on_done: Callable[[Trained], None] | None = None,
               warn: Callable[[str], None] | None = None, check: Callable | None = None,
               keep_learned: bool = True, before_training: Callable[[], None] | None = None) -> list[Trained]:
    """Train every spec into ``store``; results in the order of ``spec_paths``.

    ``jobs`` is the CPU budget (see the module docstring); ``ray_address`` sends each spec to a
    Ray cluster instead ("auto" finds a local one, "local" starts a private one for this call).
    ``on_done`` is called as each spec finishes (for progress lines); ``warn`` is told of fields
    a spec does not know, as the specs are checked; ``check``: as :func:`train_one`'s (each
    result's ``warnings``); ``keep_learned``: as :func:`train_one`'s (False: ``--drop-learned``).
    With ``skip_existing`` the objects already trained from their inputs are found before any
    training (and told to ``on_done`` first); ``before_training`` is called once the specs are
    checked, only if some object is to be trained (the CLI's refusal of a store it cannot write:
    a call with nothing to do needs none).
    """
    if jobs < 1:
        raise ValueError("jobs must be at least 1")
    store = str(Path(store).expanduser().resolve())
    plan = _plan(spec_paths, Path(store), not overwrite, warn, params if skip_existing else None)
    results: dict[str, Trained] = {}
    for p, name, done in plan:
        if done:
            results[p] = Trained(p, name, str(model_path(store, name)), skipped=True)
            if on_done:
                on_done(results[p])
    specs = [p for p, _, done in plan if not done]
    if specs:
        if before_training is not None:
            before_training()
        Path(store).mkdir(parents=True, exist_ok=True)
        results.update(_train(specs, store, params, jobs, overwrite, ray_address, on_done, check, keep_learned))
    return [results[p] for p, _, _ in plan]


def _train(specs, store, params, jobs, overwrite, ray_address, on_done, check, keep_learned) -> dict[str, Trained]:
    """Train ``specs`` (none skipped: :func:`train_many` decided which are up to date) locally or on Ray."""
    if ray_address is not None:
        return _on_ray(specs, store, dataclasses.replace(params, jobs=jobs), overwrite, ray_address, on_done, check,
                       keep_learned)
    processes = min(jobs, len(specs))
    per = dataclasses.replace(params, jobs=max(1, jobs // processes))
    return _local(specs, store, per, overwrite, processes, on_done, check, keep_learned)


def _local(specs, store, params, overwrite, processes, on_done, check=None,
           keep_learned=True) -> dict[str, Trained]:
    if processes == 1:
        out = {}
        for p in specs:
            out[p] = train_one(p, store, params, overwrite, check=check, keep_learned=keep_learned)
            if on_done:
                on_done(out[p])
        return out
    import multiprocessing

    out = {}
    # spawn, not fork: the parent may hold OpenCV/BLAS thread pools that fork would copy mid-use
    with ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_ignore_ctrl_c) as pool:
        futures = {pool.submit(train_one, p, store, params, overwrite, check=check, keep_learned=keep_learned): p
                   for p in specs}
        try:
            for f in as_completed(futures):
                out[futures[f]] = f.result()
                if on_done:
                    on_done(out[futures[f]])
        except KeyboardInterrupt:
            # Ctrl-C reaches the workers too; had they taken it, each printed its traceback, and
            # went on to train (and store) the specs queued to it: they ignore it, and end here
            # (a model is renamed into place whole, or not at all)
            for proc in list((getattr(pool, "_processes", None) or {}).values()):
                proc.terminate()
            pool.shutdown(wait=False, cancel_futures=True)
            raise
    return out


def _ignore_ctrl_c() -> None:
    """A worker process's initializer: Ctrl-C is the parent's to handle (:func:`_local`)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _on_ray(specs, store, params, overwrite, address, on_done, check=None,
            keep_learned=True) -> dict[str, Trained]:
    try:
        import ray
    except ImportError:
        raise ValueError("--ray needs Ray: pip install 'quatrack[ray]'") from None
    _reachable(address)
    started = not ray.is_initialized()
    if started:
        kwargs = {"address": None if address == "local" else address, "logging_level": "WARNING",
                  "log_to_driver": False}
        if address == "local":
            kwargs.update(num_cpus=os.cpu_count() or 1, include_dashboard=False)
        try:
            ray.init(**kwargs)
        except ConnectionError as exc:
            raise ValueError(f"--ray {address}: cannot connect to a Ray cluster ({exc})") from None
    try:
        remote = ray.remote(num_cpus=params.jobs, max_retries=1)(train_one)
        refs = {remote.remote(p, store, params, overwrite, check=check, keep_learned=keep_learned): p for p in specs}
        out = {}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                out[refs[ref]] = ray.get(ref)
                if on_done:
                    on_done(out[refs[ref]])
        return out
    finally:
        if started:
            ray.shutdown()


def _reachable(address: str, timeout: float = 10.0) -> None:
    """Refuse a ``host:port`` nobody listens on, in seconds: ``ray.init`` would retry for minutes."""
    import socket

    target = address.removeprefix("ray://")
    host, sep, port = target.rpartition(":")
    if address in ("auto", "local") or not sep or not port.isdigit():
        return
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as exc:
        raise ValueError(f"--ray {address}: no Ray cluster answers there ({exc.strerror or exc})") from None

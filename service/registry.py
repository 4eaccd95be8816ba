"""The object models the service answers for, kept in step with the model store.

Models and their FLANN indexes are immutable after loading, so every request and session uses
the same objects without locks. The store is the truth, and it changes under a running server:

- ``quatrack train`` replaces ``store/NAME`` by an atomic rename, so the folder's files get new
  inodes and times (:func:`~quatrack.viewsets.store.model_stamp`). A request whose object's stamp
  differs from the loaded one loads the new model, and a watcher thread polls the stamps every
  ``poll_s`` seconds, so new sessions get the retrained model within seconds. A running session
  keeps the ``(model, index)`` pair it started with: replacing the registry's entry never touches
  it, and the old model is freed when its last session ends.
- ``quatrack models delete`` renames the folder away: an object missing on two polls in a row is
  taken out of service (one miss may be a retraining between its two renames).
- A model that cannot be loaded (truncated, garbled, keys missing) is *that object's* error:
  logged once per version of the files, listed by ``/readyz`` under ``failed``, answered 503
  ``model_unavailable`` naming the object — while the other objects are served. A broken
  retraining of an object already loaded takes it out of service the same way (new requests and
  sessions 503, ``/readyz`` lists it under ``failed`` only, ``GET /v1/objects`` ``loaded: false``
  with its ``error``): the contract's one rule for a model that cannot be read. It had kept the
  previous model served while every endpoint also called it failed; running sessions keep theirs.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from quatrack.recognition.match import ModelIndex, index_for
from quatrack.viewsets.errors import StoreError
from quatrack.viewsets.features import Features
from quatrack.viewsets.names import NAME_RE, check_object_name
from quatrack.viewsets.store import (ObjectModel, broken_folders, list_models, load_manifest, load_model, model_stamp,
                                     remove_stale)

from .errors import ApiError

log = logging.getLogger("quatrack.service")


@dataclass(frozen=True)
class LoadedModel:
    model: ObjectModel
    index: ModelIndex
    stamp: tuple  # model_stamp() of the files it was loaded from


class ModelRegistry:
    def __init__(self, store: Path, on_load: Callable[[str], None] | None = None) -> None:
        self.store = Path(store)
        remove_stale(self.store)  # what interrupted trainings left behind
        self._models: dict[str, LoadedModel] = {}
        self._failed: dict[str, tuple[tuple, str]] = {}  # name -> (stamp that failed, why)
        self._missing: set[str] = set()  # loaded objects absent on the last poll
        self._skipped: dict[str, str] = {}  # the store's folders that are not objects (logged once each)
        self._lock = threading.Lock()  # one loader at a time
        self._on_load = on_load or (lambda result: None)
        self._stop = threading.Event()
        self._watcher: threading.Thread | None = None
        self.ready = False

    # --- what is there --------------------------------------------------------------------------
    def names(self) -> list[str]:
        return list_models(self.store)

    def loaded(self) -> list[str]:
        return sorted(self._models)

    def failed(self) -> dict[str, str]:
        """Objects of the store that cannot be loaded, with the reason (one line each; no server
        path: :meth:`public`)."""
        return {name: self.public(why) for name, (_, why) in sorted(self._failed.items())}

    def public(self, text: str) -> str:
        """``text`` as clients may read it: the store's place on the server's disk left out
        (``/data/models/cookie-box/model.npz`` is ``cookie-box/model.npz``, the store itself
        ``the store``). The store's errors name their files, which the log keeps for the operator;
        ``/readyz`` (open without a token), ``GET /v1/objects`` and the 503 answers showed them to
        any client."""
        for root in {str(self.store), str(self.store.resolve()), str(self.store.absolute())}:
            if root and root not in ("/", "."):
                text = text.replace(root + "/", "").replace(root, "the store")
        return text

    def is_known(self, name: str) -> bool:
        return name in self._models or model_stamp(self.store, name) is not None

    @staticmethod
    def check_name(name: str) -> str:
        """The name, if it cannot escape the store (400 otherwise). The whole name must match
        (``re.match`` with ``$`` let a trailing newline through: ``cookie-box%0A`` reached the
        file system), and a refused name is echoed at most 80 characters long."""
        if isinstance(name, str) and NAME_RE.fullmatch(name):
            return check_object_name(name)
        try:
            check_object_name("\n")  # (the message of any refused name)
        except StoreError as exc:
            why = str(exc)
        shown = name[:80] + "…" if isinstance(name, str) and len(name) > 80 else name
        raise ApiError(400, "invalid_object_name", why.replace(repr("\n"), repr(shown), 1))

    def manifest(self, name: str) -> dict:
        self.check_name(name)
        if model_stamp(self.store, name) is None:
            raise ApiError(404, "unknown_object", f"no object named {name!r} in the store")
        try:
            return load_manifest(self.store, name)
        except StoreError as exc:
            raise ApiError(503, "model_unavailable", self.public(str(exc))) from None

    # --- loading --------------------------------------------------------------------------------
    def get(self, name: str) -> tuple[ObjectModel, ModelIndex]:
        """The current model and its index; blocking (call it from a worker thread: it may load)."""
        self.check_name(name)
        hit = self._models.get(name)
        stamp = model_stamp(self.store, name)
        if hit is not None and stamp is None and self._watcher is None:
            # no poll will decide (QUATRACK_MODEL_POLL_S=0; `reload` reaches one worker process of
            # several): absent again a moment later — a retraining's two renames are microseconds
            # apart — the object was deleted
            time.sleep(0.05)
            stamp = model_stamp(self.store, name)
            if stamp is None:
                with self._lock:
                    self._models.pop(name, None)
                log.info("object %s left the store: out of service", name)
                raise ApiError(404, "unknown_object", f"no object named {name!r} in the store")
        if hit is not None and (stamp is None or stamp == hit.stamp):  # None: mid-retraining or deleted; the poll decides
            return hit.model, hit.index
        if stamp is None:
            raise ApiError(404, "unknown_object", f"no object named {name!r} in the store")
        entry = self._load(name, stamp)
        return entry.model, entry.index

    def _load(self, name: str, stamp: tuple) -> LoadedModel:
        with self._lock:
            hit = self._models.get(name)
            if hit is not None and hit.stamp == stamp:
                return hit
            failed = self._failed.get(name)
            if failed is None or failed[0] != stamp:
                try:
                    model = load_model(self.store, name)
                    entry = LoadedModel(model, index_for(model), stamp)
                except Exception as exc:  # StoreError, or anything the index builder met: that object's error
                    why = str(exc) if isinstance(exc, StoreError) else f"object {name!r}: {exc.__class__.__name__}: {exc}"
                    why = why.splitlines()[0][:500] if why else f"object {name!r}: cannot be loaded"
                    self._failed[name] = failed = (stamp, why)
                    self._models.pop(name, None)  # (a broken retraining: out of service, as the contract says)
                    self._on_load("failed")
                    log.error("cannot load object %s: %s%s", name, why,
                              "; out of service until it is fixed (running sessions keep their model)"
                              if hit is not None else "")
                else:
                    self._models[name] = entry
                    self._failed.pop(name, None)
                    self._on_load("ok")
                    log.info("%s object %s (%d viewsets)", "reloaded" if hit else "loaded", name, len(model.viewsets))
                    return entry
            why = failed[1]
            advice = "the other objects are served" if why.endswith("retrain it") else "fix or retrain it; the other objects are served"
            raise ApiError(503, "model_unavailable", self.public(f"{why} ({advice})"))

    def refresh(self) -> None:
        """Bring the registry in step with the store: load new and retrained models, drop deleted ones."""
        on_disk = set(self.names())
        self._report_skipped()
        for name in list(self._models):
            if name in on_disk:
                self._missing.discard(name)
            elif name in self._missing:  # absent on two polls in a row: deleted
                with self._lock:
                    self._models.pop(name, None)
                self._missing.discard(name)
                log.info("object %s left the store: out of service", name)
            else:
                self._missing.add(name)
        for name in list(self._failed):
            if name not in on_disk:
                self._failed.pop(name, None)
        for name in sorted(on_disk):
            stamp = model_stamp(self.store, name)
            if stamp is None:
                continue
            try:
                self._load(name, stamp)
            except ApiError:
                pass  # recorded in failed(), logged once

    def _report_skipped(self) -> None:
        """Log each folder of the store that is not an object (no manifest, unreadable: a
        ``lost+found`` of another user's) once, as it appears or its reason changes. Such a
        folder stopped ``serve``, every poll of the watcher (a traceback every 2 s, changes no
        longer picked up) and ``GET /v1/objects`` (500) with a PermissionError."""
        skipped = broken_folders(self.store)
        for name, why in sorted(skipped.items()):
            if self._skipped.get(name) != why:
                log.warning("skipping %s in the model store %s: it %s", name, self.store, why)
        self._skipped = skipped

    def reload(self, name: str) -> dict:
        """Check one object now (the admin call): ``loaded``, ``unchanged``, ``removed`` or ``failed``."""
        self.check_name(name)
        stamp = model_stamp(self.store, name)
        if stamp is None:
            with self._lock:
                gone = self._models.pop(name, None)
                self._failed.pop(name, None)
            self._missing.discard(name)
            if gone is None:
                raise ApiError(404, "unknown_object", f"no object named {name!r} in the store")
            log.info("object %s left the store: out of service", name)
            return {"name": name, "status": "removed"}
        before = self._models.get(name)
        if before is not None and before.stamp == stamp:
            return {"name": name, "status": "unchanged"}
        try:
            self._load(name, stamp)
        except ApiError as exc:
            return {"name": name, "status": "failed", "message": exc.message}
        return {"name": name, "status": "loaded"}

    def load_all(self) -> None:
        """Load every model of the store; a corrupt one is reported (failed()), not fatal."""
        self.refresh()
        self.ready = True

    # --- watching -------------------------------------------------------------------------------
    def start_watching(self, poll_s: float) -> None:
        """Poll the store every ``poll_s`` seconds in a daemon thread (``stop()`` ends it)."""
        if poll_s <= 0 or self._watcher is not None:
            return

        def loop():
            while not self._stop.wait(poll_s):
                try:
                    self.refresh()
                except Exception:  # a store on a flaky volume must not kill the watcher
                    log.exception("watching the model store %s failed; retrying", self.store)

        self._watcher = threading.Thread(target=loop, name="quatrack-store-watch", daemon=True)
        self._watcher.start()

    def stop(self) -> None:
        self._stop.set()
        if self._watcher is not None:
            self._watcher.join(timeout=5)
            self._watcher = None

    def warm(self) -> None:
        """Build this thread's FLANN matcher for every model (cv2 matchers are per thread)."""
        rng = np.random.default_rng(0)
        for entry in list(self._models.values()):
            index = entry.index
            d = rng.random((2, index.descriptors.shape[1] if index.descriptors.ndim == 2 else 128), dtype=np.float32)
            index.match(Features(np.zeros((2, 2), np.float32), d, np.ones(2, np.float32), np.zeros(2, np.float32)))

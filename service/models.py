"""The object models the service answers for: loaded once, then shared read-only.

Models and their FLANN indexes are immutable after loading, so every request and session uses
the same objects without locks. A model trained after start-up is loaded on its first request
(one loader at a time); retraining an object already loaded needs a restart.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from quatrack.recognition.match import ModelIndex, index_for
from quatrack.viewsets.errors import StoreError
from quatrack.viewsets.features import Features
from quatrack.viewsets.names import check_object_name
from quatrack.viewsets.store import ObjectModel, list_models, load_manifest, load_model

from .errors import ApiError

log = logging.getLogger("quatrack.service")


class ModelRegistry:
    def __init__(self, store: Path) -> None:
        self.store = Path(store)
        self._models: dict[str, tuple[ObjectModel, ModelIndex]] = {}
        self._lock = threading.Lock()
        self.ready = False

    def names(self) -> list[str]:
        return list_models(self.store)

    def loaded(self) -> list[str]:
        return sorted(self._models)

    @staticmethod
    def check_name(name: str) -> str:
        """The name, if it cannot escape the store (400 otherwise)."""
        try:
            return check_object_name(name)
        except StoreError as exc:
            raise ApiError(400, "invalid_object_name", str(exc)) from None

    def manifest(self, name: str) -> dict:
        self.check_name(name)
        if name not in self.names():
            raise ApiError(404, "unknown_object", f"no object named {name!r} in the store")
        try:
            return load_manifest(self.store, name)
        except StoreError as exc:
            raise ApiError(404, "unknown_object", str(exc)) from None

    def get(self, name: str) -> tuple[ObjectModel, ModelIndex]:
        """The model and its index; blocking (call it from a worker thread when it may load)."""
        self.check_name(name)
        hit = self._models.get(name)
        if hit is not None:
            return hit
        with self._lock:
            hit = self._models.get(name)
            if hit is not None:
                return hit
            if name not in self.names():
                raise ApiError(404, "unknown_object", f"no object named {name!r} in the store")
            try:
                model = load_model(self.store, name)
            except StoreError as exc:
                raise ApiError(404, "unknown_object", f"object {name!r} cannot be loaded: {exc}") from None
            hit = (model, index_for(model))
            self._models[name] = hit
            log.info("loaded object %s (%d viewsets)", name, len(model.viewsets))
            return hit

    def is_known(self, name: str) -> bool:
        return name in self._models or name in self.names()

    def load_all(self) -> None:
        """Load every model of the store; a corrupt one is logged and skipped, not fatal."""
        for name in self.names():
            try:
                self.get(name)
            except ApiError as exc:
                log.warning("skipping object %s: %s", name, exc.message)
        self.ready = True

    def warm(self) -> None:
        """Build this thread's FLANN matcher for every model (cv2 matchers are per thread)."""
        rng = np.random.default_rng(0)
        for _, index in list(self._models.values()):
            d = rng.random((2, index.descriptors.shape[1] if index.descriptors.ndim == 2 else 128), dtype=np.float32)
            index.match(Features(np.zeros((2, 2), np.float32), d, np.ones(2, np.float32), np.zeros(2, np.float32)))

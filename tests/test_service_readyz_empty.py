"""``/readyz`` is 503 while the server has no object to serve (an empty store, or only broken
models): it said 200 ``{"ready": true, "models": []}``, and Kubernetes routed requests to a
replica that could only answer 404 before the training Job had written a model. The store is
polled: the server becomes ready when a model appears in it."""

from __future__ import annotations

import shutil

import httpx

from conftest import wait_until
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store


def test_an_empty_store_is_not_ready_until_a_model_is_trained_into_it(tmp_path):
    store = tmp_path / "store"
    store.mkdir()
    with BackgroundServer(Settings(store=store, model_poll_s=0.1)) as srv:
        r = httpx.get(f"{srv.url}/readyz", timeout=60)
        assert r.status_code == 503 and r.json()["ready"] is False and r.json()["models"] == [], r.text
        shutil.copytree(example_store() / "cookie-box", store / "cookie-box")  # (the training Job's result)
        assert wait_until(lambda: httpx.get(f"{srv.url}/readyz", timeout=60).status_code == 200)
        assert httpx.get(f"{srv.url}/readyz", timeout=60).json()["models"] == ["cookie-box"]


def test_without_preloading_readyz_waits_for_no_model(tmp_path):
    """``QUATRACK_PRELOAD=0``: models load at their first request, so /readyz waits for none (as before)."""
    with BackgroundServer(Settings(store=tmp_path, preload=False, model_poll_s=0)) as srv:
        r = httpx.get(f"{srv.url}/readyz", timeout=60)
        assert r.status_code == 200 and r.json()["ready"], r.text

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


def test_without_preloading_an_empty_store_is_not_ready(tmp_path):
    """``QUATRACK_PRELOAD=0``: models load at their first request, so /readyz waits for none to
    load, but a store with no object is still not ready (it answered 200 ``models: []``)."""
    store = tmp_path / "store"
    store.mkdir()
    with BackgroundServer(Settings(store=store, preload=False, model_poll_s=0)) as srv:
        r = httpx.get(f"{srv.url}/readyz", timeout=60)
        assert r.status_code == 503 and r.json()["ready"] is False, r.text
        shutil.copytree(example_store() / "cookie-box", store / "cookie-box")
        r = httpx.get(f"{srv.url}/readyz", timeout=60)
        assert r.status_code == 200 and r.json()["ready"] and r.json()["models"] == [], r.text  # (none loaded yet)


def test_without_preloading_a_store_of_broken_models_is_not_ready(tmp_path):
    store = tmp_path / "store"
    shutil.copytree(example_store() / "cookie-box", store / "cookie-box")
    (store / "cookie-box" / "model.npz").write_bytes(b"truncated")
    with BackgroundServer(Settings(store=store, preload=False, model_poll_s=0)) as srv:
        assert httpx.get(f"{srv.url}/readyz", timeout=60).status_code == 200  # (not known broken yet)
        httpx.post(f"{srv.url}/v1/objects/cookie-box/reload", timeout=60)  # (the first request finds it broken)
        r = httpx.get(f"{srv.url}/readyz", timeout=60)
        assert r.status_code == 503 and "cookie-box" in r.json()["failed"], r.text

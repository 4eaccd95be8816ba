"""A failure while the service loads its models and warms up (``app._warm``: a broken OpenCV, a
numba that cannot compile) is logged at once with its traceback and said by ``/readyz``
(``error``, 503). The future's exception was never read: ``/readyz`` answered 503
``{"ready": false, "failed": {}}`` for good and the log said nothing until the shutdown printed
"Future exception was never retrieved" (a trial install with OpenCV 4.13)."""

from __future__ import annotations

import logging
import shutil

from fastapi.testclient import TestClient

from conftest import wait_until
from quatrack.service import app as app_module
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store


def test_a_failed_warm_up_is_logged_and_readyz_says_why(tmp_path, monkeypatch, caplog):
    shutil.copytree(example_store() / "cookie-box", tmp_path / "cookie-box")

    def broken(state, freeze=False):
        raise AttributeError("module 'cv2.utils' has no attribute 'logging'")

    monkeypatch.setattr(app_module, "_warm", broken)
    caplog.set_level(logging.ERROR, logger="quatrack.service")
    with TestClient(app_module.create_app(Settings(store=tmp_path, workers=1, threads=1, model_poll_s=0))) as c:
        assert wait_until(lambda: c.get("/readyz").json().get("error") is not None)
        r = c.get("/readyz")
        assert r.status_code == 503 and r.json()["ready"] is False
        assert r.json()["error"] == "AttributeError: module 'cv2.utils' has no attribute 'logging'"
    failed = [rec for rec in caplog.records if "warming the service failed" in rec.getMessage()]
    assert len(failed) == 1 and failed[0].exc_info is not None


def test_a_warm_up_that_succeeds_says_no_error(tmp_path):
    shutil.copytree(example_store() / "cookie-box", tmp_path / "cookie-box")
    with TestClient(app_module.create_app(Settings(store=tmp_path, workers=1, threads=1, model_poll_s=0))) as c:
        assert wait_until(lambda: c.get("/readyz").status_code == 200)
        assert c.get("/readyz").json()["error"] is None

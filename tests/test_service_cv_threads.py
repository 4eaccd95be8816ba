"""OpenCV's threads per worker are counted from the CPUs the process may use (``settings.usable_cores``:
the affinity mask capped by a container's CPU quota), the count the default workers and threads
come from: ``os.cpu_count()`` counts the host's, and a 2-CPU container on a 64-core host gave
each of its 2 workers 32 OpenCV threads."""

from __future__ import annotations

from quatrack.service import app as app_module
from quatrack.service.settings import Settings


def test_opencv_threads_follow_the_cpu_quota_not_the_host(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(app_module.os, "cpu_count", lambda: 64)  # the host
    monkeypatch.setattr(app_module, "usable_cores", lambda: 2)  # the container's quota
    monkeypatch.setattr(app_module.cv2, "setNumThreads", calls.append)
    app_module.create_app(Settings(store=tmp_path, workers=2, threads=1))
    assert calls == [1]

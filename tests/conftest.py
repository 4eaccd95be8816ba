"""Test-wide configuration: hypothesis profiles.

Why profiles: a property test that draws fresh random examples on every run, and then replays a
failure from ``.hypothesis/``, passes or fails depending on the machine's history. CI must give
the same verdict on every fresh clone, while a developer should keep exploring new examples.

- ``ci`` (selected when the ``CI`` environment variable is set): derandomized — the examples are
  a function of the test alone — no example database, no deadline (a deadline is a timing
  assertion: it fails on a busy machine, not on a bug).
- ``dev`` (the default otherwise): random examples, the local database replays past failures,
  no deadline either.
- ``explore``: ``dev`` with many more examples, to hunt for flaws before they reach CI:
  ``HYPOTHESIS_PROFILE=explore .venv/bin/pytest -q tests/test_adjust.py``.

``HYPOTHESIS_PROFILE`` overrides the choice. Tests state a ``max_examples`` only where an
example is expensive (a network round trip); elsewhere the profile decides.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", deadline=None, print_blob=True)
settings.register_profile("explore", deadline=None, print_blob=True, max_examples=2000,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE") or ("ci" if os.environ.get("CI") else "dev"))


# --- helpers shared by the tests of real servers (test_workers, test_deploy, test_service_ws, test_service_models)
# plain functions, imported with ``from conftest import ...`` (pytest puts tests/ on the path)

def metric_samples(text: str) -> dict:
    """{(name, frozenset(labels)): value} of a Prometheus text exposition, read by
    prometheus-client's own parser."""
    from prometheus_client.parser import text_string_to_metric_families

    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, frozenset(s.labels.items()))] = s.value
    return out


def sessions_active(url: str) -> float:
    """``quatrack_ws_sessions_active`` of the server at ``url`` (all its workers)."""
    import httpx

    found = metric_samples(httpx.get(f"{url}/metrics", timeout=60).text).get(("quatrack_ws_sessions_active", frozenset()))
    assert found is not None, f"no quatrack_ws_sessions_active in {url}/metrics"
    return found


def box_frames_jpeg(n: int) -> list[bytes]:
    """The first ``n`` frames of the bundled ``box.mp4`` as JPEG bytes."""
    from pathlib import Path

    import cv2

    cap = cv2.VideoCapture(str(Path(__file__).resolve().parent.parent / "examples" / "cookie-box" / "box.mp4"))
    out = []
    while len(out) < n:
        ok, img = cap.read()
        if not ok:
            break
        out.append(cv2.imencode(".jpg", img)[1].tobytes())
    cap.release()
    return out


def wait_until(pred, timeout: float = 60.0) -> bool:
    """Poll ``pred()`` every 50 ms until it is true (True) or ``timeout`` s pass (False): a bound
    on how long a busy machine may take, not a speed requirement."""
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.05)
    return False


# --- the zoo cube and one scene of it, shared by test_recognition_edge_fit and test_pose_ties
def zoo_cube_scene(root, camera):
    """The zoo's cube (mesh in metres) trained from one colour photo into ``root``, a scene of it
    5° from that photo's view (``random_scene`` seed 11) and its SIFT matches to the model:
    ``(model, spec, scene, matches, matched keypoints)``. OpenCV's RNG seeded: the same each run."""
    import cv2
    import numpy as np

    from quatrack.recognition.match import ModelIndex
    from quatrack.testing import zoo as Z
    from quatrack.viewsets.spec import load_spec
    from quatrack.viewsets.train import train_object

    cv2.setRNGSeed(0)
    bgs = Z.real_backgrounds()
    spec = load_spec(Z.write_spec("cube-m", root, 1, grey=False, backgrounds=bgs))
    model = train_object(spec)
    sc = Z.random_scene(np.random.default_rng(11), Z.textured("cube-m"), camera, spec.views[0].pose, bgs, 5.0, 0.0, False)
    cv2.setRNGSeed(0)
    index = ModelIndex(model)
    feats = index.describe(sc.image)
    m = index.match(feats)
    return model, spec, sc, m, feats.keypoints[m.query_idx]


# --- the one-photo cube walk shared by test_learn, test_keyframes and test_tracker_sources
def one_photo_orbit(root, span_deg: float, n_frames: int, name: str = "small-cube-cm"):
    """A zoo object (the 6 cm cube by default) trained from ONE rendered photo (azimuth 35°,
    elevation 25°, over ``clutter_background(4)``, no synthetic views) into ``root``, and a
    camera orbiting it from the photo's azimuth by ``span_deg`` over ``n_frames`` frames at
    640×480, elevation ``25° + 10° sin(π k / n)``, rendered over ``clutter_background(5)``:
    ``SimpleNamespace(root, cam, model, obj, poses, frames, bg)``."""
    from types import SimpleNamespace

    import numpy as np

    from quatrack.testing import zoo as Z
    from quatrack.testing.sequences import clutter_background
    from quatrack.viewsets.spec import load_spec
    from quatrack.viewsets.train import TrainParams, train_object

    cam = Z.zoo_camera(640, 480)
    spec = Z.write_spec(name, root / "spec", n_views=1, backgrounds=(clutter_background(4),))
    model = train_object(load_spec(spec), TrainParams(novel=None))
    obj = Z.textured(name)
    bg = clutter_background(5)
    poses = [Z.orbit_pose(obj, cam, 35.0 + span_deg * k / (n_frames - 1), 25.0 + 10.0 * np.sin(np.pi * k / n_frames))
             for k in range(n_frames)]
    frames = [Z.compose(*obj.render(cam, p), bg) for p in poses]
    return SimpleNamespace(root=root, cam=cam, model=model, obj=obj, poses=poses, frames=frames, bg=bg)


def closed_prism(sides: int = 6, radius: float = 4.0, height: float = 9.0):
    """A closed prism of ``sides`` facets standing on z = 0 (a cylinder when ``sides`` is large):
    the side's quads as two triangles each, and each cap a fan from its centre."""
    import numpy as np

    from quatrack.viewsets.mesh import make_mesh

    a = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], 1)
    V = np.concatenate([np.column_stack([ring, np.zeros(sides)]), np.column_stack([ring, np.full(sides, height)]),
                        [[0.0, 0.0, 0.0], [0.0, 0.0, height]]])
    F = []
    for i in range(sides):
        j = (i + 1) % sides
        F += [[i, j, sides + j], [i, sides + j, sides + i], [2 * sides, j, i], [2 * sides + 1, sides + i, sides + j]]
    return make_mesh(V, np.array(F))



# --- the bundled example trained into a store, for the tests of the model store (test_viewsets_store,
# test_store_changes)

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cookie-box"
FAST_TRAIN = ["--novel-views", "none", "--novel-scales", "none"]  # no synthetic views: about 2 s


@pytest.fixture(scope="module")
def base_store(tmp_path_factory):
    """A store holding the cookie box trained without synthetic views (:data:`FAST_TRAIN`), once per
    test module: read it, never change it (``store`` is a test's own copy)."""
    from quatrack.cli import main

    store = tmp_path_factory.mktemp("base")
    assert main(["train", str(EXAMPLE / "object.json"), "--store", str(store), *FAST_TRAIN]) == 0
    return store


@pytest.fixture
def store(base_store, tmp_path):
    """A copy of :func:`base_store` the test may change (modules with a ``store`` of their own keep it)."""
    s = tmp_path / "store"
    shutil.copytree(base_store, s)
    return s


@pytest.fixture
def not_started(monkeypatch):
    """``quatrack serve`` run up to uvicorn, which is not started: (monkeypatch, the keyword
    arguments uvicorn.run was called with); no ``QUATRACK_*`` variable of the caller's reaches
    it, and the environment serve exports for its workers is put back afterwards."""
    import os

    import uvicorn

    for key in list(os.environ):
        if key.upper().startswith("QUATRACK_"):
            monkeypatch.delenv(key)
    started = []
    monkeypatch.setattr(uvicorn, "run", lambda *a, **k: started.append(k))
    before = dict(os.environ)
    yield monkeypatch, started
    os.environ.clear()  # (serve exports its settings for its workers)
    os.environ.update(before)

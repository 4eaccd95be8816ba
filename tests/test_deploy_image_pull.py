"""deploy/kubernetes.yaml can run the image it names: ``image: quatrack:latest`` without an
``imagePullPolicy`` is pulled Always (the default for :latest), from docker.io/library/quatrack,
and every pod failed with ErrImagePull unless that name had been pushed; the header never said
to build, tag or push it."""

from __future__ import annotations

from pathlib import Path

import pytest

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"


def _containers(doc: dict) -> list:
    spec = doc["spec"]["template"]["spec"]
    return spec.get("containers", []) + spec.get("initContainers", [])


def test_every_container_uses_the_nodes_image_and_the_header_says_how_to_get_it_there():
    yaml = pytest.importorskip("yaml")
    text = (DEPLOY / "kubernetes.yaml").read_text()
    docs = [d for d in yaml.safe_load_all(text) if d and d["kind"] in ("Job", "Deployment")]
    containers = [c for d in docs for c in _containers(d)]
    assert len(containers) == 2
    for c in containers:
        assert c.get("imagePullPolicy") == "IfNotPresent", c["name"]
    header = text.split("apiVersion:")[0]
    assert "docker build -t" in header and "docker push" in header and "kind load docker-image" in header

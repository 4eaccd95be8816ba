"""The deploy files agree with the README's sizing rule and with each other: a replica's
``QUATRACK_WORKERS`` is its CPU limit (a container sees every core of the host: Compose ran two
unlimited replicas each starting one worker per host core), ``QUATRACK_MAX_SESSIONS`` about one
30 fps camera per CPU (they said 8 for 2 CPUs), and the Kubernetes scrape annotations come with
how Prometheus sends the token ``/metrics`` needs once ``QUATRACK_API_TOKEN`` is set."""

from __future__ import annotations

from pathlib import Path

import pytest

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
README = (DEPLOY.parent / "README.md").read_text()


def _env(items) -> dict:
    return dict(items) if isinstance(items, dict) else {e["name"]: e["value"] for e in items if "value" in e}


def test_each_replica_has_a_cpu_limit_its_workers_and_one_session_per_cpu():
    yaml = pytest.importorskip("yaml")
    q = yaml.safe_load((DEPLOY / "compose.yaml").read_text())["services"]["quatrack"]
    cpus = float(q["deploy"]["resources"]["limits"]["cpus"])
    env = _env(q["environment"])
    assert int(env["QUATRACK_WORKERS"]) == cpus and int(env["QUATRACK_MAX_SESSIONS"]) <= cpus, (cpus, env)
    docs = {d["kind"]: d for d in yaml.safe_load_all((DEPLOY / "kubernetes.yaml").read_text())}
    (c,) = docs["Deployment"]["spec"]["template"]["spec"]["containers"]
    cpus = float(c["resources"]["limits"]["cpu"])
    env = _env(c["env"])
    assert int(env["QUATRACK_WORKERS"]) == cpus and int(env["QUATRACK_MAX_SESSIONS"]) <= cpus, (cpus, env)
    assert "one 30 fps camera per core" in README


def test_the_scrape_annotations_say_how_prometheus_sends_the_token():
    text = (DEPLOY / "kubernetes.yaml").read_text()
    assert "prometheus.io/scrape" in text and "credentials_file" in text and "QUATRACK_API_TOKEN" in text
    assert "credentials_file" in README

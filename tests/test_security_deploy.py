"""The deploy files require a token: Compose published nginx's 8080 on every interface of the host
and Kubernetes exposed the pods, both with the token commented out — every endpoint open to the
network by default."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
README = (DEPLOY.parent / "README.md").read_text()


def test_compose_refuses_to_start_without_a_token():
    yaml = pytest.importorskip("yaml")
    env = yaml.safe_load((DEPLOY / "compose.yaml").read_text())["services"]["quatrack"]["environment"]
    # ${VAR:?message}: Compose stops with the message when the variable is unset or empty
    assert re.fullmatch(r"\$\{QUATRACK_API_TOKEN:\?[^}]+\}", env.get("QUATRACK_API_TOKEN", "")), env


def test_kubernetes_takes_the_token_from_a_secret():
    yaml = pytest.importorskip("yaml")
    docs = {d["kind"]: d for d in yaml.safe_load_all((DEPLOY / "kubernetes.yaml").read_text())}
    (c,) = docs["Deployment"]["spec"]["template"]["spec"]["containers"]
    env = {e["name"]: e for e in c["env"]}
    ref = env["QUATRACK_API_TOKEN"]["valueFrom"]["secretKeyRef"]
    assert ref == {"name": "quatrack-token", "key": "token"} and not ref.get("optional")
    assert "kubectl create secret generic quatrack-token" in (DEPLOY / "kubernetes.yaml").read_text()


def test_the_readme_says_the_deploy_files_need_a_token():
    assert "QUATRACK_API_TOKEN=$(openssl rand -hex 32) docker compose" in README
    assert "kubectl create secret generic quatrack-token" in README

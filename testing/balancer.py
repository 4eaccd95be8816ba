"""Debian's nginx, run unprivileged-style from a private prefix with ``deploy/nginx.conf``, in front
of ``quatrack serve`` replicas on loopback: for ``quatrack bench serve`` and tests/test_deploy.py.

The deployment's own config is used, with only the upstream servers and the listen address
substituted, so that what is measured and tested is what is shipped.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

from .loopback import Loopback, free_port, wait_for_http

ROOT = Path(__file__).resolve().parent.parent
# deploy/ of a checkout; of an installed wheel, the package data quatrack/deploy/ (pyproject.toml:
# it was not shipped, and `bench serve --replicas auto` with nginx installed failed on the read).
NGINX_CONF = ROOT / "deploy" / "nginx.conf"


def find_nginx() -> str | None:
    """The nginx binary (Debian puts it in /usr/sbin, often not on a user's PATH), or None."""
    found = shutil.which("nginx")
    if found:
        return found
    return next((p for p in ("/usr/sbin/nginx", "/usr/local/sbin/nginx") if os.access(p, os.X_OK)), None)


def nginx_config(ports: list[int], listen: int, template: Path = NGINX_CONF) -> str:
    """deploy/nginx.conf with loopback replicas at ``ports`` and ``listen`` as its port; ``user
    root`` when run as root (CI), so that the workers may write the private prefix's temp dirs."""
    text = template.read_text()
    servers = "\n".join(f"        server 127.0.0.1:{p} max_fails=1 fail_timeout=5s;" for p in ports)
    text, n = re.subn(r"^\s*server quatrack:8000[^\n]*;", servers, text, flags=re.M)
    if n != 1:
        raise ValueError(f"{template}: expected one 'server quatrack:8000 ...;' line in the upstream")
    text, n = re.subn(r"listen 8080;", f"listen 127.0.0.1:{listen};", text)
    if n != 1:
        raise ValueError(f"{template}: expected one 'listen 8080;'")
    if os.geteuid() == 0:
        text = "user root;\n" + text
    return text


class Nginx(Loopback):
    """``with Nginx(prefix, [port_a, port_b]) as lb: lb.url`` — nginx in the foreground, stopped after."""

    def __init__(self, prefix: Path, ports: list[int], port: int | None = None) -> None:
        binary = find_nginx()
        if binary is None:
            raise RuntimeError("nginx is not installed (Debian: apt-get install nginx)")
        if not NGINX_CONF.is_file():  # (an install without its package data: an OSError, one line for the CLI)
            raise FileNotFoundError(f"the deployment's nginx config is not installed here ({NGINX_CONF})")
        self.prefix, self.port = Path(prefix), port or free_port()
        (self.prefix / "logs").mkdir(parents=True, exist_ok=True)
        (self.prefix / "nginx.conf").write_text(nginx_config(ports, self.port))
        self.error_log = self.prefix / "logs" / "error.log"
        self.cmd = [binary, "-p", str(self.prefix), "-c", "nginx.conf",
                    "-g", f"daemon off; pid {self.prefix}/nginx.pid; error_log {self.error_log};"]
        self.proc = None

    def __enter__(self) -> "Nginx":
        check = subprocess.run(self.cmd + ["-t"], capture_output=True, text=True)
        if check.returncode != 0:
            raise RuntimeError(f"nginx -t: {check.stderr.strip()}")
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:  # any answer: nginx listens (what the replicas answer is theirs)
            wait_for_http(f"{self.url}/healthz", f"nginx (see {self.error_log})", 60,
                          alive=lambda: self.proc.poll() is None, accept=lambda status: True)
        except RuntimeError:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=20)

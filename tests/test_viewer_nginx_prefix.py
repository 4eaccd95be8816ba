"""The README's nginx block for the viewer under a path prefix (``location /quatrack/``), run as
written in Debian's nginx in front of a server *without* a token, and a handshake made as the
viewer's page makes it (``Origin`` the page's, through nginx).

The block lacked ``proxy_set_header Host $host;``: nginx then sent ``Host: 127.0.0.1:PORT`` (the
upstream's), which is not the page's origin, and the viewer's own WebSocket was refused
``forbidden_origin``. The block without that line is run too, to show the line is what matters.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.balancer import find_nginx
from quatrack.testing.loopback import free_port, wait_for_http

README = Path(__file__).resolve().parent.parent / "README.md"
NGINX = find_nginx()
HOST_LINE = "proxy_set_header Host $host;"


def readme_prefix_block() -> str:
    """The ```nginx block of the README's "In the browser" section."""
    text = README.read_text()
    section = text[text.index("#### In the browser"):]
    section = section[:section.index("\n#### ", 1)]
    found = re.search(r"```nginx\n(.*?)```", section, re.S)
    assert found, "the README's 'In the browser' section has no ```nginx block"
    return found.group(1)


def test_the_readme_block_passes_the_host_on():
    assert HOST_LINE in readme_prefix_block()


def _nginx_conf(block: str, upstream: int, listen: int, prefix: Path) -> str:
    """The block in a minimal nginx config: its ``map`` line in ``http``, the rest in ``server``."""
    lines = block.splitlines()
    maps = [ln for ln in lines if ln.lstrip().startswith("map ")]
    rest = "\n".join(ln for ln in lines if ln not in maps).replace("127.0.0.1:8000", f"127.0.0.1:{upstream}")
    user = "user root;\n" if os.geteuid() == 0 else ""
    return (f"{user}worker_processes 1;\nevents {{ worker_connections 64; }}\nhttp {{\n"
            f"  access_log off;\n  client_body_temp_path {prefix}/body; proxy_temp_path {prefix}/proxy;\n"
            f"  fastcgi_temp_path {prefix}/fcgi; uwsgi_temp_path {prefix}/uwsgi; scgi_temp_path {prefix}/scgi;\n"
            + "\n".join(maps) + f"\n  server {{\n    listen 127.0.0.1:{listen};\n{rest}\n  }}\n}}\n")


class _Nginx:
    def __init__(self, prefix: Path, conf: str, port: int) -> None:
        (prefix / "logs").mkdir(parents=True, exist_ok=True)
        (prefix / "nginx.conf").write_text(conf)
        self.cmd = [NGINX, "-p", str(prefix), "-c", "nginx.conf",
                    "-g", f"daemon off; pid {prefix}/nginx.pid; error_log {prefix}/logs/error.log;"]
        self.port = port

    def __enter__(self):
        check = subprocess.run(self.cmd + ["-t"], capture_output=True, text=True)
        assert check.returncode == 0, check.stderr
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_for_http(f"http://127.0.0.1:{self.port}/quatrack/healthz", "nginx", 60,
                      alive=lambda: self.proc.poll() is None)
        return self

    def __exit__(self, *exc):
        self.proc.terminate()
        self.proc.wait(timeout=20)


def refusal_code(url: str, origin: str) -> str:
    """The error code the server answers a handshake with, as an HTTP refusal's body or as the
    socket's first message (what a browser's handshake gets: docs/contract.md)."""
    try:
        with connect(url, origin=origin, open_timeout=30) as ws:
            return json.loads(ws.recv(timeout=30))["error"]["code"]
    except InvalidStatus as exc:
        return json.loads(exc.response.body)["error"]["code"]


@pytest.mark.skipif(NGINX is None, reason="nginx is not installed (Debian: apt-get install nginx)")
@pytest.mark.parametrize("with_host", [True, False])
def test_the_viewers_socket_passes_the_origin_check_through_the_readme_block(tmp_path, with_host):
    block = readme_prefix_block()
    if not with_host:
        block = block.replace(HOST_LINE, "")
    port = free_port()
    with BackgroundServer(Settings(store=tmp_path / "store", preload=False, workers=1, threads=1, model_poll_s=0)) as srv, \
            _Nginx(tmp_path / "nginx", _nginx_conf(block, srv.port, port, tmp_path / "nginx"), port):
        page = f"http://127.0.0.1:{port}"  # the viewer's page, /quatrack/viewer/, is of this origin
        code = refusal_code(f"ws://127.0.0.1:{port}/quatrack/v1/objects/nothing/track", page)
    # past the origin check, the next one refuses it (the store is empty): the origin was accepted
    assert code == ("unknown_object" if with_host else "forbidden_origin")

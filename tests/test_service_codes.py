"""One list of the WebSocket's refused-frame codes (``service/codes.py``), read by the server's
session and the Python client alike; the client imports it without the server's stack."""

from __future__ import annotations

import ast
import inspect
import subprocess
import sys
import textwrap

from quatrack.service import codes, sessions


def _codes_sent(fn) -> set[str]:
    """The code of every ``self.send_error(CODE, ...)`` in ``fn``, as a string (a literal, or a
    name of :mod:`service.codes`)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(fn)))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "send_error":
            arg = node.args[0]
            if isinstance(arg, ast.Constant):
                out.add(arg.value)
            else:
                assert isinstance(arg, ast.Name), ast.dump(arg)
                out.add(getattr(codes, arg.id))
    return out


def test_the_codes_of_frames_refused_on_arrival_are_one_list():
    """Every error ``_on_frame`` answers (a frame refused before it is numbered) is in
    ``codes.REFUSED_FRAME``, and nothing else is: a code added on one side only fails here.
    (The client had its own copy of the set: a new refusal missing there left its lock-step
    stream waiting for a frame number that never came.)"""
    assert _codes_sent(sessions.TrackSession._on_frame) == codes.REFUSED_FRAME


def test_the_client_drops_the_index_of_every_refused_frame():
    from quatrack.client import StreamResult, _Session

    for code in sorted(codes.REFUSED_FRAME) + ["bad_image"]:
        s = _Session(None, StreamResult())
        s.indices, s.numbers, s.sent_at = [7], [0], [0.0]  # (the caller's frame 7 sent, id 0, no id echoed)
        s.take({"type": "error", **codes.error_body(code, "refused")})
        assert s.numbers == ([] if code in codes.REFUSED_FRAME else [0]), code
        assert s.res.error_index == ([7] if code in codes.REFUSED_FRAME else [None]), code


def test_the_client_imports_no_server_stack(tmp_path):
    """``import quatrack.client`` loads neither FastAPI, Starlette nor uvicorn (it loaded FastAPI
    through the schemas' error class): a client machine needs pydantic, httpx and websockets."""
    probe = ("import sys, quatrack.client, quatrack.service.codes; "
             "print(sorted({m.split('.')[0] for m in sys.modules} & {'fastapi', 'starlette', 'uvicorn'}))")
    out = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": ":".join(p for p in sys.path if p), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"

"""A process that ignores SIGINT (a script's background job, ``quatrack train … &``, inherits it
ignored) must keep ignoring it while trimesh is imported: ``_trimesh`` held Ctrl-C with a handler
of its own and raised KeyboardInterrupt after the import, ending training with exit 130 (user
report F7)."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def _run(tmp_path, ignore: bool) -> subprocess.CompletedProcess:
    fake = tmp_path / "fake"
    fake.mkdir(exist_ok=True)
    # a trimesh whose import receives SIGINT, as a Ctrl-C arriving while the real one loads
    (fake / "trimesh.py").write_text("import os, signal\nos.kill(os.getpid(), signal.SIGINT)\n")
    code = textwrap.dedent(f"""
        import signal, sys
        sys.path.insert(0, {str(fake)!r})
        if {ignore!r}:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        from quatrack.viewsets.mesh import _trimesh
        try:
            _trimesh()
        except KeyboardInterrupt:
            print("interrupted")
            sys.exit(130)
        print("imported", signal.getsignal(signal.SIGINT) is signal.SIG_IGN)
    """)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_an_ignored_sigint_stays_ignored_during_the_import(tmp_path):
    r = _run(tmp_path, ignore=True)
    assert r.returncode == 0 and r.stdout.strip() == "imported True", r.stdout + r.stderr


def test_a_ctrl_c_during_the_import_still_interrupts(tmp_path):
    r = _run(tmp_path, ignore=False)
    assert r.returncode == 130 and r.stdout.strip() == "interrupted", r.stdout + r.stderr

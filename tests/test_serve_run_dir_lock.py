"""Two servers given one ``QUATRACK_RUN_DIR``: the second is refused with one line (exit 2, as
the other start-up errors) before it wipes anything; the first one's ``ready/`` and
``prometheus/`` files had been deleted in silence. A dead server's lock does not count."""

from __future__ import annotations

import os
import subprocess
import sys

from quatrack.service.settings import Settings
from quatrack.service.workers import MULTIPROC_ENV, RUN_LOCK, prepare_run_dir


def _serve(run_dir, store) -> subprocess.CompletedProcess:
    """``quatrack serve`` as a process (this interpreter's flags: the package under test), in a
    session of its own, killed whole if it does start (the refusal under test failed)."""
    import signal

    env = {k: v for k, v in os.environ.items() if not k.startswith("QUATRACK_") and k != MULTIPROC_ENV}
    env.update(QUATRACK_RUN_DIR=str(run_dir), QUATRACK_HOST="127.0.0.1")
    args = [sys.executable, *(["-P"] if sys.flags.safe_path else []), "-m", "quatrack", "serve", "--store", str(store),
            "--workers", "1", "--port", "8787"]
    proc = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
    return subprocess.CompletedProcess(args, proc.returncode, out, err)


def test_a_run_dir_held_by_a_live_server_is_refused_and_left_alone(tmp_path, monkeypatch):
    # (prepare_run_dir sets $PROMETHEUS_MULTIPROC_DIR: set here first, so that monkeypatch puts
    # back what was there after the test — left set, every later test's /metrics read a deleted dir)
    monkeypatch.setenv(MULTIPROC_ENV, str(tmp_path))
    monkeypatch.delenv(MULTIPROC_ENV)
    run, store = tmp_path / "run", tmp_path / "store"
    store.mkdir()
    fd = prepare_run_dir(Settings(store=store, run_dir=run))[3]  # the first server: holds the lock
    try:
        marker = run / "ready" / "12345"
        marker.write_text("")
        done = _serve(run, store)
        assert done.returncode == 2, (done.returncode, done.stderr)
        lines = [line for line in done.stderr.splitlines() if "warning" not in line]
        assert lines == [f"quatrack serve: error: QUATRACK_RUN_DIR {run}: another quatrack serve (pid {os.getpid()}) "
                         f"is running with this run directory; give each server its own (or leave it unset)"], done.stderr
        assert marker.exists()  # nothing of the first server's was wiped
    finally:
        os.close(fd)  # the first server died: its lock went with it
    monkeypatch.delenv(MULTIPROC_ENV, raising=False)
    os.close(prepare_run_dir(Settings(store=store, run_dir=run))[3])  # a restart in the same directory is fine
    assert (run / RUN_LOCK).read_text().strip() == str(os.getpid())

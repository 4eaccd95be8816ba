"""``python -m quatrack`` is the ``quatrack`` command (``quatrack/__main__.py``): the same help,
version, one-line errors and exit statuses as :func:`quatrack.cli.main`, which the console
script runs. (Where only a Python is at hand — no ``bin/`` on PATH, a zipapp, ``python3 -m``
in a container — this is how the command is started.)"""

from __future__ import annotations

import subprocess
import sys

import pytest

from quatrack.cli import main


def _module(args: list[str], cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "quatrack", *args], capture_output=True, text=True, timeout=120,
                          cwd=cwd)


def _in_process(args: list[str], capsys) -> tuple[int, str, str]:
    try:
        status = main(args)
    except SystemExit as exc:  # (argparse's --help, --version and usage errors)
        status = exc.code
    out = capsys.readouterr()
    return status, out.out, out.err


@pytest.mark.parametrize("args", [["--help"], ["--version"], ["locate", "--help"], ["nosuch"], [],
                                  ["locate", "--object", "x"]])
def test_the_same_output_and_exit_status_as_the_command(tmp_path, capsys, args):
    r = _module(args, tmp_path)
    assert (r.returncode, r.stdout, r.stderr) == _in_process(args, capsys), args
    assert "Traceback" not in r.stderr


def test_a_users_error_is_one_line_with_status_2(tmp_path):
    r = _module(["models", "show", "nothing-here", "--store", str(tmp_path / "store")], tmp_path)
    assert r.returncode == 2 and r.stdout == "", r
    assert r.stderr.startswith("quatrack models: error: no object named 'nothing-here' in ") \
        and r.stderr.count("\n") == 1, r.stderr

"""`quatrack serve` as an operator configures it: every bad value a one-line error naming the
variable (no server is started)."""

from __future__ import annotations

import pytest

from quatrack.cli import main


@pytest.fixture
def clean_env(monkeypatch):
    import os

    for key in list(os.environ):
        if key.upper().startswith("QUATRACK_"):
            monkeypatch.delenv(key)
    return monkeypatch


def _serve(capsys, tmp_path, *extra) -> tuple[int, list[str]]:
    code = main(["serve", "--store", str(tmp_path), *extra])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return code, err.strip().splitlines()


@pytest.mark.parametrize("env, names", [
    ({"QUATRACK_MAX_FPS": "abc"}, "QUATRACK_MAX_FPS='abc'"),
    ({"QUATRACK_MAX_BODY_BYTES": "-1"}, "QUATRACK_MAX_BODY_BYTES='-1'"),
    ({"QUATRACK_PORT": "70000"}, "QUATRACK_PORT='70000'"),
    ({"QUATRACK_HOST": "  "}, "QUATRACK_HOST='  '"),  # was "settings: Value error, host must not be empty"
    ({"QUATRACK_RUN_DIR": "FILE"}, "QUATRACK_RUN_DIR="),  # was "[Errno 17] File exists: ..."
])
def test_a_bad_value_is_one_line_naming_the_variable(clean_env, capsys, tmp_path, env, names):
    (tmp_path / "file").write_text("")
    for key, value in env.items():
        clean_env.setenv(key, str(tmp_path / "file") if value == "FILE" else value)
    code, lines = _serve(capsys, tmp_path)
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"quatrack serve: error: environment variable {names}"), lines


def test_a_blank_host_option_is_named(clean_env, capsys, tmp_path):
    code, lines = _serve(capsys, tmp_path, "--host", " ")
    assert code == 2 and lines == ["quatrack serve: error: host=' ': Value error, the address must not be blank"], lines

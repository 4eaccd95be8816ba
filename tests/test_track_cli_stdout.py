"""``quatrack track --out -`` and ``--out /dev/stdout``: the rows alone on stdout, the summary on
stderr (it came after the last row, read as rows by the consumer)."""

from __future__ import annotations

import os

import pytest

from quatrack.cli import main
from quatrack.recognition.trackio import CSV_HEADER
from quatrack.testing.scenes import EXAMPLE, example_store

ARGS = ["track", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"), "--video",
        str(EXAMPLE / "box.mp4"), "--store", str(example_store()), "--max-frames", "3"]


def _rows_only(out: str) -> None:
    lines = out.splitlines()
    assert lines[0] == CSV_HEADER and len(lines) == 4, out
    assert all(line.split(",")[0] == str(k) for k, line in enumerate(lines[1:]))


def test_out_dash_writes_the_rows_to_stdout_and_the_summary_to_stderr(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(ARGS + ["--out", "-"]) == 0
    said = capsys.readouterr()
    _rows_only(said.out)
    assert "tracked 3 frames -> stdout" in said.err and not os.path.exists(tmp_path / "-")


@pytest.mark.skipif(not os.path.exists("/dev/stdout"), reason="no /dev/stdout here")
def test_out_dev_stdout_keeps_the_summary_off_stdout(capfd):
    assert main(ARGS + ["--out", "/dev/stdout"]) == 0
    said = capfd.readouterr()
    _rows_only(said.out)
    assert "tracked 3 frames -> /dev/stdout" in said.err


def test_a_file_output_keeps_the_summary_on_stdout(capsys, tmp_path):
    assert main(ARGS + ["--out", str(tmp_path / "p.csv")]) == 0
    assert "tracked 3 frames ->" in capsys.readouterr().out

"""``locate`` with a glob that matches no file (user report 3, finding 9): it said "cannot read
image empty/*.png: No such file or directory", as if a file had that name, where ``track
--images`` says "no file matches". It is still that argument's own line and exit status 1 (the
contract's per-image errors); a folder asks for a glob of its images, as ``track`` does."""

from __future__ import annotations

import json

import pytest

from quatrack.cli import main
from quatrack.testing.scenes import EXAMPLE, example_store


@pytest.mark.parametrize("obj", ["cookie-box", "all"])
def test_a_glob_matching_nothing_says_so_on_its_line(tmp_path, capsys, obj):
    (tmp_path / "empty").mkdir()
    pattern, folder = str(tmp_path / "empty" / "*.png"), str(tmp_path / "empty")
    base = ["locate", "--object", obj, "--camera", str(EXAMPLE / "camera.json"), "--store", str(example_store())]
    assert main([*base, pattern, folder]) == 1
    out, err = capsys.readouterr()
    assert out == "" and err.splitlines() == [
        f"{pattern}: error: no file matches",
        f"{folder}: error: is a folder; give a glob of its images, e.g. {pattern!r}"], err
    assert main([*base, "--json", pattern]) == 1
    line = json.loads(capsys.readouterr().out)
    assert line == {"image": pattern, "found": False, "error": f"{pattern}: no file matches"}

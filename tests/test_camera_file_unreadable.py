"""A camera file that cannot be read is said in plain words (user report): a missing one said
"cannot read camera file (FileNotFoundError: [Errno 2] No such file or directory: ...)"; now
"cannot read camera file PATH: no such file", and likewise for a directory or a file the user
may not read, wherever the CLI reads one (--camera, a spec's camera)."""

from __future__ import annotations

from pathlib import Path

import pytest

from quatrack.cli import main
from quatrack.viewsets.camera import load_camera
from quatrack.viewsets.errors import SpecError


def test_a_missing_camera_file_is_no_such_file(tmp_path, capsys):
    path = tmp_path / "nope.json"
    with pytest.raises(SpecError) as e:
        load_camera(path)
    assert str(e.value) == f"cannot read camera file {path}: no such file"
    image = tmp_path / "frame.png"
    image.write_bytes(b"")
    assert main(["locate", "--object", "cookie-box", "--store", str(tmp_path), "--camera", str(path), str(image)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"quatrack locate: error: cannot read camera file {path}: no such file", err


def test_a_folder_or_a_forbidden_file_is_said_so(tmp_path, monkeypatch):
    with pytest.raises(SpecError) as e:
        load_camera(tmp_path)
    assert str(e.value) == f"cannot read camera file {tmp_path}: it is a directory"
    path = tmp_path / "camera.json"
    path.write_text("{}")

    def forbidden(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "read_text", forbidden)  # (as root the file's mode would not stop it)
    with pytest.raises(SpecError) as e:
        load_camera(path)
    assert str(e.value) == f"cannot read camera file {path}: permission denied"

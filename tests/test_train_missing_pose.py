"""``train`` on a spec whose view gives neither ``pose`` nor ``points`` (user report 3, finding 9;
the README's step 4 writes such a spec for ``quatrack register --locate``): the refusal names
``register --locate``, and is the only line — it came after a warning about another view
("view 0: pose solved from its 6 points … `quatrack register` also fits it …")."""

from __future__ import annotations

import json

from quatrack.cli import main
from test_register import _points_spec


def test_a_view_without_pose_or_points_is_told_of_register_locate_alone(tmp_path, capsys):
    path, _, _ = _points_spec(tmp_path)
    data = json.loads(path.read_text())
    data.pop("zoo", None)  # (the zoo fixture's own field: warned of as unknown)
    bare = {k: data["views"][0][k] for k in ("image", "camera")}
    data["views"].append(bare)
    path.write_text(json.dumps(data))
    assert main(["train", str(path), "--store", str(tmp_path / "store")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "warning" not in err, err
    assert "view 1: missing field 'pose' (or 'points'" in err and f"quatrack register {path} --locate" in err, err
    assert not (tmp_path / "store").exists()


def test_with_no_view_to_start_from_it_is_not_told_of_locate(tmp_path, capsys):
    """(--locate needs a view with a pose or points to train its finder on)"""
    path, _, _ = _points_spec(tmp_path)
    data = json.loads(path.read_text())
    del data["views"][0]["points"]
    path.write_text(json.dumps(data))
    assert main(["train", str(path), "--store", str(tmp_path / "store")]) == 2
    err = capsys.readouterr().err
    assert "view 0: missing field 'pose' (or 'points'" in err and "--locate" not in err, err

"""``quatrack track`` options that apply to one output format only; ``train``'s help on its RFCH options."""

from __future__ import annotations

from quatrack.testing.scenes import EXAMPLE

from test_track_cli import _track


def test_obj_id_is_checked_and_said_to_be_for_bop_only(tmp_path, capsys):
    # --obj-id -3 was written into the BOP file as given; --obj-id with csv was ignored in silence
    video = ["--video", str(EXAMPLE / "box.mp4"), "--max-frames", "1"]
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, *video, "--format", "bop", "--mesh-unit", "cm", "--obj-id", "-3", "--out", str(out)) == 2
    assert capsys.readouterr().err.strip() == ("quatrack track: error: --obj-id -3: BOP object ids are whole numbers "
                                               "from 0 (the datasets' start at 1)") and not out.exists()
    assert _track(tmp_path, *video, "--obj-id", "5", "--out", str(out)) == 0
    assert capsys.readouterr().err.strip() == ("quatrack track: warning: --obj-id is for --format bop only; the csv "
                                               "output has no object id")


def test_train_help_tells_the_rfch_defaults():
    # --rfch-clusters, --rfch-distance and --rfch-scales said nothing of their defaults
    import argparse

    from quatrack.cli import build_parser
    from quatrack.viewsets.rfch import RFCHParams

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["train"]
    helps = {a.option_strings[-1]: a.help for a in sub._actions if a.option_strings}
    d = RFCHParams()
    assert helps["--rfch-clusters"].endswith(f"(default {d.n_clusters})")
    assert helps["--rfch-distance"].endswith(f"(default {d.distance})")
    assert helps["--rfch-scales"].endswith(f"(default {','.join(f'{x:g}' for x in d.scales)})")


def test_mesh_unit_with_csv_does_not_claim_the_mesh_is_in_that_unit(tmp_path, capsys):
    # --mesh-unit mm with CSV said "the csv output is in the mesh's own units (mm)": the cookie
    # box's mesh is in cm; the user's unit was repeated as if it were the mesh's
    video = ["--video", str(EXAMPLE / "box.mp4"), "--max-frames", "1"]
    assert _track(tmp_path, *video, "--mesh-unit", "mm", "--out", str(tmp_path / "poses.csv")) == 0
    assert capsys.readouterr().err.strip() == (
        "quatrack track: warning: --mesh-unit is for --format bop only (it says what unit the mesh is in, to give "
        "BOP's t in mm); the csv output is in the mesh's own units, whatever they are, unconverted")


def test_an_init_pose_quaternion_not_of_length_1_is_said_as_in_a_spec(tmp_path, capsys):
    # q × −2 was normalised in silence while an R scaled by 2 was refused; a spec's pose warns of it
    import json

    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"q_wxyz": [-2.0, 0.0, 0.0, 0.0], "t": [0.0, 0.0, 60.0]}))
    video = ["--video", str(EXAMPLE / "box.mp4"), "--max-frames", "1"]
    assert _track(tmp_path, *video, "--init-pose", str(pose), "--out", str(tmp_path / "poses.csv")) == 0
    err = capsys.readouterr().err.splitlines()
    assert err[0] == (f"quatrack track: warning: --init-pose {pose}: field 'q_wxyz' is 2 long, not 1: read as the "
                      f"unit quaternion [-1, 0, 0, 0] (a unit quaternion [w, x, y, z] is expected)"), err

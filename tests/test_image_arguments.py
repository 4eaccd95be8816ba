"""The image files ``track --images`` and ``locate IMAGE...`` take, expanded alike
(``trackio.image_paths``): globs quoted or expanded by the shell, several of them, list files,
files named that are missing; and the warning for numbered frames read out of their order."""

from __future__ import annotations

import csv
import json

import cv2

from quatrack.cli import main
from quatrack.recognition import trackio
from quatrack.testing.scenes import EXAMPLE, example_store

from test_track_cli import _box_frames, _track


def _frames(folder, names) -> None:
    frame = _box_frames(1)[0]
    for name in names:
        assert cv2.imwrite(str(folder / name), frame)


def test_a_missing_file_among_those_named_is_a_lost_row_in_its_place(tmp_path, capsys):
    # --images f0.png missing.png f2.png: the missing one was left out without a word, and f2's
    # row came as frame 1 (a list's missing line was already a lost row in its place)
    frames = _box_frames(3)
    for k in (0, 2):
        assert cv2.imwrite(str(tmp_path / f"f{k}.png"), frames[k])
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, "--images", str(tmp_path / "f0.png"), str(tmp_path / "missing.png"),
                  str(tmp_path / "f2.png"), "--out", str(out)) == 0
    rows = list(csv.reader(out.open()))[1:]
    assert [(r[0], r[2]) for r in rows] == [("0", "init"), ("1", "lost"), ("2", "tracking")]
    assert "frame 1 cannot be read" in capsys.readouterr().err
    # all named files missing: as before, no file matches
    paths = [str(tmp_path / "none.png")]
    assert _track(tmp_path, "--images", *paths, "--out", str(out)) == 2
    assert "no file matches" in capsys.readouterr().err


def test_frames_numbered_without_leading_zeros_named_one_by_one_are_warned_of(tmp_path, capsys):
    # `--images frames/frame_*.png` unquoted: the shell expands and sorts the names itself, so
    # track got frame_1 frame_10 frame_2 as files named one by one and warned of nothing (the
    # quoted glob was warned of); and so a list written by `ls`
    _frames(tmp_path, [f"frame_{n}.png" for n in (1, 2, 10)])
    by_name = [str(tmp_path / f"frame_{n}.png") for n in (1, 10, 2)]
    out = str(tmp_path / "poses.csv")
    assert _track(tmp_path, "--images", *by_name, "--max-frames", "1", "--out", out) == 0
    err = capsys.readouterr().err.strip()
    assert err == (f"quatrack track: warning: --images are read in the order given, so {by_name[1]} comes before "
                   f"{by_name[2]}: number the files with leading zeros (0002 for 2), or give them in order"), err
    listing = tmp_path / "frames.txt"
    listing.write_text("\n".join(p.rsplit("/", 1)[1] for p in by_name) + "\n")
    assert _track(tmp_path, "--images", str(listing), "--max-frames", "1", "--out", out) == 0
    assert f"so {by_name[1]} comes before {by_name[2]}" in capsys.readouterr().err
    # in their order, or backwards on purpose: nothing to say
    for order in ((1, 2, 10), (10, 2, 1)):
        assert _track(tmp_path, "--images", *[str(tmp_path / f"frame_{n}.png") for n in order],
                      "--max-frames", "1", "--out", out) == 0
        assert capsys.readouterr().err == ""


def test_locate_reads_a_list_file_as_track_does(tmp_path, capsys):
    # locate frames.txt was read as an image ("cannot be decoded"); track --images frames.txt reads
    # the images it lists
    _frames(tmp_path, ["0000.png"])
    listing = tmp_path / "frames.txt"
    listing.write_text("0000.png\nmissing.png\n")
    rc = main(["locate", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"), "--store",
               str(example_store()), "--json", str(listing)])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["image"] for line in lines] == [str(tmp_path / "0000.png"), str(tmp_path / "missing.png")]
    assert lines[0]["found"] and "error" in lines[1] and rc == 1
    assert trackio.image_paths([str(listing)]) == [line["image"] for line in lines]


def test_a_list_of_missing_files_names_the_first(tmp_path, capsys):
    listing = tmp_path / "frames.txt"
    listing.write_text("gone.png\n")
    assert _track(tmp_path, "--images", str(listing), "--out", str(tmp_path / "poses.csv")) == 2
    err = capsys.readouterr().err
    assert "no frame can be read" in err and "gone.png" in err, err


"""``quatrack demo``'s outputs for a video with frames that cannot be decoded: one row per frame
and one overlay frame per row, as ``quatrack track`` writes them."""

from __future__ import annotations

import csv

import cv2

from quatrack.cli import main
from quatrack.testing.scenes import EXAMPLE, example_store

from test_track_cli import _box_frames, _mjpg_avi


def test_demo_writes_a_lost_row_for_a_frame_that_cannot_be_decoded(tmp_path, capsys):
    # frames 3 and 4 zeroed: the CSV went from frame 2 to frame 5 (track writes them as lost) and the
    # overlay had 4 frames for 6 rows (the last rows' frames were never read)
    video = tmp_path / "damaged.avi"
    _mjpg_avi(video, _box_frames(8), damaged=(3, 4))
    out = tmp_path / "out"
    assert main(["demo", "--video", str(video), "--camera", str(EXAMPLE / "camera.json"), "--store",
                 str(example_store()), "--out-dir", str(out), "--plot", "none", "--quiet"]) == 0
    printed, err = capsys.readouterr()
    rows = list(csv.DictReader((out / "poses.csv").open()))
    assert [r["frame"] for r in rows] == [str(k) for k in range(8)]
    assert [rows[k]["status"] for k in (3, 4)] == ["lost", "lost"] and rows[3]["tx"] == ""
    assert f"demo: frame 3 cannot be read, written as lost: --video {video}: its data cannot be decoded" in err
    assert "demo: 6 frames sent, 6 tracked answers" in printed and "0 errors" in printed, printed
    cap = cv2.VideoCapture(str(out / "overlay.mp4"))
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == 8

"""`quatrack track`'s closing summary when the object was never found (user report, session 73):
it said "pose in 0.0 % of frames after the first init; step p50 - ms" of a run with no init."""

from __future__ import annotations

import cv2
import numpy as np

from quatrack.cli import main
from quatrack.testing.scenes import EXAMPLE, example_store


def test_a_run_that_never_finds_the_object_says_so(tmp_path, capsys):
    for k in range(2):
        assert cv2.imwrite(str(tmp_path / f"{k:04d}.png"), np.full((480, 640, 3), 128, np.uint8))
    code = main(["track", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"), "--store",
                 str(example_store()), "--images", str(tmp_path / "*.png"), "--out", str(tmp_path / "p.csv")])
    out = capsys.readouterr().out
    assert code == 0
    assert "init 0, tracking 0, lost 2; the object was found in no frame" in out, out
    assert "after the first init" not in out

"""``--motion-noise`` (and ``TrackerParams.motion_noise``) values beyond
:data:`~quatrack.recognition.tracker.params.MAX_MOTION_NOISE` are refused naming the range
(user report: ``a=1e300,alpha=1e300`` passed the "finite value >= 0" check, and numpy's
"overflow encountered in multiply" and "invalid value encountered in subtract" came out twice
each); values up to it track without a numpy warning."""

from __future__ import annotations

import pytest

from quatrack.recognition.tracker.params import MAX_MOTION_NOISE
from quatrack.recognition.video import TrackerParams
from quatrack.testing.scenes import EXAMPLE

from test_track_cli import _track

VIDEO = ["--video", str(EXAMPLE / "box.mp4")]


def test_a_noise_whose_products_overflow_is_refused_naming_the_range(tmp_path, capsys):
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, *VIDEO, "--motion-noise", "a=1e300,alpha=1e300", "--out", str(out)) == 2
    assert capsys.readouterr().err.strip() == (
        "quatrack track: error: --motion-noise: 'a=1e300' is too large: give a value from 0 to 1e+100 (in the "
        "mesh's units; ude's defaults: a = 1.85 × the object's diameter², alpha = 20)")
    assert not out.exists()
    assert _track(tmp_path, *VIDEO, "--motion-model", "m1", "--motion-noise", "sigma_phi2=1e200", "--out", str(out)) == 2
    assert "m1's defaults: sigma_p2 = 0.093 × the object's diameter², sigma_phi2 = 0.3" in capsys.readouterr().err


@pytest.mark.parametrize("model, noise", [("ude", {"alpha": 1e300}), ("m2", {"sigma_p2": 2e100})])
def test_the_library_refuses_them_too(model, noise):
    with pytest.raises(ValueError, match=r"motion_noise\['\w+'\] = [0-9e+]+ is too large: at most 1e\+100 \("):
        TrackerParams(motion_model=model, motion_noise=noise)


def test_the_largest_noise_taken_tracks_without_a_numpy_warning(tmp_path, capsys):
    big = f"{MAX_MOTION_NOISE:g}"
    assert _track(tmp_path, *VIDEO, "--max-frames", "4", "--motion-noise", f"a={big},alpha={big}",
                  "--out", str(tmp_path / "poses.csv")) == 0
    assert capsys.readouterr().err == ""

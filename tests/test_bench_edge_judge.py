"""``quatrack bench edge-judge`` (issue 12): the edge judges' error rates from the truth.

- a pose moved by ``share`` of the criterion is exactly that far (any share, any direction);
- the figures are the shares of refusals of the verdicts given;
- on a short rendered walk (``short_orbit``: the whole object in view, no blur, light or hand) the
  judges pass the true poses and the refit-based ones refuse poses 1.2 × the criterion off.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, strategies as st

from quatrack.bench import edge_judge as E
from quatrack.recognition.evidence import pose_shift
from quatrack.testing import zoo as Z
from quatrack.testing.orbit import short_orbit
from quatrack.tracking import quaternion as quat
from quatrack.tracking.pose import Pose


@given(share=st.floats(0.01, 3.0), seed=st.integers(0, 2**31 - 1), rot=st.lists(st.floats(-3, 3), min_size=3, max_size=3))
def test_a_moved_pose_is_that_share_of_the_criterion_away(share, seed, rot):
    mesh = Z.textured("hex-prism-m").mesh
    pose = Pose(quat.exp(0.5 * np.array(rot)), np.array([0.01, -0.02, 0.6]))
    moved = E.moved(pose, share, mesh.centre, mesh.extent, np.random.default_rng(seed))
    assert abs(pose_shift(moved, pose, mesh) - share) < 1e-6 * max(share, 1.0)


def test_the_figures_are_the_shares_refused():
    def v(frame, d, refused, shift=0.1, gain=0.0):
        return E.Verdict("w", frame, d, {j: refused for j in E.JUDGES}, shift, gain)

    verdicts = [v(0, 0.0, False), v(1, 0.0, True, 0.7, 0.2), v(0, 0.3, False), v(1, 0.3, False),
                v(0, 1.2, True), v(1, 1.2, True), v(2, 0.0, False, float("nan"), float("nan"))]
    f = E.figures(verdicts)
    assert f["w"]["frames"] == 3 and f["all"]["frames"] == 3
    for j in E.JUDGES:
        assert f["w"][j] == {"0.0": 1 / 3, "0.3": 0.0, "1.2": 1.0}
    assert f["w"]["shift_at_truth"][0] == pytest.approx(0.4)  # the median of the finite shifts (0.1, 0.7)
    assert "| w | 3 |" in E.report(f)


def test_on_a_clean_walk_true_poses_pass_and_poses_beyond_the_criterion_are_caught():
    verdicts = E.study(("wide-box-cm",), renderings=1, every=6, seconds=1.0, orbit=short_orbit(1.0),
                       backgrounds=Z.real_backgrounds())
    at = {d: [v for v in verdicts if v.distance == d] for d in E.DISTANCES}
    assert len(at[0.0]) == 5
    assert not any(v.refused["agreement"] for v in at[0.0])
    for j in ("edges-refit", "agreement-gain"):
        assert np.mean([v.refused[j] for v in at[1.2]]) >= 0.8, j


def test_the_cli_refuses_bad_options_with_a_message(capsys):
    from quatrack.cli import main

    assert main(["bench", "edge-judge", "--every", "0"]) == 2
    assert "--every must be >= 1" in capsys.readouterr().err
    assert main(["bench", "edge-judge", "--sequences", "teapot"]) == 2
    assert "no zoo object 'teapot'" in capsys.readouterr().err
    assert main(["bench", "track-zoo", "--renderings", "0"]) == 2
    assert "--renderings must be between 1 and 20" in capsys.readouterr().err
    for bad in ("a,b,c,d", "-0.1,0.02", "1,2,3,4,5,6,7,8,9", "nan,0,0,0"):
        assert main(["bench", "track-zoo", f"--lens={bad}"]) == 2
        assert "--lens must be 4 to 8 numbers" in capsys.readouterr().err
    for bad in ("1280", "1280x", "wide", "100x100", "8000x720"):
        assert main(["bench", "track-zoo", "--size", bad]) == 2
        assert "--size must be" in capsys.readouterr().err

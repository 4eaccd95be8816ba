"""The Ude (1999) experiment as a test of the whole filter: consistency with its own bounds.

The benchmark itself (20 seeds, timings) runs from the CLI; here two seeds check properties
that must hold for any correct implementation, whatever the random draw.
"""

import json

import numpy as np
import pytest

from quatrack.bench import ude_cube
from quatrack.cli import main
from quatrack.tracking import quaternion as quat

REQUIRED = ["position_mm", "orientation_deg", "velocity_mm_s", "angular_velocity_deg_s",
            "predicted_position_mm", "predicted_orientation_deg"]


@pytest.fixture(scope="module")
def summary():
    return ude_cube.run(seeds=2, progress=False)


def test_trajectory_is_the_papers():
    p, q = ude_cube.truth(np.array([0.0, 6.0]))
    np.testing.assert_allclose(p[0], [-300 * np.sqrt(3), 300 * np.sqrt(3), 2800])
    np.testing.assert_allclose(np.linalg.norm(ude_cube.V_TRUE), 300.0)  # mm/s
    np.testing.assert_allclose(np.degrees(np.linalg.norm(ude_cube.OMEGA_TRUE)), 15.0)  # deg/s
    # 6 s at 15 °/s
    assert np.degrees(quat.angle_between(q[1], q[0])) == pytest.approx(90.0)
    cam = ude_cube.camera()
    assert cam.fx == pytest.approx(727.2727, rel=1e-6)
    # the cube stays in the image for the whole sequence, with 4 to 9 visible edges
    V, edges, _ = ude_cube.cube()
    for t in ude_cube.frame_times():
        p, q = ude_cube.truth(t)
        idx = ude_cube.visible_edges(p, q)
        assert 4 <= len(idx) <= 9
        uv = cam.project(V[edges[idx]].reshape(-1, 3) @ quat.to_matrix(q).T + p)
        assert (uv >= 0).all() and (uv[:, 0] < 640).all() and (uv[:, 1] < 480).all()


def test_converges_like_table_1(summary):
    assert summary["iterations"] <= 6
    assert summary["iterations_max"] <= 6
    assert summary["final_gradient_norm_sq_max"] < 1e-10
    grads = [row[4] for row in summary["table1"]]
    assert all(b < a for a, b in zip(grads, grads[1:]))  # ‖∇F‖² falls every step


def test_filter_covariance_agrees_with_the_plant_noise_bound(summary):
    for key in REQUIRED:
        assert summary["per_seed"][key]["filter_sigma_vs_crb"] == pytest.approx(1.0, abs=0.1), key


def test_errors_agree_with_the_filters_linearised_prediction(summary):
    for key in REQUIRED:
        # two seeds: sampling error of an RMS is large; a units slip (×2 in angle) is not
        assert 0.6 < summary["linearised_prediction_ratio"][key] < 1.5, key
        assert summary["crb_ratio_no_plant_noise"][key] > 0.7, key  # no estimator beats the bound


def test_cli_prints_the_json_contract(capsys):
    assert main(["bench", "ude-cube", "--seeds", "2", "--json", "--variant", "silhouette-edges"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in REQUIRED + ["adjust_ms_p50", "adjust_ms_p95", "iterations"]:
        assert np.isfinite(out[key]), key
    for group in ("crb_ratio", "crb_ratio_no_plant_noise"):
        assert set(REQUIRED) <= set(out[group])


def test_cli_refuses_bad_arguments(capsys):
    assert main(["bench", "ude-cube", "--seeds", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--seeds" in err
    with pytest.raises(SystemExit):
        main(["bench", "ude-cube", "--variant", "nonsense"])

"""``quatrack bench track-ab``: tracker settings compared in one process on one video."""

from __future__ import annotations

import doctest
import json

import pytest

from quatrack.bench import track_ab
from quatrack.recognition.video import TrackerParams


def test_the_module_examples_hold():
    assert doctest.testmod(track_ab).failed == 0


def test_a_variant_replaces_fields_and_nested_fields_and_keeps_the_rest():
    base = TrackerParams()
    name, p = track_ab.parse_variant('lean={"max_points": 150, "klt": {"win": 17}, "sources": ["trained", "mesh"], '
                                     '"systematic_pct": 1}', base)
    assert name == "lean"
    assert (p.max_points, p.klt.win, p.sources) == (150, 17, ("trained", "mesh"))
    assert p.systematic_pct == 1.0 and isinstance(p.systematic_pct, float)
    assert p.klt.levels == base.klt.levels and p.min_points == base.min_points and p.locate == base.locate


@pytest.mark.parametrize("text, message", [
    ('x={"nope": 1}', "TrackerParams has no field 'nope' (known: adjust,"),
    ('x={"klt": {"wide": 3}}', "KLTParams has no field 'wide'"),
    ('x={"klt": {"win": "a"}}', 'win must be an integer, not "a"'),
    ('x={"klt": {"win": 1.5}}', "win must be an integer, not 1.5"),
    ('x={"learn": 1}', "learn must be true or false, not 1"),
    ('x={"sources": "trained"}', 'sources must be a list, not "trained"'),
    ("x=[1]", "the JSON must be an object"),
    ('x={"a": ', "not JSON"),
    ('{"klt": {}}', "write NAME=JSON"),
])
def test_a_variant_the_tracker_cannot_take_is_refused_with_the_reason(text, message):
    with pytest.raises(ValueError) as err:
        track_ab.parse_variant(text, TrackerParams())
    assert message in str(err.value)


@pytest.fixture(scope="module")
def box_frames():
    from quatrack.examples import example_dir
    from quatrack.recognition.trackio import open_frames

    frames, times = [], []
    for _, t, image in open_frames(video=str(example_dir() / "box.mp4"), max_frames=8):
        frames.append(image)
        times.append(t)
    return frames, times


def test_the_trackers_step_apart_and_an_unchanged_variant_gives_the_same_poses(box_frames):
    """Each variant has its own tracker: one with the defaults spelt out tracks exactly as base
    (distance 0), one that weighs the points differently does not; every step is timed."""
    from quatrack.service.tracker_factory import make_tracker
    from quatrack.testing.scenes import EXAMPLE, example_model
    from quatrack.viewsets.camera import load_camera

    frames, times = box_frames
    model, camera = example_model(), load_camera(EXAMPLE / "camera.json")
    base = make_tracker(model, camera, None, 640 * 480).params
    variants = [("base", base), track_ab.parse_variant(f'same={{"audit_every": {base.audit_every}}}', base),
                track_ab.parse_variant(f'other={{"sigma_px": {2 * base.sigma_px}}}', base)]
    rows = track_ab.compare(frames, times, model, camera, variants)
    by = {r["variant"]: r for r in rows}
    assert [r["variant"] for r in rows] == ["base", "same", "other"]
    assert all(r["frames"] == len(frames) and r["lost"] == 0 and r["cpu_p50_ms"] > 0 for r in rows)
    assert by["base"]["from_base_max_pct"] == 0.0 and by["same"]["from_base_max_pct"] == 0.0
    assert by["other"]["from_base_max_pct"] > 0.0
    table = track_ab.report(rows)
    assert table.count("\n") == 4 and "| same | 8 | 0 |" in table
    json.dumps({"variants": rows})  # (the --json output)


def test_the_command_refuses_a_bad_variant_without_a_traceback(capsys):
    from quatrack.cli import main

    assert main(["bench", "track-ab", "--frames", "2", 'x={"klt": {"win": -3}}']) == 2
    err = capsys.readouterr().err
    assert "variant 'x': the tracker failed" in err and "Traceback" not in err
    assert main(["bench", "track-ab", "--frames", "1"]) == 2
    assert "--frames must be at least 2" in capsys.readouterr().err


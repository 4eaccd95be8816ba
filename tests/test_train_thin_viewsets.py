"""Viewsets with few keypoints are said in one line (user report 3, finding 4): a textureless box
gave one warning per viewset (15 lines), the two with none were dropped without a word (the
summary said 13 viewsets), and no line said that the model would hardly be found from other
viewpoints than its photos'."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from quatrack.viewsets.novel import NovelViewParams
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.train import TrainParams, _thin_notes, train_object

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cookie-box"


@dataclass
class _VS:
    label: str
    synthetic: bool
    n: int

    def __len__(self) -> int:
        return self.n


def test_training_says_the_thin_viewsets_in_one_line(tmp_path):
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / data["mesh"])
    data["views"] = [dict(data["views"][0], image=str(EXAMPLE / data["views"][0]["image"]))]
    (tmp_path / "spec.json").write_text(json.dumps(data))
    said: list[str] = []
    # (every viewset "thin": at least a million keypoints asked of each)
    params = TrainParams(novel=NovelViewParams((20.0,), "xy", ()), min_keypoints=10**6, min_keypoint_density=None)
    model = train_object(load_spec(tmp_path / "spec.json"), params, warn=said.append)
    assert len(model.viewsets) == 5
    thin = [m for m in said if "keypoints with 3-D points" in m]
    assert len(thin) == 1 and thin[0].startswith("5 of 5 viewsets have fewer than 1000000 keypoints"), said
    assert "view0: " in thin[0] and "4 synthetic: " in thin[0] and "dropped" not in thin[0], thin
    assert said[-1].endswith("the model will hardly be found from other viewpoints than the photos'"), said


def test_the_dropped_are_counted_and_named():
    vs = [_VS("view0", False, 10)] + [_VS(f"view0-s{k}", True, n) for k, n in enumerate((0, 3, 0, 8, 25))]
    line, verdict = _thin_notes(vs, 20)
    assert line == ("5 of 6 viewsets have fewer than 20 keypoints with 3-D points (view0: 10; 4 synthetic: 0–8); "
                    "2 with none are dropped (view0-s0, view0-s2): nothing in them to match")
    assert "4 of 5 synthetic" in verdict and "hardly be found" in verdict


def test_a_few_thin_views_are_not_said_to_make_the_model_hard_to_find():
    vs = [_VS("view0", False, 300), _VS("view1", False, 0)] + [_VS(f"view0-s{i}", True, 50 + i) for i in range(4)]
    assert _thin_notes(vs, 20) == ["1 of 6 viewsets has fewer than 20 keypoints with 3-D points (view1: 0); "
                                   "1 with none is dropped (view1): nothing in it to match"]
    assert _thin_notes(vs[:1], 20) == []

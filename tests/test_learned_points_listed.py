"""``models list`` counts the learned views' points too (trial report, item 3).

Its points column was the training summary's ``points3d_total``: a model that learned ten views
on a walk round listed the same points as before it. The column keeps that number (the trained
views' points) and adds the learned views' own, as the viewsets column does: ``930 points (+N learned)``.
"""

from __future__ import annotations

from quatrack.cli import main
from quatrack.viewsets import learn as L
from quatrack.viewsets import store as S
from test_store_changes import turned_views

NAME = "cookie-box"


def _row(store, capsys) -> list[str]:
    capsys.readouterr()
    assert main(["models", "list", "--store", str(store)]) == 0
    return capsys.readouterr().out.splitlines()[0].split("\t")


def test_models_list_adds_the_learned_points(store, capsys):
    model = S.load_model(store, NAME)
    trained = model.manifest["training_summary"]["points3d_total"]
    assert _row(store, capsys)[2] == f"{trained} points"  # (nothing learned: as before)
    views = turned_views(model)
    L.merge_learned(store, NAME, views, model.mesh)
    learned = sum(len(vs) for vs in views)
    assert learned > 0
    row = _row(store, capsys)
    assert row[1] == f"{len(model.viewsets)} viewsets (+2 learned)" and row[2] == f"{trained} points (+{learned} learned)", row
    assert S.learned_points(S.load_manifest(store, NAME)) == learned


def test_learned_points_of_a_manifest_without_learned_views_or_readable_entries():
    assert S.learned_points({}) == 0
    assert S.learned_points({"viewsets": "garbage"}) == 0
    assert S.learned_points({"viewsets": [{"keypoints": 5}, {"keypoints": 7, "learned": True}, 3,
                                          {"keypoints": "x", "learned": True}]}) == 7


def test_the_objects_list_says_the_learned_points(store):
    """``GET /v1/objects``: ``points3d`` stays the trained views' points, and the learned views'
    own are ``learned_points3d`` (it listed the same points after ten views were learned)."""
    from fastapi.testclient import TestClient

    from quatrack.service.app import create_app
    from quatrack.service.settings import Settings

    model = S.load_model(store, NAME)
    trained = model.manifest["training_summary"]["points3d_total"]
    views = turned_views(model)
    L.merge_learned(store, NAME, views, model.mesh)
    with TestClient(create_app(Settings(store=store, preload=False, workers=1, threads=1, model_poll_s=0))) as c:
        item = c.get("/v1/objects").json()["objects"][0]
    assert item["points3d"] == trained and item["learned_viewsets"] == 2
    assert item["learned_points3d"] == sum(len(vs) for vs in views) > 0

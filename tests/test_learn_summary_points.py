"""``track --learn``'s closing line says what the views it learned hold (user report, finding 7):
a box with four plain sides, walked round, "learned 7 new view(s)" of 296–472 points, only 10–18
of them where the model had none (its two textured faces again), and re-finding it from its
other sides gained nothing, with no hint. The line now gives each view's points and the new ones
among them, and a warning (a line of its own, without the word "learned": one line has it) names
the views that add fewer new points than a view needs to be learned at all."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import cv2
import numpy as np

from quatrack.recognition.video import TrackerParams
from quatrack.track_cli import _store_learned
from quatrack.tracking.pose import Pose
from quatrack.viewsets.learn import new_points
from quatrack.viewsets.store import load_model

NAME = "cookie-box"


def _seen_turned(vs, centre: np.ndarray, deg: float, shift: np.ndarray | None = None):
    """``vs`` as a learned view from ``deg`` round the object (about its centre's z axis), its
    points moved by ``shift`` (None: the view's own points, texture the model knows)."""
    Rz = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(deg)]))[0]
    R0, t0 = vs.pose.R, vs.pose.t
    pose = Pose.from_matrix(R0 @ Rz, R0 @ (centre - Rz @ centre) + t0)
    points = vs.points3d if shift is None else vs.points3d + shift
    return dataclasses.replace(vs, label="new", pose=pose, points3d=points, learned=True)


def test_new_points_counts_the_points_away_from_every_known_one(base_store):
    model = load_model(base_store, NAME)
    vs, d = model.viewsets[0], model.mesh.extent
    away = _seen_turned(vs, model.mesh.centre, 90.0, np.array([0.0, 0.0, 3.0 * d]))
    assert new_points([vs, away], model.viewsets, d) == [0, len(vs)]
    assert new_points([vs], [], d) == [len(vs)]  # (nothing known: every point is new)


def test_the_line_gives_the_views_points_and_warns_of_views_that_add_none(store, capsys):
    model = load_model(store, NAME)
    vs, c, d = model.viewsets[0], model.mesh.centre, model.mesh.extent
    views = [_seen_turned(vs, c, 90.0), _seen_turned(vs, c, 180.0, np.array([0.0, 0.0, 3.0 * d]))]
    tracker = SimpleNamespace(learned_viewsets=lambda: views, params=TrackerParams(), model=model)
    s = SimpleNamespace(store=store, model=model, tracker=tracker)
    capsys.readouterr()
    _store_learned(s, NAME)
    err = capsys.readouterr().err.splitlines()
    n = len(vs)
    assert len(err) == 2, err
    assert err[0] == (f"quatrack track: learned 2 new view(s) -> {store / NAME} (2 learned in all); their points: "
                      f"{n}, {n} ({n} of them where the model had none: 0, {n})"), err
    assert err[1].startswith("quatrack track: warning: 1 of the 2 new view(s) hold fewer than 30 points where the "
                             "model had none (0): they show texture it already knew"), err
    assert "learned" not in err[1]
    assert sum(v.learned for v in load_model(store, NAME).viewsets) == 2

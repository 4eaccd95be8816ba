"""``viewsets.store.save_model`` replacing a stored model that holds views learned while
tracking by one without them: the library call dropped them in silence, where ``quatrack
train`` and ``learn.save_trained`` keep them (or say what they drop). Now it warns, naming how
many and the function that keeps them."""

from __future__ import annotations

import dataclasses
import warnings

import pytest

from quatrack.viewsets import learn as L
from quatrack.viewsets import store as S
from test_store_changes import turned_views

NAME = "cookie-box"


@pytest.fixture
def learned_store(store):
    model = S.load_model(store, NAME)
    assert L.merge_learned(store, NAME, turned_views(model), model.mesh)[1] == 2
    return store


def _trained_only(store):
    model = S.load_model(store, NAME)
    return dataclasses.replace(model, viewsets=[v for v in model.viewsets if not v.learned])


def test_replacing_learned_views_warns_how_many_and_what_keeps_them(learned_store):
    with pytest.warns(UserWarning, match=r"'cookie-box' in .* 2 dropped \(quatrack\.viewsets\.learn\.save_trained"):
        S.save_model(learned_store, _trained_only(learned_store))
    assert S.learned_count(learned_store, NAME) == 0  # (saved all the same: a warning, not a refusal)


def test_keeping_them_or_having_none_is_silent(learned_store, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        S.save_model(learned_store, S.load_model(learned_store, NAME))  # the learned views saved back
        assert S.learned_count(learned_store, NAME) == 2
        kept = L.save_trained(learned_store, _trained_only(learned_store))  # what train does: kept
        assert (kept.kept, kept.dropped) == (2, 0) and S.learned_count(learned_store, NAME) == 2
        asked = L.save_trained(learned_store, _trained_only(learned_store), keep_learned=False)
        assert asked.dropped == 2 and S.learned_count(learned_store, NAME) == 0  # (asked for: no warning)
        S.save_model(learned_store, _trained_only(learned_store))  # nothing learned to lose
        S.save_model(tmp_path / "fresh", _trained_only(learned_store))  # nothing stored to replace

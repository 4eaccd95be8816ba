"""What ``quatrack serve`` warns of when it starts (it still starts).

``QUATRACK_LEARN_VIEWS`` naming an object the store does not hold (a typo, another case) is
warned of when ``quatrack serve`` starts, with the nearest name: the names are compared whole, so
those sessions learned nothing, in silence. The server still starts (an object of that name
trained later is learned from)."""

from __future__ import annotations

import pytest

from quatrack.cli import main
from quatrack.testing.loopback import free_port
from quatrack.testing.scenes import example_store


@pytest.mark.parametrize("value, warned", [
    ("Cookie-Box", ["'Cookie-Box'", "did you mean 'cookie-box'?"]),
    ("cookie-box,cookie-bx", ["'cookie-bx'", "did you mean 'cookie-box'?"]),
    ("cookie-box", []),
    ("*", []),
])
def test_a_learned_object_the_store_lacks_is_warned_of(not_started, capsys, value, warned):
    env, started = not_started
    store = example_store()
    env.setenv("QUATRACK_LEARN_VIEWS", value)
    code = main(["serve", "--store", str(store), "--port", str(free_port()), "--workers", "1"])
    err = capsys.readouterr().err
    assert code == 0 and len(started) == 1, err
    lines = [line for line in err.splitlines() if "QUATRACK_LEARN_VIEWS" in line]
    if not warned:
        assert lines == [], err
    else:
        assert len(lines) == 1 and lines[0].startswith("quatrack serve: warning: QUATRACK_LEARN_VIEWS names "), err
        assert all(part in lines[0] for part in warned) and "(it holds cookie-box)" in lines[0], lines[0]
        assert lines[0].endswith("its sessions learn no views until an object of that name is trained"), lines[0]


def test_no_such_warning_for_a_store_that_does_not_exist(not_started, capsys, tmp_path):
    env, _ = not_started
    env.setenv("QUATRACK_LEARN_VIEWS", "box")
    assert main(["serve", "--store", str(tmp_path / "nowhere"), "--port", str(free_port()), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    assert "does not exist" in err and "QUATRACK_LEARN_VIEWS" not in err, err


def test_a_models_own_folder_as_the_store_is_warned_of(not_started, capsys):
    """``--store STORE/cookie-box`` (the model's folder) served a store without objects, in
    silence, as ``models list`` read it before (``viewsets.store.store_note``)."""
    store = example_store()
    assert main(["serve", "--store", str(store / "cookie-box"), "--port", str(free_port()), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    assert (f"quatrack serve: warning: the store {store / 'cookie-box'} holds no object (the folder of object "
            f"'cookie-box' itself: its store is {store})\n") in err, err
    assert main(["serve", "--store", str(store), "--port", str(free_port()), "--workers", "1"]) == 0
    assert "holds no object" not in capsys.readouterr().err

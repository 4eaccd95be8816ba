"""``quatrack bench serve --object NAME`` with a name the store does not hold: refused before the
run (every stream would be refused: a table of NaN, exit 0) as the other commands refuse it
(``viewsets.store.unknown_object``): the nearest name and the objects held. It said ``not in
STORE (it holds ...)``, with no suggestion, after decoding the whole video."""

from __future__ import annotations

from quatrack.cli import main
from quatrack.testing.scenes import example_store

BENCH = ["bench", "serve", "--replicas", "no", "--clients", "1", "--workers", "1", "--frames", "1"]


def test_a_misspelt_object_gets_the_nearest_name_before_the_video_is_read(tmp_path, capsys):
    store = example_store()
    # (a video that does not exist: the object is checked first, so it is never opened)
    assert main([*BENCH, "--store", str(store), "--object", "Cookie-bx", "--video", str(tmp_path / "none.mp4")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"quatrack bench: error: --object: no object named 'Cookie-bx' in {store}; "
                   f"did you mean 'cookie-box'? (it holds cookie-box)"), err


def test_an_empty_or_missing_store_is_said_so(tmp_path, capsys):
    empty = tmp_path / "store"
    empty.mkdir()
    assert main([*BENCH, "--store", str(empty)]) == 2
    assert capsys.readouterr().err.strip() == \
        f"quatrack bench: error: --object: no object named 'cookie-box' in {empty} (it holds none)"
    assert main([*BENCH, "--store", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"quatrack bench: error: --object: no object named 'cookie-box' in {tmp_path / 'nowhere'}") \
        and "no such folder" in err and "\n" not in err, err


def test_the_object_of_the_trained_spec_is_named(capsys):
    """Without ``--store`` the run trains the example into a temporary store: the message names
    the spec, not that folder."""
    from quatrack.examples import example_dir

    assert main([*BENCH, "--object", "cookie-bx"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"quatrack bench: error: --object: no object named 'cookie-bx' in the model trained from "
                   f"{example_dir() / 'object.json'}; did you mean 'cookie-box'? (it holds cookie-box)"), err

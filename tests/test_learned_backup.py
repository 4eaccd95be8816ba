"""A retraining that drops learned views unasked keeps them recoverable (trial report, item 2).

``train --root-sift`` (or another mesh) over a model holding views learned on a walk round dropped
them all, with a warning printed after the old model was already replaced (exit 0): a walk-round
is expensive to repeat. Now the replaced model is first copied to ``STORE/.learned-backup/NAME``
(the warning says where and how to restore it), and a later retraining that fits them again —
the README's unattended ``train ... --skip-existing`` with the former settings — carries them back.
"""

from __future__ import annotations

from conftest import EXAMPLE, FAST_TRAIN
from quatrack.cli import main
from quatrack.viewsets import learn as L
from quatrack.viewsets import store as S
from test_store_changes import turned_views

NAME = "cookie-box"
SPEC = str(EXAMPLE / "object.json")


def _learned(store, name=NAME) -> list[str]:
    return [vs.label for vs in S.load_model(store, name).viewsets if vs.learned]


def _with_learned(store) -> None:
    model = S.load_model(store, NAME)
    assert L.merge_learned(store, NAME, turned_views(model), model.mesh)[1] == 2


def test_other_descriptors_keep_a_copy_and_a_retraining_carries_them_back(store, capsys):
    _with_learned(store)
    capsys.readouterr()
    assert main(["train", SPEC, "--store", str(store), *FAST_TRAIN, "--root-sift"]) == 0
    out, err = capsys.readouterr()
    backup = store / L.BACKUP_DIR / NAME
    assert "2 dropped: the descriptors changed" in err, err
    assert (f"quatrack train: warning: the replaced model of {NAME!r}, with its 2 learned view(s), is kept in "
            f"{backup}: train {NAME!r} again with its former mesh and settings") in err, err
    assert f"&& mv {backup} {store / NAME}" in err, err
    assert _learned(store) == [] and _learned(store / L.BACKUP_DIR) == ["learned1", "learned2"]
    assert main(["models", "list", "--store", str(store)]) == 0
    listed = capsys.readouterr()
    assert [line.split("\t")[0] for line in listed.out.splitlines()] == [NAME] and L.BACKUP_DIR not in listed.err
    # the README's unattended command, with the former settings: the views come back, the copy goes
    assert main(["train", SPEC, "--store", str(store), *FAST_TRAIN, "--skip-existing"]) == 0
    out, err = capsys.readouterr()
    assert f"  views learned while tracking: 2 carried back from {store / L.BACKUP_DIR}\n" in out, (out, err)
    assert "learned" not in err, err  # (only --skip-existing's "the training options changed; training it again")
    assert _learned(store) == ["learned1", "learned2"] and not backup.exists()
    assert S.load_model(store, NAME).manifest["learned_viewsets"] == 2


def test_drop_learned_forgets_the_copy_too(store, capsys):
    _with_learned(store)
    assert main(["train", SPEC, "--store", str(store), *FAST_TRAIN, "--root-sift"]) == 0
    assert (store / L.BACKUP_DIR / NAME).is_dir()
    assert main(["train", SPEC, "--store", str(store), *FAST_TRAIN, "--drop-learned"]) == 0
    capsys.readouterr()
    assert _learned(store) == [] and not (store / L.BACKUP_DIR / NAME).exists()


def test_a_copy_that_does_not_fit_stays(store, capsys):
    """Retrained with --root-sift twice: the second finds no view in the stored model and none of
    the copy's fits (still SIFT): the copy stays for a retraining that fits it."""
    _with_learned(store)
    for _ in range(2):
        assert main(["train", SPEC, "--store", str(store), *FAST_TRAIN, "--root-sift"]) == 0
    out, err = capsys.readouterr()
    assert "carried back" not in out and _learned(store / L.BACKUP_DIR) == ["learned1", "learned2"]


def test_several_specs_say_where_the_copy_is(store, tmp_path, capsys):
    from test_train_many import renamed_spec

    _with_learned(store)
    capsys.readouterr()
    assert main(["train", SPEC, str(renamed_spec(tmp_path, "box-two")), "--store", str(store), "--jobs", "1",
                 *FAST_TRAIN, "--root-sift"]) == 0
    err = capsys.readouterr().err
    assert f"quatrack train: warning: {SPEC}: the replaced model of {NAME!r}, with its 2 learned view(s), is kept in " \
           f"{store / L.BACKUP_DIR / NAME}" in err, err
    assert main(["train", SPEC, str(renamed_spec(tmp_path, "box-two")), "--store", str(store), "--jobs", "1",
                 *FAST_TRAIN]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith(f"trained {NAME!r}"))
    assert f", views learned while tracking: 2 carried back from {store / L.BACKUP_DIR}," in line, out
    assert _learned(store) == ["learned1", "learned2"]


def test_an_object_deleted_and_trained_afresh_does_not_get_the_copys_views(store, capsys):
    """``models delete`` then ``train``: a first training (maybe another object of that name and
    mesh), not a retraining: the copy's views are not carried back into it."""
    _with_learned(store)
    assert main(["train", SPEC, "--store", str(store), *FAST_TRAIN, "--root-sift"]) == 0
    assert main(["models", "delete", NAME, "--store", str(store)]) == 0
    assert main(["train", SPEC, "--store", str(store), *FAST_TRAIN]) == 0
    out = capsys.readouterr().out
    assert "carried back" not in out and _learned(store) == [], out


def test_deleting_the_object_says_where_its_copy_stays(store, capsys):
    """``models delete`` removes the model, not the copy a retraining kept (it is what restoring
    the copy by hand starts from): the deletion says where it stays and how to use or remove it."""
    _with_learned(store)
    assert main(["train", SPEC, "--store", str(store), *FAST_TRAIN, "--root-sift"]) == 0
    capsys.readouterr()
    assert main(["models", "delete", NAME, "--store", str(store)]) == 0
    out, err = capsys.readouterr()
    backup = store / L.BACKUP_DIR / NAME
    assert out == f"deleted {NAME!r} from {store}\n", out
    assert (f"quatrack models: note: the copy of {NAME!r}'s replaced model with 2 learned view(s) stays in {backup} "
            f"(a new training of {NAME!r} does not use it): put it back with mv {backup} {store / NAME}, "
            f"or remove it with rm -r {backup}\n") == err, err
    assert backup.is_dir() and not (store / NAME).exists()
    # done as it says: the model is back, with its learned views
    backup.rename(store / NAME)
    assert _learned(store) == ["learned1", "learned2"]


def test_deleting_an_object_without_a_copy_says_nothing_more(store, capsys):
    assert main(["models", "delete", NAME, "--store", str(store)]) == 0
    out, err = capsys.readouterr()
    assert out == f"deleted {NAME!r} from {store}\n" and err == "", (out, err)

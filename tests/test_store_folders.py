"""The store's folders that are not (readable) models, deleting, and what a broken model says.

A store operator's trial: an unreadable folder (``lost+found`` of another user's, mode 700, on a
server not run as root) stopped ``serve``, ``models list``, the store watch and ``GET /v1/objects``;
a folder without a manifest (a half-finished copy) was invisible yet blocked ``train
--no-overwrite``; ``models delete`` failed on a full disk and left the learned views' lock file;
a newer schema's model said "retrain it"; ``models list`` could not tell a script of BROKEN
models. The unreadable folder is simulated (``Path.is_file`` raising), so the tests need not run
as a user other than root.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import shutil
import tempfile
from pathlib import Path

import pytest

import quatrack.viewsets.store as S
from quatrack.cli import main
from quatrack.viewsets.errors import StoreError

NAME = "cookie-box"  # the conftest's store holds it (base_store, store: a test's own copy)
UNREADABLE = ("old copy", "private")  # (another user's, mode 700: "old copy" is no object's name)


@pytest.fixture
def unreadable(store, monkeypatch):
    """``store`` with two folders whose contents cannot be read (as mode 700 of another user's)."""
    for n in UNREADABLE:
        (store / n).mkdir()
    real = Path.is_file

    def is_file(self):
        if self.parent.name in UNREADABLE:
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real(self)

    monkeypatch.setattr(Path, "is_file", is_file)
    return store


def test_an_unreadable_folder_is_reported_not_fatal(unreadable):
    assert S.list_models(unreadable) == [NAME]
    broken = S.broken_folders(unreadable)
    assert sorted(broken) == sorted(UNREADABLE)
    assert all(why == "cannot be read (Permission denied)" for why in broken.values())


def test_models_list_marks_an_unreadable_object_folder_and_skips_another(unreadable, capsys):
    assert main(["models", "list", "--store", str(unreadable)]) == 0
    out, err = capsys.readouterr()
    rows = out.splitlines()
    assert rows[0].startswith(f"{NAME}\t") and "BROKEN" not in rows[0]
    assert rows[1] == "private\tBROKEN\tobject 'private': its folder cannot be read (Permission denied)"
    assert len(rows) == 2  # "old copy" is no object's name: said on stderr, one line
    assert err == f"quatrack models: skipped {unreadable / 'old copy'} (not an object's folder): it cannot be read (Permission denied)\n"
    assert "Traceback" not in err


def test_the_service_registry_serves_the_others_and_logs_each_folder_once(unreadable, caplog):
    from quatrack.service.registry import ModelRegistry

    registry = ModelRegistry(unreadable)
    with caplog.at_level(logging.WARNING, logger="quatrack.service"):
        registry.load_all()  # (serve's start, then the watcher's polls)
        registry.refresh()
        registry.refresh()
    assert registry.loaded() == [NAME] and registry.names() == [NAME]  # (GET /v1/objects lists names())
    skipped = [r.getMessage() for r in caplog.records if "skipping" in r.getMessage()]
    assert len(skipped) == 2 and all("cannot be read (Permission denied)" in m for m in skipped), skipped


def test_delete_on_a_full_disk_makes_no_folder(store, capsys, monkeypatch):
    """``mkdtemp(".del-…")`` failed with "No space left on device": the folder is renamed instead."""
    def full(*a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(tempfile, "mkdtemp", full)
    monkeypatch.setattr(os, "mkdir", full)
    assert main(["models", "delete", NAME, "--store", str(store)]) == 0
    assert capsys.readouterr().out == f"deleted {NAME!r} from {store}\n"
    assert S.list_models(store) == [] and [p.name for p in store.iterdir()] == []


def test_delete_from_a_read_only_store_is_one_line_and_keeps_the_model(store, capsys, monkeypatch):
    def read_only(src, dst, *a, **kw):
        raise OSError(errno.EROFS, "Read-only file system", str(src), None, str(dst))

    monkeypatch.setattr(os, "rename", read_only)
    assert main(["models", "delete", NAME, "--store", str(store)]) == 2
    err = capsys.readouterr().err
    assert err == f"quatrack models: error: cannot delete {NAME!r} from {store} (Read-only file system)\n"
    assert S.list_models(store) == [NAME]


def half_copy(store: Path, name: str = "half") -> Path:
    """A model folder without its manifest: a copy (``cp -r``, ``rsync``) cut short."""
    folder = store / name
    folder.mkdir()
    shutil.copy(store / NAME / S.ARRAYS, folder / S.ARRAYS)
    return folder


def test_a_folder_without_manifest_is_listed_broken_shown_and_deleted(store, capsys):
    half_copy(store)
    assert S.list_models(store) == [NAME]  # (not an object: locate --object all skips it, as before)
    assert main(["models", "list", "--store", str(store)]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert rows[1].startswith("half\tBROKEN\tobject 'half': its folder holds no manifest.json (a copy or a move cut short?)")
    assert main(["models", "show", "half", "--store", str(store)]) == 2
    err = capsys.readouterr().err
    assert "holds no manifest.json" in err and "quatrack models delete half" in err and err.count("\n") == 1
    assert main(["models", "delete", "half", "--store", str(store)]) == 0
    assert not (store / "half").exists() and S.list_models(store) == [NAME]
    assert not any(p.name.startswith(".del-") for p in store.iterdir())


def test_a_newer_schema_says_upgrade_and_a_missing_one_says_so(store):
    path = store / NAME / S.MANIFEST
    manifest = json.loads(path.read_text())
    path.write_text(json.dumps({**manifest, "schema_version": S.SCHEMA_VERSION + 1}))
    with pytest.raises(StoreError) as info:
        S.load_model(store, NAME)
    assert f"model schema {S.SCHEMA_VERSION + 1} was written by a newer quatrack" in str(info.value)
    assert "upgrade quatrack" in str(info.value) and " is not " not in str(info.value)
    del manifest["schema_version"]
    path.write_text(json.dumps(manifest))
    with pytest.raises(StoreError) as info:
        S.load_model(store, NAME)
    assert "None" not in str(info.value) and "has no schema_version" in str(info.value)


def test_delete_removes_the_learned_views_lock_file_unless_it_is_held(store, base_store):
    from quatrack.viewsets.learn import store_lock

    with store_lock(store, NAME):
        pass
    lock = S.learn_lock_path(store, NAME)
    assert lock.is_file()  # what a track --learn run leaves
    S.delete_model(store, NAME)
    assert not lock.exists() and list(store.iterdir()) == []

    shutil.copytree(base_store / NAME, store / NAME)
    lock.touch()
    fd = os.open(lock, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # a merge holds it: left to it
        S.delete_model(store, NAME)
        assert lock.is_file() and S.list_models(store) == []
    finally:
        os.close(fd)


def test_models_list_check_exits_1_on_a_broken_object(store, capsys):
    assert main(["models", "list", "--check", "--store", str(store)]) == 0
    (store / NAME / S.ARRAYS).write_bytes(b"PK\x03\x04 truncated")
    capsys.readouterr()
    assert main(["models", "list", "--store", str(store)]) == 0  # (without --check: as always)
    assert "\tBROKEN\t" in capsys.readouterr().out
    assert main(["models", "list", "--check", "--store", str(store)]) == 1
    out, err = capsys.readouterr()
    assert "\tBROKEN\t" in out and err == "quatrack models: 1 of 1 object(s) BROKEN (--check)\n"


def test_lost_found_and_dot_folders_are_not_listed(store, capsys):
    """A store on a volume of its own has a ``lost+found``, which ``models list`` told to "delete
    it or retrain it" (user report F8); dot-folders were skipped already."""
    for n in ("lost+found", ".cache"):
        (store / n).mkdir()
    assert S.broken_folders(store) == {} and S.list_models(store) == [NAME]
    assert main(["models", "list", "--store", str(store)]) == 0
    out, err = capsys.readouterr()
    assert len(out.splitlines()) == 1 and err == ""

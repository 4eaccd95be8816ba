"""The model store under changes users make while it is in use: a retraining or a deletion while
a ``track --learn`` run (or a service session) stores its views, a model folder renamed by hand,
a manifest whose SIFT settings this version cannot use. Built on the cookie box trained without
synthetic views (about 2 s); its learned views here are its trained view seen from new directions
(the store's rules, not recognition, are under test)."""

from __future__ import annotations

import dataclasses
import json
import shutil
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from quatrack.cli import main
from quatrack.tracking.pose import Pose
from quatrack.viewsets import learn as L
from quatrack.viewsets import store as S

from conftest import EXAMPLE  # (base_store and store: conftest's fixtures)

NAME = "cookie-box"


def turned_views(model, degrees=(60.0, 120.0)) -> list:
    """The model's first view as seen from cameras turned about the object's centre: new directions."""
    vs, c = model.viewsets[0], model.mesh.centre
    out = []
    for k, deg in enumerate(degrees):
        R = cv2.Rodrigues(np.array([0.0, np.radians(deg), 0.0]))[0]
        pose = Pose.from_matrix(vs.pose.R @ R, vs.pose.R @ (c - R @ c) + vs.pose.t)  # turned about the centre
        out.append(dataclasses.replace(vs, label=f"learned{k + 1}", learned=True, pose=pose))
    assert all(L.is_new_direction(v.pose, c, model.viewsets) for v in out)
    return out


def _during_merge(monkeypatch, action):
    """Run ``action`` in another thread right after merge_learned has read the stored model, and
    give it a moment to finish before the merge writes (it finishes unless a lock holds it back)."""
    real = L.load_model
    threads = []

    def load_then_act(store, name):
        model = real(store, name)
        t = threading.Thread(target=action)
        t.start()
        threads.append(t)
        t.join(timeout=1.5)  # (held back by the object's lock: the merge goes on and writes first)
        return model

    monkeypatch.setattr(L, "load_model", load_then_act)
    return threads


def test_a_retraining_while_views_are_stored_is_not_undone(store, monkeypatch):
    """A model retrained while a `track --learn` run stored its views: the merge wrote the model
    it had read, with its views, over the retrained one (the retraining was lost, silently)."""
    model = S.load_model(store, NAME)
    retrained = dataclasses.replace(model, manifest={**model.manifest, "created": "the retraining"})
    threads = _during_merge(monkeypatch, lambda: S.save_model(store, retrained))
    _, added, _ = L.merge_learned(store, NAME, turned_views(model), model.mesh)
    for t in threads:
        t.join()
    assert added == 2
    back = S.load_model(store, NAME)
    assert back.manifest["created"] == "the retraining"  # the later write stands, whole
    assert not [p for p in store.iterdir() if p.name.startswith((".tmp-", ".old-"))]


def test_a_model_deleted_while_views_are_stored_stays_deleted(store, monkeypatch):
    model = S.load_model(store, NAME)
    threads = _during_merge(monkeypatch, lambda: S.delete_model(store, NAME))
    L.merge_learned(store, NAME, turned_views(model), model.mesh)
    for t in threads:
        t.join()
    assert S.list_models(store) == []  # (it came back with the merge's write)


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    path = tmp_path_factory.mktemp("frame") / "frame.png"
    ok, img = cv2.VideoCapture(str(EXAMPLE / "box.mp4")).read()
    assert ok and cv2.imwrite(str(path), img)
    return path


def _copy(store: Path, name: str, edit) -> None:
    shutil.copytree(store / NAME, store / name)
    m = json.loads((store / name / S.MANIFEST).read_text())
    m["name"] = name
    edit(m)
    (store / name / S.MANIFEST).write_text(json.dumps(m))


@pytest.mark.parametrize("edit", [lambda m: m["parameters"]["viewsets"].update(future_knob=3),
                                  lambda m: m["parameters"]["viewsets"].update(max_features="1500"),
                                  lambda m: m["parameters"]["viewsets"].update(root_sift=None)],
                         ids=["unknown-setting", "string", "null"])
def test_sift_settings_this_version_cannot_use_make_that_model_broken_not_locate(store, frame, capsys, edit):
    """A model whose manifest holds SIFT settings this version cannot describe images with (a
    newer version's setting, a hand edit) loaded, then failed inside every query with a TypeError
    traceback — `locate --object all` too, for every object of the store."""
    _copy(store, "odd-box", edit)
    cam = str(EXAMPLE / "camera.json")
    with pytest.raises(S.StoreError, match="'odd-box'"):
        S.load_model(store, "odd-box")
    assert main(["locate", "--object", "odd-box", "--camera", cam, str(frame), "--store", str(store)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "'odd-box'" in err and "Traceback" not in err, err
    assert main(["locate", "--object", "all", "--camera", cam, str(frame), "--store", str(store), "--json"]) == 0
    out, err = capsys.readouterr()
    assert err.strip().startswith("quatrack locate: warning: object 'odd-box': ") and err.count("\n") == 1, err
    line = json.loads(out)
    assert [o["object"] for o in line["objects"]] == [NAME]  # the others are still searched
    assert main(["models", "list", "--store", str(store)]) == 0
    assert "odd-box\tBROKEN\t" in capsys.readouterr().out


def test_a_model_folder_renamed_by_hand_is_that_object(store, frame, capsys):
    """`mv STORE/cookie-box STORE/my-box` (the store has no rename command): the model was
    'corrupt ... (manifest names object 'cookie-box'); retrain it' everywhere."""
    (store / NAME).rename(store / "my-box")
    shutil.copytree(store / "my-box", store / "my-box-copy")
    model = S.load_model(store, "my-box")
    assert model.name == "my-box" and model.manifest["name"] == "my-box"
    assert main(["models", "list", "--store", str(store)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("my-box\t1 viewsets") and "my-box-copy\t1 viewsets" in out and "BROKEN" not in out, out
    cam = str(EXAMPLE / "camera.json")
    assert main(["locate", "--object", "my-box", "--camera", cam, str(frame), "--store", str(store), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["object"] == "my-box"
    # the next write (views learned into it) records the new name
    L.merge_learned(store, "my-box", turned_views(model), model.mesh)
    assert json.loads((store / "my-box" / S.MANIFEST).read_text())["name"] == "my-box"
    assert S.load_model(store, "my-box").name == "my-box"


@pytest.mark.parametrize("where", ["store", "model"])
def test_track_learn_into_a_store_it_cannot_write_is_refused_before_the_first_frame(store, tmp_path, capsys,
                                                                                    monkeypatch, where):
    """A read-only store (or model folder): the whole walk was tracked, then the learned views
    were lost at the end ('--learn: the 3 learned view(s) were not saved ...')."""
    import os

    from quatrack.recognition.video import Tracker

    ro = store if where == "store" else store / NAME
    real, real_step = os.access, Tracker.step
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == ro else real(p, mode, **kw))  # (root ignores modes)
    monkeypatch.setattr(Tracker, "step", lambda *a, **kw: pytest.fail("tracked a frame"))
    out = tmp_path / "poses.csv"
    args = ["track", "--object", NAME, "--camera", str(EXAMPLE / "camera.json"), "--video", str(EXAMPLE / "box.mp4"),
            "--max-frames", "2", "--out", str(out), "--store", str(store), "--quiet"]
    assert main([*args, "--learn"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"cannot store learned views in {ro} (" in err and "without --learn" in err, err
    assert not out.exists()
    monkeypatch.setattr(Tracker, "step", real_step)
    assert main(args) == 0  # without --learn the store is only read
    assert out.exists()


def test_a_model_deleted_during_a_learning_run_says_the_views_were_not_saved(store, tmp_path, capsys, monkeypatch):
    """The run ended 'error: no object named ...': nothing said the learned views were lost."""
    from quatrack.recognition.video import Tracker

    views = turned_views(S.load_model(store, NAME))
    real_step, calls = Tracker.step, []

    def step(self, image, t):
        calls.append(t)
        self.learned = list(views)
        if len(calls) == 2:
            S.delete_model(store, NAME)
        return real_step(self, image, t)

    monkeypatch.setattr(Tracker, "step", step)
    out = tmp_path / "poses.csv"
    assert main(["track", "--object", NAME, "--camera", str(EXAMPLE / "camera.json"), "--video", str(EXAMPLE / "box.mp4"),
                 "--max-frames", "3", "--out", str(out), "--store", str(store), "--quiet", "--learn"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"no object named '{NAME}'" in err and "the 2 learned view(s) were not saved" in err, err
    assert len(out.read_text().splitlines()) == 4  # the poses are kept


def test_the_service_does_not_learn_into_a_store_it_cannot_write(store, monkeypatch, caplog):
    """QUATRACK_LEARN_VIEWS with a read-only store: sessions learned, told the client
    '"learns": true', and every session's views were refused at its end."""
    import logging
    import os

    from quatrack.service import learning
    from quatrack.service.settings import Settings

    settings = Settings(store=store, learn_views=(NAME,))
    assert learning.learns(settings, NAME) and not learning.learns(settings, "other")
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == store else real(p, mode, **kw))
    with caplog.at_level(logging.WARNING, logger="quatrack.service"):
        assert not learning.learns(settings, NAME) and not learning.learns(settings, NAME)
    said = [r.getMessage() for r in caplog.records if "learn nothing" in r.getMessage()]
    assert len(said) == 1 and f"cannot store learned views in {store}" in said[0], said  # once, not per session


def test_a_model_holding_the_most_learned_views_says_so(store, tmp_path, capsys):
    """The line said 'none seen from a new direction with a confident pose' whatever the walk
    showed, once the model held its 24 learned views."""
    from quatrack.testing import zoo as Z

    model = S.load_model(store, NAME)
    vs, c = model.viewsets[0], model.mesh.centre
    dist = np.linalg.norm(vs.pose.inverse().t - c)
    k = np.arange(60) + 0.5
    dirs = np.stack([np.cos(np.pi * (1 + 5 ** 0.5) * k) * np.sin(np.arccos(1 - 2 * k / 60)),
                     np.sin(np.pi * (1 + 5 ** 0.5) * k) * np.sin(np.arccos(1 - 2 * k / 60)), 1 - 2 * k / 60], 1)
    views = [dataclasses.replace(vs, learned=True, pose=Z.look_at(c + dist * d, c, up=(1.0, 0.0, 0.0) if abs(d[2]) > 0.9
                                                                                        else (0.0, 0.0, 1.0)))
             for d in dirs]
    full = L.with_learned(model, views)
    assert sum(v.learned for v in full.viewsets) == L.MAX_LEARNED
    S.save_model(store, full)
    assert main(["track", "--object", NAME, "--camera", str(EXAMPLE / "camera.json"), "--video", str(EXAMPLE / "box.mp4"),
                 "--max-frames", "2", "--out", str(tmp_path / "poses.csv"), "--store", str(store), "--quiet",
                 "--learn"]) == 0
    err = capsys.readouterr().err
    assert f"learned no new views (the model holds {L.MAX_LEARNED} learned views, the most it keeps; " in err, err


def test_a_store_shared_by_a_group_takes_every_members_learned_views(store, monkeypatch):
    """The first merge created .learn-NAME.lock as 0644 whatever the umask, and another member
    of the group sharing the store (a server run by a service user, a colleague's track --learn)
    could not open it for writing: 'the N learned view(s) were not saved ...: Permission denied'."""
    import os

    model = S.load_model(store, NAME)
    views = turned_views(model)
    old = os.umask(0o002)
    try:
        L.merge_learned(store, NAME, views[:1], model.mesh)
    finally:
        os.umask(old)
    lock = store / f".learn-{NAME}.lock"
    assert lock.stat().st_mode & 0o777 == 0o664  # (the group may open it as the models' folders)
    real = os.open

    def not_ours(path, flags, *a, **kw):  # (root opens anything: the other user's 0644 file, simulated)
        if str(path) == str(lock) and flags & (os.O_WRONLY | os.O_RDWR):
            raise PermissionError(13, "Permission denied", str(path))
        return real(path, flags, *a, **kw)

    monkeypatch.setattr(os, "open", not_ours)
    _, added, total = L.merge_learned(store, NAME, views[1:], model.mesh)
    assert (added, total) == (1, 2)

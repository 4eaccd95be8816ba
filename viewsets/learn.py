"""Views learned while tracking (issue 12, item 3): new viewsets from video frames at tracked poses.

A model trained from one photo knows only the sides that photo shows: recognition (and so the
tracker's re-initialisation after a loss) cannot find the object from any other side. While
the tracker follows the object round to those sides with a confident pose, the frame's SIFT
keypoints on the object, lifted to 3-D by casting their rays onto the mesh at that pose
(:func:`~quatrack.viewsets.viewset.build_viewset`, the training path: same SIFT parameters,
same ray caster), make a viewset like a trained one, flagged ``learned``.

Rules kept here, so that the tracker, the CLI and the service agree:

- **direction**: a view is new only when the direction it sees the object from (object frame,
  from the centre to the camera; roll ignored, SIFT is blind to it) is at least
  ``min_angle_deg`` from that of every viewset already in the model, trained or learned
  (:func:`view_angles_deg`);
- **bound**: at most ``max_learned`` learned viewsets per model (the FLANN index and each
  re-initialisation grow with them);
- **well-conditioned depth**: a keypoint on a face seen at a grazing angle has a badly
  conditioned lifted depth (an error δ across the ray moves the point δ/cos along the face),
  so learned views lift only points whose ray meets the face with ``|cos| ≥ min_cos``.

:func:`with_learned` merges learned viewsets into a model (a new model; the input untouched);
:func:`save_learned` merges them into the stored model under a lock and writes it atomically
(:func:`~quatrack.viewsets.store.save_model`), so concurrent writers (two service sessions of
one object, a CLI run) never lose each other's views nor leave a half-written model. The store's
format is unchanged (schema 1): a learned viewset is stored like a trained one, with
``"learned": true`` in its manifest entry, which older code ignores. A retraining of the object
(:func:`save_trained`) keeps its learned views when they still fit the new model — the same mesh,
descriptors of the same kind — and says how many it dropped otherwise (:func:`carry_learned`).

The model's RFCH histogram (the window search's colour co-occurrence statistics) is trained on
the registered photos' object pixels; a learned view brings its frame's co-occurrence counts
(labelled with the model's own cluster centres), averaged in with equal weight per view:
``H ← (n·H + Σ hᵢ) / (n + k)`` for ``n`` views already in it and ``k`` new ones, so the window
search also knows the colours of the sides the photos never showed. The window sizes it tries
widen to the learned views' boxes (carried to the training camera's width).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shlex
import shutil
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose

from .errors import StoreError
from .features import RUN_TIME_STRETCH
from .mesh import Mesh
from .render import RenderBuffers, footprint, render_window
from .rfch import RFCHModel, cooccurrence, descriptor_planes, label_planes
from .store import MANIFEST, ObjectModel, learn_lock_path, learned_count, load_model, model_lock, model_path, save_model
from .viewset import Viewset, ViewsetParams, build_viewset

MAX_LEARNED = 24  # learned viewsets per model at most
MIN_ANGLE_DEG = 25.0  # a learned view sees the object from at least this far from every other view
MIN_COS = 0.4  # learned points: the ray meets the face within ~66° of its normal


def view_angles_deg(pose: Pose, centre: np.ndarray, viewsets: list[Viewset]) -> np.ndarray:
    """Angle (degrees) between the direction ``pose`` sees the object from and each viewset's."""
    if not viewsets:
        return np.zeros(0)
    a = pose.viewing_direction(centre)
    b = np.array([vs.pose.viewing_direction(centre) for vs in viewsets])
    return np.degrees(np.arccos(np.clip(b @ a, -1.0, 1.0)))


def is_new_direction(pose: Pose, centre: np.ndarray, viewsets: list[Viewset], min_angle_deg: float = MIN_ANGLE_DEG) -> bool:
    """True when ``pose`` sees the object from at least ``min_angle_deg`` away from every viewset."""
    ang = view_angles_deg(pose, centre, viewsets)
    return bool(len(ang) == 0 or ang.min() >= min_angle_deg)


def learned_viewset(label: str, image: np.ndarray, feature_mask: np.ndarray, camera: PinholeCamera, pose: Pose,
                    mesh: Mesh, params: ViewsetParams, min_cos: float = MIN_COS,
                    rfch: RFCHModel | None = None, zoom: float = 1.0) -> Viewset:
    """The viewset of one video frame at a tracked ``pose``: SIFT inside ``feature_mask`` (the
    visible faces, away from the silhouette), described with the model's ``params``, each
    keypoint's ray cast onto the mesh (:func:`~quatrack.viewsets.viewset.build_viewset`), only
    where it meets the face with ``|cos| ≥ min_cos``. With ``rfch``, the frame's object pixels'
    label co-occurrence (:attr:`Viewset.cooccurrence`) comes along for the window search, its
    scales and pair distance ``zoom`` frame pixels per training pixel, as the window search
    describes this camera's frames (:func:`~.rfch.texture_zoom`).

    The work is done on the object's box (plus a margin for SIFT's and the RFCH's
    neighbourhoods) seen by the same camera with its principal point shifted — the same rays,
    so the same lifted points — and the keypoints are returned in the frame's pixels. Only that
    box (with the margin) is rendered (:func:`~.render.render_window` over the mesh's
    :func:`~.render.footprint`): the same buffers there as the whole frame's render."""
    empty = Viewset(label, -1, False, camera, pose, np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32),
                    np.zeros((0, 3)), (0, 0, 0, 0), learned=True)
    pair_d = max(1, int(round(rfch.distance * zoom))) if rfch is not None else 0
    m = 16 + (int(np.ceil(3 * max(rfch.scales) * zoom)) + pair_d if rfch is not None else 0)
    win = footprint(mesh, camera, pose, m)
    if win is None:
        return empty
    w, h = int(camera.width), int(camera.height)
    buffers = render_window(mesh, camera, pose, win)
    obj = buffers.face >= 0
    if not obj.any():
        return empty
    ys, xs = np.nonzero(obj)
    xs, ys = xs + win[0], ys + win[1]
    x0, y0 = max(int(xs.min()) - m, 0), max(int(ys.min()) - m, 0)
    x1, y1 = min(int(xs.max()) + m + 1, w), min(int(ys.max()) + m + 1, h)
    crop = np.ascontiguousarray(image[y0:y1, x0:x1])
    cam = camera.cropped(x0, y0, x1, y1)
    rows, cols = slice(y0 - win[1], y1 - win[1]), slice(x0 - win[0], x1 - win[0])  # (inside the window)
    buf = RenderBuffers(buffers.depth[rows, cols], buffers.face[rows, cols])
    mask = np.where((np.asarray(feature_mask)[y0:y1, x0:x1] > 0) & (buf.face >= 0), 255, 0).astype(np.uint8)
    p = dataclasses.replace(params, min_cos=max(params.min_cos, float(min_cos)))
    vs = build_viewset(label, -1, False, crop, mask, cam, pose, mesh, buf, p, RUN_TIME_STRETCH)
    if len(vs) == 0:
        return empty
    co = None
    if rfch is not None:
        # the descriptors of the whole frame (their intensity is normalised over the image, as
        # in training and in the window search), labelled only on the object: only its pixels pair up
        planes = descriptor_planes(image, tuple(float(sig) * zoom for sig in rfch.scales))[:, y0:y1, x0:x1]
        inside = buf.face >= 0
        labels = np.full(inside.shape, -1, np.int32)
        labels[inside] = label_planes(planes[:, inside][:, :, None], rfch.centres, rfch.desc_mean, rfch.desc_std).ravel()
        co = cooccurrence(labels, buf.mask, len(rfch.centres), pair_d)
    return dataclasses.replace(vs.uncropped(camera, x0, y0), learned=True, cooccurrence=co)


def _rfch_with(model: ObjectModel, added: list[Viewset]) -> RFCHModel:
    """The model's RFCH with the added views' co-occurrence averaged in and their boxes in the
    window sizes (see the module)."""
    rfch = model.rfch
    hists = [vs.cooccurrence for vs in added
             if vs.cooccurrence is not None and vs.cooccurrence.shape == rfch.histogram.shape and vs.cooccurrence.sum() > 0]
    if hists:
        n = int(model.manifest.get("rfch_views", model.manifest.get("training_summary", {}).get("views", 1)) or 1)
        H = (n * rfch.histogram + sum(h / h.sum() for h in hists)) / (n + len(hists))
        rfch = dataclasses.replace(rfch, histogram=H / max(H.sum(), 1e-12))
    tw = model.training_width
    if tw:
        lo, hi = np.array(rfch.size_min, float), np.array(rfch.size_max, float)
        for vs in added:
            if vs.camera.width and vs.bbox[2] > 0 and vs.bbox[3] > 0:
                wh = np.array(vs.bbox[2:], float) * tw / vs.camera.width
                lo, hi = np.minimum(lo, wh), np.maximum(hi, wh)
        rfch = dataclasses.replace(rfch, size_min=tuple(int(np.floor(x)) for x in lo),
                                   size_max=tuple(int(np.ceil(x)) for x in hi))
    return rfch


def with_learned(model: ObjectModel, viewsets, max_learned: int = MAX_LEARNED,
                 min_angle_deg: float = MIN_ANGLE_DEG) -> ObjectModel:
    """A new model whose viewsets are ``model``'s (trained and already learned) plus those of
    ``viewsets`` that see the object from a new direction (:func:`is_new_direction`, against
    every viewset kept so far), in order, while fewer than ``max_learned`` are learned. Added
    views are labelled ``learnedK`` (K continues the model's numbering); their co-occurrence
    joins the RFCH histogram. ``model`` itself is not changed. Same model back if none is new."""
    kept = list(model.viewsets)
    centre = model.mesh.centre
    n_learned = sum(vs.learned for vs in kept)
    used = {vs.label for vs in kept}
    added = []
    for vs in viewsets:
        if n_learned >= max_learned:
            break
        if len(vs) == 0 or not is_new_direction(vs.pose, centre, kept, min_angle_deg):
            continue
        k = n_learned + 1
        while f"learned{k}" in used:
            k += 1
        vs = dataclasses.replace(vs, label=f"learned{k}", learned=True)
        used.add(vs.label)
        kept.append(vs)
        added.append(vs)
        n_learned += 1
    if not added:
        return model
    rfch = _rfch_with(model, added)
    stored = [dataclasses.replace(vs, cooccurrence=None) for vs in kept]  # folded into the RFCH now
    manifest = dict(model.manifest)
    n_views = int(manifest.get("rfch_views", manifest.get("training_summary", {}).get("views", 1)) or 1)
    manifest["rfch_views"] = n_views + sum(vs.cooccurrence is not None for vs in added)
    manifest["learned_viewsets"] = n_learned
    manifest["learned_updated"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    return dataclasses.replace(model, rfch=rfch, viewsets=stored, manifest=manifest)


@contextlib.contextmanager
def store_lock(store: str | Path, name: str):
    """The lock a merge of learned views holds (see :func:`merge_learned`): an exclusive ``flock``
    on ``store/.learn-NAME.lock`` — what older versions' merges take, so that they and this one
    still exclude each other — and the store's own :func:`~.store.model_lock`, which trainings and
    deletions take too."""
    store = Path(store)
    store.mkdir(parents=True, exist_ok=True)
    path = learn_lock_path(store, name)
    try:  # (0o666 less the umask, as the models' folders: a store shared by a group stays usable by all)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except PermissionError:  # another user's lock file, not writable to us: flock needs only an open file
        fd = os.open(path, os.O_RDONLY)
    try:
        try:
            import fcntl

            fcntl.flock(fd, fcntl.LOCK_EX)
        except (ImportError, OSError):  # (not POSIX, or a file system that cannot lock it: the write is still atomic)
            pass
        with model_lock(store, name):
            yield
    finally:
        os.close(fd)  # closing releases the flock


def why_none_learned(model: ObjectModel, max_learned: int = MAX_LEARNED) -> str:
    """Why a run learned no view of ``model`` (the CLI's line): the bound reached, else no
    confident frame from a new direction (that one said so, too, when the bound was the cause)."""
    n = sum(vs.learned for vs in model.viewsets)
    if n >= max_learned:
        return f"the model holds {n} learned views, the most it keeps; retrain it with --drop-learned to learn afresh"
    return "none seen from a new direction with a confident pose"


def check_can_store(store: str | Path, name: str) -> None:
    """Raise :class:`StoreError` when the stored model ``name`` cannot take learned views: its
    store or its folder is read-only to this process (a read-only mount, another user's store).
    ``track --learn`` asks before its first frame — it found out at the end, after the whole
    walk, and the views were lost."""
    store = Path(store)
    for folder in (store, model_path(store, name)):  # (the store gains a new folder; the old one is moved away)
        if folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):
            ro = hasattr(os, "statvfs") and bool(os.statvfs(folder).f_flag & getattr(os, "ST_RDONLY", 1))
            raise StoreError(f"--learn: cannot store learned views in {folder} "
                             f"({'read-only file system' if ro else 'permission denied'}): "
                             f"track without --learn, or copy the model to a store you can write in")


def merge_learned(store: str | Path, name: str, viewsets, mesh: Mesh | None = None, max_learned: int = MAX_LEARNED,
                  min_angle_deg: float = MIN_ANGLE_DEG, learned_on: ObjectModel | None = None) -> tuple[Path, int, int]:
    """Merge ``viewsets`` into the *stored* model ``name``: :func:`merge_learned_views`, with the
    number of views added instead of the views. Returns ``(folder, views added, learned views in
    the model)``."""
    folder, added, total = merge_learned_views(store, name, viewsets, mesh, max_learned, min_angle_deg, learned_on)
    return folder, len(added), total


def merge_learned_views(store: str | Path, name: str, viewsets, mesh: Mesh | None = None,
                        max_learned: int = MAX_LEARNED, min_angle_deg: float = MIN_ANGLE_DEG,
                        learned_on: ObjectModel | None = None) -> tuple[Path, list[Viewset], int]:
    """Merge ``viewsets`` into the *stored* model ``name`` (re-read under :func:`store_lock`, so a
    concurrent writer's views are kept) and write it atomically. Returns ``(folder, the views
    added as stored, learned views in the model)``; nothing is written when none is new. Raises
    :class:`StoreError` if the object is missing or its mesh is not ``mesh``, the one they were
    learned on (the object was retrained on another mesh meanwhile), or — given ``learned_on``,
    the model the tracker ran — if the stored model describes its views otherwise (its SIFT
    settings, e.g. RootSIFT, or its RFCH colour clusters differ: retrained meanwhile; such views
    would never match, and their colours would be counted in the wrong clusters)."""
    viewsets = list(viewsets)
    with store_lock(store, name):
        try:
            model = load_model(store, name)
        except StoreError as exc:  # (deleted or renamed meanwhile, broken: the message said nothing of the views)
            if not viewsets:
                raise
            raise StoreError(f"{exc}; the {len(viewsets)} learned view(s) were not saved") from None
        folder = model_path(Path(store), name)
        # (the views were lifted on the mesh the tracker ran on: the stored one, or its run-time
        # decimation, Mesh.run_time, which lies on it; the stored model keeps its full mesh)
        if viewsets and mesh is not None and not (same_mesh(mesh, model.mesh) or same_mesh(mesh, model.mesh.run_time)):
            raise StoreError(f"object {name!r} in {store} has another mesh than the views were learned on "
                             "(retrained meanwhile?); the learned views were not saved")
        if viewsets and learned_on is not None and not same_description(learned_on, model):
            raise StoreError(f"object {name!r} in {store} was retrained with other feature settings than the views "
                             "were learned with (SIFT or RFCH); the learned views were not saved")
        if not viewsets:
            return folder, [], sum(vs.learned for vs in model.viewsets)
        merged = with_learned(model, viewsets, max_learned, min_angle_deg)
        added = list(merged.viewsets[len(model.viewsets):])  # (with_learned appends them, in order)
        if added:
            save_model(store, merged, overwrite=True, locked=True)
        return folder, added, sum(vs.learned for vs in merged.viewsets)


#: a learned view's point is *new* when it lies farther than this share of the mesh's extent (its
#: bounding box's diagonal) from every point of the views the model held before: nearer, it
#: describes texture those views already hold. A 12 × 8 × 6 cm box textured on two faces only,
#: walked round with ``--learn``: 7 views of 296–472 points, of which 10–18 new (its plain sides
#: give none; the rest lie on the two faces again); a frustum textured on every face: 7 views of
#: 96–396 points, 61–247 new (user report, finding 7)
NEW_POINT_SHARE = 0.02


def new_points(viewsets, known, extent: float, share: float = NEW_POINT_SHARE) -> list[int]:
    """For each of ``viewsets``, how many of its 3-D points are new: farther than ``share`` ×
    ``extent`` from every 3-D point of the viewsets ``known`` (all of them new if none is known)."""
    from scipy.spatial import cKDTree

    known = [np.asarray(vs.points3d, float).reshape(-1, 3) for vs in known]
    points = np.concatenate(known) if known else np.zeros((0, 3))
    if not len(points):
        return [len(vs.points3d) for vs in viewsets]
    tree = cKDTree(points)
    return [int(np.count_nonzero(tree.query(np.asarray(vs.points3d, float).reshape(-1, 3))[0] > share * extent))
            if len(vs.points3d) else 0 for vs in viewsets]


@dataclasses.dataclass(frozen=True)
class Retrained:
    """What :func:`save_trained` did with the views the replaced model had learned while tracking:
    ``kept`` carried into the new model, ``dropped`` not, and ``why`` (None when none was dropped);
    ``backup``: where the replaced model was copied with the views it dropped unasked (None when
    none was), and ``restored``: views carried back from such a copy (:data:`BACKUP_DIR`)."""

    path: Path
    kept: int = 0
    dropped: int = 0
    why: str | None = None
    backup: Path | None = None
    restored: int = 0

    def note(self, name: str, store: str | Path) -> str | None:
        """The warning a retraining owes its user when it dropped learned views it was not told
        to drop (None otherwise): how many, why, and how many were kept."""
        if not self.dropped or self.why == DROP_ASKED:
            return None
        return (f"{name!r} in {store} held {self.kept + self.dropped} view(s) learned while tracking; "
                f"{self.dropped} dropped: {self.why}" + (f"; {self.kept} kept" if self.kept else "")
                + " (track --learn learns them again)")

    def backup_note(self, name: str) -> str | None:
        """Where the dropped views are kept and how to get them back (None when none was backed up)."""
        if self.backup is None:
            return None
        store = self.backup.parent.parent
        return (f"the replaced model of {name!r}, with its {self.dropped} learned view(s), is kept in {self.backup}: "
                f"train {name!r} again with its former mesh and settings (e.g. without --root-sift) and they are "
                f"carried back; or put it back in place: quatrack models delete {name} --store {shlex.quote(str(store))}"
                f" && {restore_command(store, name)}")


#: the folder of the store (itself a store: ``quatrack models list --store STORE/.learned-backup``)
#: where a retraining copies the model it replaces when it drops learned views unasked (another mesh,
#: another kind of descriptors): a walk-round is expensive to repeat. One copy per object, the last.
BACKUP_DIR = ".learned-backup"


def backup_path(store: str | Path, name: str) -> Path:
    """The folder of ``name``'s backup copy in ``store`` (it may not exist): ``STORE/.learned-backup/NAME``."""
    return model_path(Path(store) / BACKUP_DIR, name)


def backup_left(store: str | Path, name: str) -> str | None:
    """What ``models delete NAME`` leaves behind: the copy of a replaced model with its learned
    views (:func:`backup_path`), which a first training after the deletion does not carry back
    (:func:`save_trained`) — where it is, how many views it holds and how to use or remove it;
    None when there is no copy. Why: deleting the object said nothing of it, and the copy stayed
    in the store unseen (a folder starting with ``.``)."""
    backup = backup_path(store, name)
    if not (backup / MANIFEST).is_file():
        return None
    n = learned_count(backup.parent, name)
    return (f"the copy of {name!r}'s replaced model with {n} learned view(s) stays in {backup} "
            f"(a new training of {name!r} does not use it): put it back with "
            f"{restore_command(store, name)}, or remove it with rm -r {shlex.quote(str(backup))}")


def restore_command(store: str | Path, name: str) -> str:
    """The shell command that puts ``name``'s backup copy (:func:`backup_path`) back in its place
    in ``store`` (once the model there is deleted): one spelling for every message that gives it.

    >>> restore_command("/data/my store", "mug")
    "mv '/data/my store/.learned-backup/mug' '/data/my store/mug'"
    """
    return f"mv {shlex.quote(str(backup_path(store, name)))} {shlex.quote(str(model_path(store, name)))}"


#: :attr:`Retrained.why` when the caller asked for the learned views to go (``train --drop-learned``)
DROP_ASKED = "--drop-learned"


def carry_learned(stored: ObjectModel | None, model: ObjectModel) -> tuple[ObjectModel, int, str | None]:
    """``model`` (a new training of ``stored``'s object) with ``stored``'s learned views, when they
    fit it: the same mesh (their 3-D points were lifted onto the old one: another mesh, even one
    scaled or moved, puts them off the object) and descriptors of the same kind (SIFT or RootSIFT:
    one does not match the other). Other settings — SIFT's threshold and keypoint count, the RFCH
    clusters, the photos — change which keypoints a view holds and the window search's colours,
    not what a learned view's points are, so its views stay. Returns ``(model, views carried,
    why none was)``. All of them are carried, with their labels and boxes (which widen the RFCH
    window sizes as when they were learned); their colours, folded into the old model's RFCH
    histogram, are not: the new histogram is the photos' alone."""
    learned = [vs for vs in (stored.viewsets if stored is not None else []) if vs.learned]
    if not learned:
        return model, 0, None
    if not same_mesh(stored.mesh, model.mesh):
        return model, 0, "the mesh changed (their 3-D points lie on the old one)"
    from .viewset import params_from_manifest

    if params_from_manifest(stored.manifest).root_sift != params_from_manifest(model.manifest).root_sift:
        return model, 0, "the descriptors changed (--root-sift): they would not match"
    merged = with_learned(model, learned, max_learned=max(MAX_LEARNED, len(learned)), min_angle_deg=0.0)
    if merged is not model and "learned_updated" in stored.manifest:  # (when views were last learned: not now)
        merged.manifest["learned_updated"] = stored.manifest["learned_updated"]
    return merged, len(merged.viewsets) - len(model.viewsets), None


def save_trained(store: str | Path, model: ObjectModel, overwrite: bool = True, keep_learned: bool = True) -> Retrained:
    """Save a new training ``model`` of an object (:func:`~.store.save_model`, atomic) keeping the
    views the stored model learned while tracking where they fit it (:func:`carry_learned`;
    ``keep_learned=False``: none). The stored model is read and replaced under the store's lock,
    which merges of learned views hold from their read to their write (:func:`merge_learned`,
    :func:`~.store.model_lock`; no lock file is added to the store), so views a ``track --learn`` run stores meanwhile
    are kept or reported too, never lost between the read and the write. A stored model that
    cannot be read (broken) is replaced, as before, with nothing to carry.

    Learned views dropped unasked (another mesh, another kind of descriptors) are not lost: the
    replaced model is first copied to :func:`backup_path` (``STORE/.learned-backup/NAME``, the
    object's last such copy), and a later retraining that keeps none from the stored model carries
    them back from there when they fit it (trained again with the old mesh and settings: the copy
    is then removed) — a retraining, not a first training after ``models delete``.
    ``keep_learned=False`` (``--drop-learned``) removes the copy too."""
    store = Path(store)
    with model_lock(store, model.name):
        n = learned_count(store, model.name)
        stored = None
        if n and keep_learned:
            try:
                stored = load_model(store, model.name)
            except StoreError:
                stored = None
        model, kept, why = carry_learned(stored, model) if stored is not None else (model, 0, None)
        if n and not keep_learned:
            why = DROP_ASKED
        elif n and stored is None:
            why = "the stored model cannot be read"
        backup, restored = backup_path(store, model.name), 0
        # (only over a stored model: an object deleted and trained afresh — maybe another object
        # of that name and mesh — does not get the old one's views back)
        replacing = (model_path(store, model.name) / MANIFEST).is_file()
        if keep_learned and not kept and replacing and (backup / MANIFEST).is_file():
            try:
                model, restored, _ = carry_learned(load_model(backup.parent, model.name), model)
            except StoreError:  # (a broken copy: nothing to carry back, left for the user to look at)
                restored = 0
        saved_backup = None
        if stored is not None and n - kept and why != DROP_ASKED:  # (before the stored model is replaced)
            saved_backup = save_model(backup.parent, stored, overwrite=True, locked=True)
        elif (restored or not keep_learned) and backup.is_dir():
            shutil.rmtree(backup, ignore_errors=True)
        path = save_model(store, model, overwrite=overwrite, locked=True)
    return Retrained(path, kept, n - kept, why if n - kept else None, saved_backup, restored)


def save_learned(store: str | Path, name: str, viewsets, mesh: Mesh | None = None) -> Path:
    """Write the object's stored model with ``viewsets`` learned (:func:`merge_learned`) atomically
    into ``store``; returns its folder."""
    return merge_learned(store, name, viewsets, mesh)[0]


def same_description(a: ObjectModel, b: ObjectModel) -> bool:
    """The same SIFT settings (the manifests' viewset parameters) and the same RFCH clusters: views
    described for one are views of the other."""
    from .viewset import params_from_manifest

    return params_from_manifest(a.manifest) == params_from_manifest(b.manifest) \
        and np.array_equal(a.rfch.centres, b.rfch.centres)


#: how close two meshes' corners must be to be the same (relative to the larger bounding-box diagonal):
#: a text PLY/OBJ/STL export rounds coordinates to ~6 significant digits, far below what moves a
#: learned point off the surface
SAME_MESH_REL_TOL = 1e-5


def same_mesh(a: Mesh, b: Mesh, rel_tol: float = SAME_MESH_REL_TOL) -> bool:
    """The same surface: the same set of triangles, each a set of corner positions equal within
    ``rel_tol`` of the meshes' size — whatever the order of the vertices, of the faces and of a
    face's corners, and whether faces share their vertices or not (an STL file stores each
    triangle's corners apart). Learned 3-D points only make sense on their own mesh; they are in
    the object frame, not tied to vertex or face indices, so a re-export of the same geometry keeps
    them valid. (Compared index by index, a re-export or the same box as STL dropped every learned
    view: "the mesh changed".) Another triangulation of the same surface counts as another mesh."""
    if a is b or (a.vertices.shape == b.vertices.shape and a.faces.shape == b.faces.shape
                  and np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)):
        return True
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    tol = rel_tol * max(a.extent, b.extent, 1e-300)
    if abs(a.extent - b.extent) > 2 * tol:  # (cheap: another size is another mesh)
        return False
    # the corners of both meshes, one id per position (within tol, chained), then each face as its
    # sorted ids: the meshes are the same when their sets of faces are
    V = np.concatenate([a.vertices, b.vertices])
    pairs = cKDTree(V).query_pairs(tol, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(V), len(V)))
    _, ids = connected_components(graph, directed=False)
    fa = np.unique(np.sort(ids[a.faces], axis=1), axis=0)
    fb = np.unique(np.sort(ids[np.asarray(b.faces) + len(a.vertices)], axis=1), axis=0)
    return fa.shape == fb.shape and np.array_equal(fa, fb)


__all__ = ["MAX_LEARNED", "MIN_ANGLE_DEG", "MIN_COS", "view_angles_deg", "is_new_direction",
           "learned_viewset", "with_learned", "why_none_learned", "check_can_store", "merge_learned",
           "merge_learned_views", "new_points", "NEW_POINT_SHARE", "save_learned", "store_lock", "same_mesh", "SAME_MESH_REL_TOL",
           "carry_learned", "save_trained", "Retrained", "BACKUP_DIR", "backup_path",
           "same_description"]

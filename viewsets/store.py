"""The model store: one folder per object, ``NAME/manifest.json`` + ``NAME/model.npz``.

Views learned while tracking (:mod:`quatrack.viewsets.learn`) are stored like trained ones, with
``"learned": true`` in their manifest entry: the format stays schema 1, older code reads them as
trained views and models without the key load as before.

Writes are atomic: a model is built in a temporary folder inside the store and renamed into
place only when complete, so readers never see a partial model and a failed retraining leaves
the old one intact. Folders whose names start with ``.`` are temporary and never listed; those
an interrupted write left behind are removed after an hour (:func:`remove_stale`) when the store
is opened (training, listing, serving).

Every change of a model — a (re)training's rename, a deletion, the merge of views learned while
tracking (read, merge, write) — holds the store's lock (:func:`model_lock`), so none of them comes
between another's read and write: a model retrained or deleted while a ``track --learn`` run
stored its views was put back as it was before.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import secrets
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from quatrack.tracking.camera import PinholeCamera

from .errors import StoreError
from .mesh import Mesh
from .names import check_object_name
from .rfch import RFCHModel
from quatrack.tracking.pose import Pose
from .texture import TextureReference
from .viewset import Viewset, ViewsetParams

__all__ = ["ObjectModel", "StoreError", "load_model", "save_model", "list_models", "delete_model",
           "model_lock", "default_store", "resolve_store", "model_path", "load_manifest", "model_stamp",
           "trained_from", "retrain_reason", "NOT_STORED", "broken_folders", "learn_lock_path", "learned_count", "learned_points", "learned_views_warning", "remove_stale", "unknown_object", "names_hint",
           "store_note"]

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
ARRAYS = "model.npz"


@dataclass
class ObjectModel:
    """Everything recognition needs about one object (units: mesh units, pixels)."""

    name: str
    rfch: RFCHModel
    viewsets: list[Viewset]
    mesh: Mesh
    manifest: dict = field(default_factory=dict)
    # the registered photos' grey crops of the object (viewsets/texture.py): evidence a wrong
    # pose cannot fake (recognition/appearance.py). Models stored before session 36 have none.
    appearance: list[TextureReference] = field(default_factory=list)

    @property
    def training_width(self) -> float | None:
        """The median width (px) of the images trained from (registered and synthetic views, not
        views learned while tracking): the pixel unit of the RFCH's window sizes and texture
        scales (:func:`~quatrack.viewsets.rfch.texture_zoom`); None when no view states it."""
        widths = [vs.camera.width for vs in self.viewsets if not vs.learned and vs.camera.width]
        return float(np.median(widths)) if widths else None

    def at_run_time(self) -> "ObjectModel":
        """This model with the mesh recognition and tracking work with (``Mesh.run_time``: a
        scan's decimation; most meshes are their own, and then this is the model itself)."""
        return self if self.mesh.run_time is self.mesh else replace(self, mesh=self.mesh.run_time)


def default_store() -> Path:
    """``$QUATRACK_STORE``, else ``$XDG_DATA_HOME/quatrack/models`` (``~/.local/share/...``)."""
    env = os.environ.get("QUATRACK_STORE")
    if env:
        return Path(env).expanduser()
    data = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(data).expanduser() / "quatrack" / "models"


def resolve_store(store: str | Path | None) -> Path:
    """The store to use: an explicit ``--store`` wins over the environment and the default."""
    return Path(store).expanduser() if store else default_store()


def model_path(store: str | Path, name: str) -> Path:
    """The folder of object ``name`` in ``store`` (it may not exist); a name that is not a valid
    object name (a path, ``..``) is a :class:`StoreError`."""
    return Path(store) / check_object_name(name)


@contextlib.contextmanager
def model_lock(store: str | Path, name: str | None = None):
    """An exclusive lock on the store's changes (``flock`` on the store's folder itself: no file
    is added to the store; released when its holder exits, even killed): replacing, deleting
    and merging views into a model never interleave. Not re-entrant: code that holds it calls
    :func:`save_model` with ``locked=True``. ``name`` is the object about to change (checked;
    the lock covers the store). Where the filesystem cannot lock a folder (some network ones),
    the writes go on unlocked, each still atomic, as before the lock existed."""
    store = Path(store)
    if name is not None:
        model_path(store, name)
    store.mkdir(parents=True, exist_ok=True)
    fd = os.open(store, os.O_RDONLY)
    try:
        try:
            import fcntl

            fcntl.flock(fd, fcntl.LOCK_EX)
        except (ImportError, OSError):  # (not POSIX, or a folder that cannot be locked here)
            pass
        yield
    finally:
        os.close(fd)  # closing releases the flock


def _camera_row(c: PinholeCamera) -> np.ndarray:
    d = np.zeros(8)
    d[: c.dist_coeffs.size] = c.dist_coeffs
    return np.concatenate([[c.fx, c.fy, c.cx, c.cy, c.width or 0, c.height or 0], d])


def _model_arrays(model: ObjectModel) -> dict[str, np.ndarray]:
    vs = model.viewsets
    offsets = np.concatenate([[0], np.cumsum([len(v) for v in vs])]).astype(np.int64)

    def cat(attr, shape, dtype):
        parts = [getattr(v, attr).reshape(-1, *shape) for v in vs]
        return np.concatenate(parts).astype(dtype) if parts else np.zeros((0, *shape), dtype)

    r = model.rfch
    return {
        "rfch_centres": r.centres, "rfch_histogram": r.histogram,
        "rfch_desc_mean": r.desc_mean, "rfch_desc_std": r.desc_std,
        "mesh_vertices": model.mesh.vertices, "mesh_faces": model.mesh.faces,
        "vs_offsets": offsets,
        "vs_keypoints": cat("keypoints", (2,), np.float32),
        "vs_descriptors": cat("descriptors", (128,), np.float32),
        "vs_points3d": cat("points3d", (3,), np.float64),
        "vs_R": np.array([v.pose.R for v in vs]).reshape(-1, 3, 3),
        "vs_t": np.array([v.pose.t for v in vs]).reshape(-1, 3),
        "vs_camera": np.array([_camera_row(v.camera) for v in vs]).reshape(-1, 14),
        "vs_bbox": np.array([v.bbox for v in vs], dtype=np.int64).reshape(-1, 4),
        "vs_synthetic": np.array([v.synthetic for v in vs], dtype=bool),
        "vs_source": np.array([v.source_view for v in vs], dtype=np.int64),
        **_appearance_arrays(model.appearance),
    }


def _appearance_arrays(refs: list[TextureReference]) -> dict[str, np.ndarray]:
    """The photos' crops flattened (``ap_pixels``, ``ap_mask``: uint8, one after another, each
    ``ap_shape`` rows × columns), with their cameras and poses; nothing for a model without."""
    if not refs:
        return {}
    return {
        "ap_shape": np.array([r.image.shape[:2] for r in refs], dtype=np.int64),
        "ap_pixels": np.concatenate([r.image.ravel() for r in refs]).astype(np.uint8),
        "ap_mask": np.concatenate([(np.full(r.image.shape[:2], 255, np.uint8) if r.mask is None else r.mask).ravel()
                                   for r in refs]).astype(np.uint8),
        "ap_camera": np.array([_camera_row(r.camera) for r in refs]),
        "ap_R": np.array([r.pose.R for r in refs]),
        "ap_t": np.array([r.pose.t for r in refs]),
    }


def _appearance(a: dict[str, np.ndarray]) -> list[TextureReference]:
    """The references back from :func:`_appearance_arrays`' arrays (none when absent)."""
    if "ap_shape" not in a:
        return []
    shape, pix, mask = a["ap_shape"], a["ap_pixels"], a["ap_mask"]
    n = len(shape)
    if shape.ndim != 2 or shape.shape[1] != 2 or np.any(shape < 1):
        raise ValueError("appearance crops have invalid sizes")
    sizes = shape[:, 0] * shape[:, 1]
    if pix.ndim != 1 or len(pix) != sizes.sum() or mask.shape != pix.shape or pix.dtype != np.uint8:
        raise ValueError("appearance pixels do not match their sizes")
    for key, tail in (("ap_camera", (14,)), ("ap_R", (3, 3)), ("ap_t", (3,))):
        if a[key].shape != (n, *tail) or not np.all(np.isfinite(a[key])):
            raise ValueError(f"array {key!r} has shape {a[key].shape}")
    out, start = [], 0
    for i in range(n):
        h, w = (int(x) for x in shape[i])
        c = a["ap_camera"][i]
        cam = PinholeCamera(c[0], c[1], c[2], c[3], c[6:], width=int(c[4]), height=int(c[5]))
        out.append(TextureReference(pix[start : start + h * w].reshape(h, w), cam,
                                    Pose.from_matrix(a["ap_R"][i], a["ap_t"][i]), mask[start : start + h * w].reshape(h, w)))
        start += h * w
    return out


def save_model(store: str | Path, model: ObjectModel, overwrite: bool = True, locked: bool = False) -> Path:
    """Write ``model`` atomically as ``store/NAME``; refuses an existing name unless ``overwrite``.
    The files are written first, then put in place under the store's :func:`model_lock` (taken
    here unless ``locked``: the caller holds it).

    A stored model replaced by one with fewer views learned while tracking (``learned=True``: a
    retraining saved with this function) loses them: that is warned of (``UserWarning``, naming
    how many), since :func:`quatrack.viewsets.learn.save_trained` — what ``quatrack train`` uses —
    keeps those that fit the new model and says what it drops (``keep_learned=False``: drops them
    without a warning). Callers holding the lock (``locked``) read and merge the stored model
    themselves (``learn.save_trained``, ``learn.merge_learned``) and say what they drop: no warning."""
    if not isinstance(model, ObjectModel):  # (a spec, a name: AttributeError 'name')
        raise TypeError(f"model: an ObjectModel (quatrack.viewsets.train.train_object(spec) makes one), "
                        f"got {type(model).__name__}")
    if store is None or isinstance(store, bool) or not isinstance(store, (str, os.PathLike)):
        raise TypeError(f"store: a folder's path (quatrack.viewsets.store.resolve_store(None) is the default "
                        f"store), got {type(store).__name__}")
    store = Path(store)
    final = model_path(store, model.name)
    if final.exists() and not overwrite:
        raise StoreError(f"object {model.name!r} already exists in {store} (and --no-overwrite was given)")
    store.mkdir(parents=True, exist_ok=True)
    remove_stale(store)
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{model.name}-", dir=store))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # (mkdtemp's 0700 would survive the rename: a server run by another user could not read the model)
    old = None
    try:
        manifest = dict(model.manifest)
        manifest["schema_version"] = SCHEMA_VERSION
        manifest["name"] = model.name
        manifest["viewsets"] = [
            {"label": v.label, "source_view": v.source_view, "synthetic": v.synthetic, "keypoints": len(v),
             **({"learned": True} if v.learned else {}),  # (older readers ignore the key: a learned view reads as trained)
             **({"relayed": True} if v.relayed else {})}
            for v in model.viewsets
        ]
        with open(tmp / ARRAYS, "wb") as f:
            np.savez_compressed(f, **_model_arrays(model))
            f.flush()
            os.fsync(f.fileno())
        with open(tmp / MANIFEST, "w", encoding="utf-8") as f:
            json.dump(manifest, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        with contextlib.nullcontext() if locked else model_lock(store, model.name):
            # (read under the lock: views a track --learn run merges meanwhile are counted too)
            dropped = 0 if locked else learned_count(store, model.name) - sum(v.learned for v in model.viewsets)
            if final.exists():
                if not overwrite:
                    raise StoreError(f"object {model.name!r} already exists in {store} (and --no-overwrite was given)")
                old = Path(tempfile.mkdtemp(prefix=f".old-{model.name}-", dir=store))
                os.replace(final, old / "model")
            os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and not final.exists():
            os.replace(old / "model", final)  # put the previous model back
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    if dropped > 0:
        warnings.warn(f"save_model: {model.name!r} in {store} held {dropped} more view(s) learned while tracking than "
                      f"the model saved in its place: {dropped} dropped (quatrack.viewsets.learn.save_trained(store, "
                      f"model) keeps those that fit a retrained model, as quatrack train does)", UserWarning, stacklevel=2)
    return final


def learned_count(store: str | Path, name: str, relayed: bool = False) -> int:
    """How many views learned while tracking the stored model's manifest lists (``"learned":
    true``; 0: none, no model, an unreadable manifest); ``relayed``: only those also marked
    ``"relayed": true`` (:attr:`Viewset.relayed <quatrack.viewsets.viewset.Viewset.relayed>`)."""
    try:
        if not (model_path(Path(store), name) / MANIFEST).is_file():
            return 0  # (before load_manifest: its unknown-object message lists the store for a hint)
        entries = load_manifest(store, name).get("viewsets")
    except StoreError:
        return 0
    if not isinstance(entries, list):
        return 0
    return sum(isinstance(e, dict) and e.get("learned") is True and (not relayed or e.get("relayed") is True)
               for e in entries)


def learned_points(manifest: dict) -> int:
    """How many 3-D points the views learned while tracking hold, from a model's ``manifest`` (its
    ``"learned": true`` entries' ``keypoints``: one lifted point each); 0 when none or unreadable.
    The training summary's ``points3d_total`` counts the trained views' points only: learned views
    come after it (``models list`` shows both: ``930 points (+1210 learned)``)."""
    entries = manifest.get("viewsets") if isinstance(manifest, dict) else None
    if not isinstance(entries, list):
        return 0
    return sum(int(e.get("keypoints") or 0) for e in entries
               if isinstance(e, dict) and e.get("learned") is True and isinstance(e.get("keypoints"), int))


def load_manifest(store: str | Path, name: str) -> dict:
    """The stored model's ``manifest.json`` (training parameters, views, versions) without loading
    its arrays; :class:`StoreError` when there is no such object or the manifest is unreadable."""
    folder = model_path(Path(store), name)
    path = folder / MANIFEST
    try:
        present = path.is_file()
    except OSError as exc:  # (a folder of another user's, mode 700: a PermissionError traceback)
        raise StoreError(f"object {name!r}: its folder {folder} cannot be read ({exc.strerror or exc})") from None
    if not present:
        if folder.is_dir():  # (a half-finished copy: it was "no object named", yet blocked train --no-overwrite)
            raise StoreError(f"object {name!r}: its folder {folder} holds no {MANIFEST} (a copy or a move cut short?); "
                             f"delete it (quatrack models delete {name}) or retrain it")
        raise unknown_object(store, name)
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise StoreError(f"object {name!r}: unreadable manifest {path} ({exc.__class__.__name__}: {exc})"[:500]) from None
    if not isinstance(manifest, dict):
        raise StoreError(f"object {name!r}: manifest {path} is not a JSON object; retrain it")
    return manifest


NOT_STORED = "not in the store"


def retrain_reason(store: str | Path, name: str, checksum: str) -> str | None:
    """Why ``train --skip-existing`` must train ``name`` (again), or None when the stored model
    was trained from these very inputs and loads. ``checksum`` is
    :func:`quatrack.viewsets.batch.inputs_checksum`'s — the spec file, the mesh, photos and masks
    it names, its cameras and poses, and the training options — recorded as ``spec.inputs_sha256``
    in the manifest. Only the spec file's bytes were compared, so an edited photo or mesh, or
    other options, were "nothing to do"; and a broken model (a truncated ``model.npz``) trained
    from the same spec was skipped for ever. A model without the key (trained before it was
    recorded) is trained again. :data:`NOT_STORED` when there is no such object."""
    if not model_path(Path(store), name).exists():
        return NOT_STORED
    try:
        spec = load_manifest(store, name).get("spec")
        if not isinstance(spec, dict) or not spec.get("inputs_sha256"):
            return "its manifest records no checksum of its inputs (trained by an older quatrack)"
        if spec["inputs_sha256"] != checksum:
            return "the spec, the files it names or the training options changed"
        load_model(store, name)
    except ValueError as exc:  # (StoreError: no manifest, unreadable, schema, arrays)
        return f"the stored model is broken ({exc})"
    return None


def trained_from(store: str | Path, name: str, checksum: str) -> bool:
    """Whether the stored model ``name`` was trained from the inputs whose checksum is
    ``checksum`` and loads (:func:`retrain_reason` is None): ``train --skip-existing``'s test."""
    return retrain_reason(store, name, checksum) is None


def learned_views_warning(store: str | Path, name: str) -> str | None:
    """The warning a retraining of ``name`` that replaces the model with :func:`save_model` owes
    when the stored model holds views learned while tracking, else None. (For callers that
    replace a model with :func:`save_model` themselves: ``train`` — one spec or several — keeps
    them where they fit, :func:`.learn.save_trained`, and says what it dropped.)"""
    if not model_path(Path(store), name).exists():
        return None
    try:
        n_learned = int(load_manifest(store, name).get("learned_viewsets") or 0)
    except (ValueError, TypeError):
        return None
    if not n_learned:
        return None
    return (f"{name!r} in {store} holds {n_learned} view(s) learned while tracking; "
            f"retraining replaces them (track --learn learns them again)")


# What model.npz must hold: name -> (number of dimensions, trailing shape or None, kind).
# "n" is the number of viewsets, "K" the number of keypoints over all of them.
_ARRAY_SPEC = {
    "rfch_centres": (2, None, "f"), "rfch_histogram": (2, None, "f"),
    "rfch_desc_mean": (1, None, "f"), "rfch_desc_std": (1, None, "f"),
    "mesh_vertices": (2, (3,), "f"), "mesh_faces": (2, (3,), "i"),
    "vs_offsets": (1, None, "i"),
    "vs_keypoints": (2, (2,), "f"), "vs_descriptors": (2, (128,), "f"), "vs_points3d": (2, (3,), "f"),
    "vs_R": (3, (3, 3), "f"), "vs_t": (2, (3,), "f"), "vs_camera": (2, (14,), "f"),
    "vs_bbox": (2, (4,), "i"), "vs_synthetic": (1, None, "b"), "vs_source": (1, None, "i"),
}


def _check_arrays(a: dict[str, np.ndarray], n: int) -> None:
    """Raise ValueError unless the arrays fit together (a garbled file may still decompress)."""
    for key, (ndim, tail, kind) in _ARRAY_SPEC.items():
        if key not in a:
            raise ValueError(f"array {key!r} is missing")
        x = a[key]
        if x.ndim != ndim or (tail is not None and x.shape[1:] != tail) or x.dtype.kind not in (kind + ("iu" if kind == "i" else "")):
            raise ValueError(f"array {key!r} has shape {x.shape} and type {x.dtype}")
        if kind == "f" and not np.all(np.isfinite(x)):
            raise ValueError(f"array {key!r} holds NaN or infinite values")
    off = a["vs_offsets"]
    k = len(a["vs_keypoints"])
    if len(off) != n + 1 or off[0] != 0 or off[-1] != k or np.any(np.diff(off) < 0):
        raise ValueError("viewset offsets do not match the keypoints")
    if len(a["vs_descriptors"]) != k or len(a["vs_points3d"]) != k:
        raise ValueError("keypoints, descriptors and 3-D points differ in number")
    for key in ("vs_R", "vs_t", "vs_camera", "vs_bbox", "vs_synthetic", "vs_source"):
        if len(a[key]) != n:
            raise ValueError(f"array {key!r} has {len(a[key])} rows for {n} viewsets")
    faces, nv = a["mesh_faces"], len(a["mesh_vertices"])
    if faces.size and (faces.min() < 0 or faces.max() >= nv):
        raise ValueError("mesh faces index missing vertices")
    c = a["rfch_centres"]
    if a["rfch_histogram"].shape != (len(c), len(c)) or a["rfch_desc_mean"].shape != c.shape[1:] \
            or a["rfch_desc_std"].shape != c.shape[1:]:
        raise ValueError("RFCH arrays do not fit together")


def load_model(store: str | Path, name: str) -> ObjectModel:
    """Load ``store/NAME`` back into an :class:`ObjectModel`.

    Anything unreadable — a truncated, zeroed or garbled ``model.npz``, a manifest missing keys,
    arrays that do not fit together — is that object's :class:`StoreError` naming it, never a
    ``BadZipFile``/``zlib.error``/``KeyError`` from deep inside: the CLI prints one line (exit 2)
    and the service reports that object as broken while serving the others.
    """
    manifest = load_manifest(store, name)
    if (why := _schema_problem(manifest.get("schema_version"))) is not None:
        raise StoreError(f"object {name!r}: {why}")
    path = model_path(Path(store), name) / ARRAYS
    try:
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
    except Exception as exc:  # BadZipFile, EOFError, zlib.error, OSError, ValueError, ...: all "unreadable"
        raise StoreError(f"object {name!r}: unreadable model arrays {path} ({exc.__class__.__name__}: {exc}); retrain it"[:500]) from None
    try:
        return _build_model(name, manifest, a)
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
        what = f"missing key {exc}" if isinstance(exc, KeyError) else f"{exc.__class__.__name__}: {exc}"
        raise StoreError(f"object {name!r}: corrupt model in {path.parent} ({what}); retrain it"[:500]) from None


def _schema_problem(version) -> str | None:
    """Why a manifest's ``schema_version`` is not one this version reads (None: it is). A newer
    schema is a newer quatrack's model — upgrading reads it — and a missing one is said so: both
    were "model schema 2 is not 1" / "model schema None is not 1; retrain it"."""
    if version == SCHEMA_VERSION and not isinstance(version, bool):
        return None
    if isinstance(version, int) and not isinstance(version, bool) and version > SCHEMA_VERSION:
        return (f"model schema {version} was written by a newer quatrack (this one reads schema {SCHEMA_VERSION}): "
                f"upgrade quatrack, or retrain it")
    if version is None:
        return "its manifest has no schema_version (not a quatrack model, or a damaged one); retrain it"
    return f"model schema {version!r} is not {SCHEMA_VERSION}; retrain it"


def _check_sift_settings(manifest: dict) -> None:
    """Raise ValueError unless ``parameters.viewsets`` are SIFT settings this version describes
    images with (:func:`~.viewset.params_from_manifest`, which every query calls): a key it does
    not know (a model from a newer version, a hand edit) or a value of the wrong kind was a
    TypeError traceback out of ``locate`` — out of ``locate --object all`` for every object."""
    p = manifest["parameters"]["viewsets"]
    if not isinstance(p, dict):
        raise ValueError("manifest 'parameters.viewsets' is not an object")
    known = {f.name for f in dataclasses.fields(ViewsetParams)}
    unknown = sorted(set(p) - known)
    if unknown:
        raise ValueError(f"its SIFT settings hold {', '.join(map(repr, unknown))}, which this version does not "
                         f"know (trained by a newer quatrack?)")
    default = ViewsetParams()
    for key, value in p.items():
        d = getattr(default, key)
        if isinstance(d, bool):
            ok = isinstance(value, bool)
        else:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0 \
                and (isinstance(value, int) or not isinstance(d, int))
        if not ok:
            raise ValueError(f"manifest 'parameters.viewsets.{key}' is {value!r}"[:200])


def _build_model(name: str, manifest: dict, a: dict[str, np.ndarray]) -> ObjectModel:
    metas = manifest["viewsets"]
    if not isinstance(metas, list):
        raise ValueError("manifest 'viewsets' is not a list")
    _check_arrays(a, len(metas))
    _check_sift_settings(manifest)
    p = manifest["parameters"]["rfch"]
    info = manifest["rfch"]
    rfch = RFCHModel(
        a["rfch_centres"], a["rfch_histogram"], tuple(float(x) for x in p["scales"]), int(p["n_clusters"]),
        int(p["distance"]), a["rfch_desc_mean"], a["rfch_desc_std"], tuple(int(x) for x in info["size_min"]),
        tuple(int(x) for x in info["size_max"]),
    )
    viewsets = []
    off = a["vs_offsets"]
    for i, meta in enumerate(metas):
        c = a["vs_camera"][i]
        cam = PinholeCamera(c[0], c[1], c[2], c[3], c[6:], width=int(c[4]), height=int(c[5]))
        s = slice(int(off[i]), int(off[i + 1]))
        viewsets.append(Viewset(
            str(meta["label"]), int(a["vs_source"][i]), bool(a["vs_synthetic"][i]), cam,
            Pose.from_matrix(a["vs_R"][i], a["vs_t"][i]), a["vs_keypoints"][s], a["vs_descriptors"][s],
            a["vs_points3d"][s], tuple(int(x) for x in a["vs_bbox"][i]), learned=meta.get("learned") is True,
            relayed=meta.get("relayed") is True,
        ))
    mesh = Mesh(a["mesh_vertices"], a["mesh_faces"])
    if manifest.get("name", name) != name:
        # a folder renamed (or copied) by hand: the object is named by its folder, as it is listed
        # and asked for (it was "corrupt model ... retrain it"); the manifest follows at the next write
        manifest = {**manifest, "name": name}
    return ObjectModel(name, rfch, viewsets, mesh, manifest, _appearance(a))


# a file system's own folders at its root (ext*, XFS): a store on its own volume has one, which
# `models list` told to "delete it or retrain it" (never an object's: `+` is no name's)
FILESYSTEM_FOLDERS = frozenset({"lost+found"})


def _entries(store: Path) -> list[tuple[str, str | None]]:
    """The store's visible folders (not dot-folders nor ``lost+found``): ``(name, None)`` for an
    object (a folder with a manifest),
    ``(name, why)`` for a folder that is not one. Each entry is looked at on its own: one that
    cannot be read (``lost+found``, another user's folder, mode 700, on a server not run as
    root) was a PermissionError out of every listing — ``serve``, ``models list``, the service's
    store watch and ``GET /v1/objects``."""
    out: list[tuple[str, str | None]] = []
    for p in store.iterdir():
        if p.name.startswith(".") or p.name in FILESYSTEM_FOLDERS:
            continue
        try:
            if (p / MANIFEST).is_file():
                out.append((p.name, None))
                continue
            if not p.is_dir():
                continue  # (a file beside the models: not the store's)
            why = f"holds no {MANIFEST} (a copy or a move cut short?); delete it or retrain it"
        except OSError as exc:
            why = f"cannot be read ({exc.strerror or exc})"
        out.append((p.name, why))
    return sorted(out)


def list_models(store: str | Path) -> list[str]:
    """Names of the objects in the store (a folder with a manifest; temporary folders excluded),
    sorted. A listed object may still be broken: :func:`load_model` says so. Folders that are not
    objects — no manifest, unreadable — are :func:`broken_folders`, never an error here."""
    store = Path(store)
    if not store.is_dir():
        return []
    return [name for name, why in _entries(store) if why is None]


def broken_folders(store: str | Path) -> dict[str, str]:
    """The store's folders that are not objects, each with why: one without a manifest (a
    half-finished copy, which blocked ``train --no-overwrite`` while no command listed it) or one
    that cannot be read. Those with an object's name are listed BROKEN by ``models list`` and
    removed by ``models delete`` (:func:`delete_model`); others (``lost+found``) are only reported."""
    store = Path(store)
    if not store.is_dir():
        return {}
    return {name: why for name, why in _entries(store) if why is not None}


def unknown_object(store: str | Path, name: str) -> StoreError:
    """The error for an object ``name`` that ``store`` does not hold, for every command that names
    one (``locate``, ``track``, ``models show|delete``, ``demo``): the objects it holds, or that it
    holds none or does not exist, and the nearest name (:func:`names_hint`). It said only
    "no object named 'mybx' in STORE"."""
    msg = f"no object named {name!r} in {store}"
    return StoreError(msg + (store_note(store) or names_hint(name, list_models(store))))


def store_note(store: str | Path) -> str:
    """Why ``store`` holds no object although it was given as one, or "": `` (no such folder)``
    (a typo), or `` (the folder of object 'NAME' itself: its store is PARENT)`` — a model's own
    folder given as ``--store`` read as an empty store."""
    store = Path(store)
    if not store.is_dir():
        return " (no such folder)"
    if (store / MANIFEST).is_file():
        return f" (the folder of object {store.name!r} itself: its store is {store.parent})"
    return ""


def names_hint(name: str, names: list[str], shown: int = 12) -> str:
    """What follows "no object named NAME" (the store's, or a server's, ``names``): ``; did you
    mean 'NEAR'?`` when one is near — another case, a typo (:func:`difflib.get_close_matches`) —
    then `` (it holds A, B, ...)``, at most ``shown`` of them, or `` (it holds none)``."""
    import difflib

    if not names:
        return " (it holds none)"
    lower = {n.lower(): n for n in names}
    key = name.lower() if name.lower() in lower else next(iter(difflib.get_close_matches(name.lower(), list(lower), n=1)), None)
    held = ", ".join(names[:shown]) + (f", ... ({len(names)} in all)" if len(names) > shown else "")
    return (f"; did you mean {lower[key]!r}?" if key is not None else "") + f" (it holds {held})"


def model_stamp(store: str | Path, name: str) -> tuple | None:
    """What changes when ``store/NAME`` is replaced (an atomic rename brings new inodes and
    times) or removed (``None``): compared by the service to reload a retrained model."""
    folder = model_path(Path(store), name)
    try:
        m, z = os.stat(folder / MANIFEST), os.stat(folder / ARRAYS)
    except OSError:
        try:
            m = os.stat(folder / MANIFEST)
        except OSError:
            return None
        return (m.st_ino, m.st_mtime_ns, m.st_size, None)
    return (m.st_ino, m.st_mtime_ns, m.st_size, z.st_ino, z.st_mtime_ns, z.st_size)


STALE_AFTER_S = 3600.0


def remove_stale(store: str | Path, max_age_s: float = STALE_AFTER_S, now: float | None = None) -> list[str]:
    """Clean what interrupted writes left behind; returns the folders removed or restored.

    ``.tmp-NAME-*`` (a training killed while writing), ``.del-NAME-*`` (a delete killed while
    removing) and ``.old-NAME-*`` folders older than ``max_age_s`` are removed — younger ones may
    belong to a write in progress. An ``.old-NAME-*/model`` whose ``NAME`` is missing is the
    previous model of a retraining killed between its two renames: it is put back instead.
    """
    store = Path(store)
    if not store.is_dir():
        return []
    now = time.time() if now is None else now
    done = []
    for p in store.iterdir():
        kind = p.name[:5]
        if kind not in (".tmp-", ".old-", ".del-") or not p.is_dir():
            continue
        try:
            age = now - p.stat().st_mtime
        except OSError:
            continue
        if age < max_age_s:
            continue
        if kind == ".old-":
            name = p.name[5:].rsplit("-", 1)[0]
            final = store / name
            if (p / "model" / MANIFEST).is_file() and not final.exists():
                try:
                    os.replace(p / "model", final)
                    done.append(f"restored {name}")
                except OSError:
                    pass
        shutil.rmtree(p, ignore_errors=True)
        done.append(p.name)
    return done


def learn_lock_path(store: str | Path, name: str) -> Path:
    """``store/.learn-NAME.lock``: the lock file :func:`quatrack.viewsets.learn.store_lock` (a
    merge of learned views) takes beside the store's own lock."""
    return Path(store) / f".learn-{model_path(store, name).name}.lock"


def delete_model(store: str | Path, name: str) -> None:
    """Remove ``store/NAME`` — a model, or a folder of that name without a manifest (a
    half-finished copy, listed BROKEN: it blocked ``train --no-overwrite`` and nothing removed it).

    The folder is renamed straight to ``.del-NAME-RANDOM`` (so a half-deleted folder is never
    visible; :func:`remove_stale` finishes a removal killed midway), then removed: no folder is
    made first — ``mkdtemp`` failed on a full disk ("No space left on device"), which is when a
    model is deleted. Its learned views' lock file (:func:`learn_lock_path`) goes with it, unless
    a merge holds it."""
    store = Path(store)
    final = model_path(store, name)
    if not final.is_dir():
        raise unknown_object(store, name)
    with model_lock(store, name):  # (not between a merge's read and its write: the model came back)
        if not final.is_dir():
            raise unknown_object(store, name)
        trash = store / f".del-{name}-{secrets.token_hex(6)}"
        try:
            os.rename(final, trash)
        except OSError as exc:  # (a read-only store)
            raise StoreError(f"cannot delete {name!r} from {store} ({exc.strerror or exc})") from None
        if trash.is_symlink():  # (a link put in the store by hand: removed, its target kept)
            trash.unlink()
        else:
            shutil.rmtree(trash, ignore_errors=True)
        _remove_unheld_lock(learn_lock_path(store, name))


def _remove_unheld_lock(path: Path) -> None:
    """Remove the lock file ``path`` unless someone holds it (a non-blocking ``flock`` fails)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return  # (none, or not ours to open)
    try:
        try:
            import fcntl

            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except ImportError:
            pass
        except OSError:  # (held: a merge is running; it is an empty file, left to it)
            return
        with contextlib.suppress(OSError):
            path.unlink()
    finally:
        os.close(fd)

"""The model store: one folder per object, ``NAME/manifest.json`` + ``NAME/model.npz``.

Writes are atomic: a model is built in a temporary folder inside the store and renamed into
place only when complete, so readers never see a partial model and a failed retraining leaves
the old one intact. Folders whose names start with ``.`` are temporary and never listed.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quatrack.tracking.camera import PinholeCamera

from .errors import StoreError
from .mesh import Mesh
from .names import check_object_name
from .rfch import RFCHModel
from quatrack.tracking.pose import Pose
from .viewset import Viewset

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


def model_path(store: Path, name: str) -> Path:
    return Path(store) / check_object_name(name)


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
    }


def save_model(store: str | Path, model: ObjectModel, overwrite: bool = True) -> Path:
    """Write ``model`` atomically as ``store/NAME``; refuses an existing name unless ``overwrite``."""
    store = Path(store)
    final = model_path(store, model.name)
    if final.exists() and not overwrite:
        raise StoreError(f"object {model.name!r} already exists in {store} (and --no-overwrite was given)")
    store.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{model.name}-", dir=store))
    old = None
    try:
        manifest = dict(model.manifest)
        manifest["schema_version"] = SCHEMA_VERSION
        manifest["name"] = model.name
        manifest["viewsets"] = [
            {"label": v.label, "source_view": v.source_view, "synthetic": v.synthetic, "keypoints": len(v)}
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
    return final


def load_manifest(store: str | Path, name: str) -> dict:
    path = model_path(Path(store), name) / MANIFEST
    if not path.is_file():
        raise StoreError(f"no object named {name!r} in {store}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise StoreError(f"{path}: unreadable manifest ({exc})") from None


def load_model(store: str | Path, name: str) -> ObjectModel:
    """Load ``store/NAME`` back into an :class:`ObjectModel`."""
    manifest = load_manifest(store, name)
    if manifest.get("schema_version") != SCHEMA_VERSION:
        raise StoreError(f"object {name!r}: model schema {manifest.get('schema_version')} is not {SCHEMA_VERSION}; retrain it")
    path = model_path(Path(store), name) / ARRAYS
    try:
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise StoreError(f"{path}: unreadable model arrays ({exc})") from None
    p = manifest["parameters"]["rfch"]
    info = manifest["rfch"]
    rfch = RFCHModel(
        a["rfch_centres"], a["rfch_histogram"], tuple(p["scales"]), int(p["n_clusters"]), int(p["distance"]),
        a["rfch_desc_mean"], a["rfch_desc_std"], tuple(info["size_min"]), tuple(info["size_max"]),
    )
    viewsets = []
    off = a["vs_offsets"]
    for i, meta in enumerate(manifest["viewsets"]):
        c = a["vs_camera"][i]
        cam = PinholeCamera(c[0], c[1], c[2], c[3], c[6:], width=int(c[4]), height=int(c[5]))
        s = slice(int(off[i]), int(off[i + 1]))
        viewsets.append(Viewset(
            meta["label"], int(a["vs_source"][i]), bool(a["vs_synthetic"][i]), cam,
            Pose.from_matrix(a["vs_R"][i], a["vs_t"][i]), a["vs_keypoints"][s], a["vs_descriptors"][s],
            a["vs_points3d"][s], tuple(int(x) for x in a["vs_bbox"][i]),
        ))
    mesh = Mesh(a["mesh_vertices"], a["mesh_faces"])
    return ObjectModel(manifest["name"], rfch, viewsets, mesh, manifest)


def list_models(store: str | Path) -> list[str]:
    """Names of the complete models in the store (temporary folders excluded), sorted."""
    store = Path(store)
    if not store.is_dir():
        return []
    return sorted(
        p.name for p in store.iterdir()
        if not p.name.startswith(".") and (p / MANIFEST).is_file() and (p / ARRAYS).is_file()
    )


def delete_model(store: str | Path, name: str) -> None:
    """Remove ``store/NAME`` (renamed away first, so a half-deleted folder is never visible)."""
    store = Path(store)
    final = model_path(store, name)
    if not (final / MANIFEST).is_file():
        raise StoreError(f"no object named {name!r} in {store}")
    trash = Path(tempfile.mkdtemp(prefix=f".del-{name}-", dir=store))
    os.replace(final, trash / "model")
    shutil.rmtree(trash, ignore_errors=True)

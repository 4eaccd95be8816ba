"""Camera files (JSON, or OpenCV YAML with camera_matrix / distortion_coefficients) → PinholeCamera.

There is one camera model in the project, :class:`quatrack.tracking.camera.PinholeCamera`; this
module only parses files into it and checks what a user can get wrong.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from quatrack.tracking.camera import PinholeCamera

from .errors import SpecError

_KEYS = ("fx", "fy", "cx", "cy")


def _number(value: Any, where: str, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SpecError(f"{where}: field {field!r} must be a finite number, got {value!r}")
    return float(value)


def camera_from_dict(data: Any, where: str = "camera") -> PinholeCamera:
    """A camera from the contract's JSON object ``{width, height, fx, fy, cx, cy[, dist_coeffs]}``."""
    if not isinstance(data, dict):
        raise SpecError(f"{where}: a camera must be a JSON object, got {type(data).__name__}")
    missing = [k for k in (*_KEYS, "width", "height") if k not in data]
    if missing:
        raise SpecError(f"{where}: missing field(s) {', '.join(missing)}")
    fx, fy, cx, cy = (_number(data[k], where, k) for k in _KEYS)
    if fx <= 0 or fy <= 0:
        raise SpecError(f"{where}: focal lengths must be positive, got fx={fx:g}, fy={fy:g}")
    size = []
    for k in ("width", "height"):
        v = data[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v != int(v) or v <= 0:
            raise SpecError(f"{where}: field {k!r} must be a positive integer, got {v!r}")
        size.append(int(v))
    dist = data.get("dist_coeffs", [0.0] * 5)
    if dist is None:
        dist = [0.0] * 5
    if not isinstance(dist, list) or not all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in dist
    ):
        raise SpecError(f"{where}: field 'dist_coeffs' must be a list of numbers")
    if len(dist) not in (0, 4, 5, 8):
        raise SpecError(f"{where}: field 'dist_coeffs' must have 4, 5 or 8 entries (OpenCV order), got {len(dist)}")
    return _make(fx, fy, cx, cy, dist, size[0], size[1], where)


def _make(fx, fy, cx, cy, dist, width, height, where) -> PinholeCamera:
    try:
        return PinholeCamera(fx, fy, cx, cy, np.asarray(dist, float), width=width, height=height)
    except ValueError as exc:
        raise SpecError(f"{where}: {exc}") from None


def _camera_from_yaml(path: Path) -> PinholeCamera:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise SpecError(f"{path}: cannot read camera file (not JSON nor OpenCV YAML)")
        K = fs.getNode("camera_matrix").mat()
        D = fs.getNode("distortion_coefficients").mat()
        w = fs.getNode("image_width")
        h = fs.getNode("image_height")
        width = int(w.real()) if not w.empty() else 0
        height = int(h.real()) if not h.empty() else 0
    finally:
        fs.release()
    if K is None or K.shape != (3, 3):
        raise SpecError(f"{path}: field 'camera_matrix' missing or not 3×3")
    if width <= 0 or height <= 0:
        raise SpecError(f"{path}: fields 'image_width' and 'image_height' are required")
    dist = [] if D is None else [float(x) for x in D.ravel()]
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise SpecError(f"{path}: focal lengths must be positive and finite, got fx={fx:g}, fy={fy:g}")
    return _make(fx, fy, cx, cy, dist, width, height, str(path))


def load_camera(path: str | Path) -> PinholeCamera:
    """A camera from a JSON file (contract format) or an OpenCV YAML/XML calibration file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(f"{path}: cannot read camera file ({exc.__class__.__name__}: {exc})") from None
    if path.suffix.lower() in (".yml", ".yaml", ".xml") or text.lstrip().startswith("%YAML"):
        return _camera_from_yaml(path)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SpecError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    return camera_from_dict(data, str(path))


def camera_to_dict(camera: PinholeCamera) -> dict:
    """The contract's JSON form of a camera (for manifests and round trips)."""
    return {
        "width": camera.width, "height": camera.height,
        "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
        "dist_coeffs": [float(x) for x in camera.dist_coeffs],
    }

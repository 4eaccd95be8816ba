"""Camera files (JSON, or OpenCV YAML with camera_matrix / distortion_coefficients) → PinholeCamera.

There is one camera model in the project, :class:`quatrack.tracking.camera.PinholeCamera`; this
module only parses files into it and checks what a user can get wrong.
"""

from __future__ import annotations

import json
from dataclasses import replace
import math
import numbers
import re
from pathlib import Path
from typing import Any

import numpy as np

from quatrack.tracking.camera import PinholeCamera

from .errors import SpecError

__all__ = ["load_camera", "camera_from_dict", "camera_to_dict", "check_lens", "check_plausible", "lens_reach_px",
           "misspelt_field", "resized_for", "stated_size_doubt", "within_pixels"]

_KEYS = ("fx", "fy", "cx", "cy")
CAMERA_FIELDS = ("width", "height", "fx", "fy", "cx", "cy", "dist_coeffs")


# Other programs' names for the contract's fields (OpenCV's calibration output, ROS's CameraInfo
# "K"/"D" and ROS 2's "k"/"d", per-coefficient k1…p2 forms): lowercased name → the field(s) meant.
# They are refused with the contract's name, not read: "K" is a 3×3 matrix (row-major in ROS, a
# nested list in OpenCV dumps), "D" may follow another lens model (ROS's "equidistant") — a
# reading that guesses wrong gives a wrong pose, which is what ignoring them gave (5 % in depth).
FIELD_ALIASES = {
    **dict.fromkeys(("dist", "d", "distortion", "distortion_coefficients", "distortion_coeffs", "distcoeffs",
                     "dist_coefs", "k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2"), ("dist_coeffs",)),
    **dict.fromkeys(("k", "camera_matrix", "cameramatrix", "intrinsics", "intrinsic_matrix"), _KEYS),
    **dict.fromkeys(("image_width", "imagewidth"), ("width",)),
    **dict.fromkeys(("image_height", "imageheight"), ("height",)),
}


def misspelt_field(data: dict, known=CAMERA_FIELDS, where: str = "camera") -> str | None:
    """A message naming a field of ``data`` that looks like a misspelling of a known field it
    lacks (``dist_coeff`` for ``dist_coeffs``, ``fxx`` for ``fx``; difflib's ratio ≥ 0.75) or is
    another program's name for it (:data:`FIELD_ALIASES`: ``dist``, ``D``, ``k1``, ``K``,
    ``camera_matrix``), else None. Why: other fields are ignored (a camera file may carry its own
    notes), so a misspelt or OpenCV/ROS-named ``dist_coeffs`` dropped the lens's distortion without
    a word, everywhere a camera is read.

    >>> misspelt_field({"fx": 600, "dist_coeff": [0.1, 0, 0, 0]})
    "camera: unknown field 'dist_coeff' (did you mean 'dist_coeffs'?)"
    >>> misspelt_field({"fx": 600, "D": [0.1, 0, 0, 0, 0]})
    "camera: unknown field 'D' (did you mean 'dist_coeffs'?)"
    >>> misspelt_field({"fx": 600, "model": "pinhole"}) is None
    True
    """
    import difflib

    absent = [k for k in known if k not in data]
    for key in data:
        if not isinstance(key, str) or key in known:
            continue
        meant = FIELD_ALIASES.get(key.lower(), ())
        if any(k not in data for k in meant):
            return f"{where}: unknown field {_shown(key)} (did you mean {', '.join(map(repr, meant))}?)"
        near = difflib.get_close_matches(key.lower(), absent, n=1, cutoff=0.75)
        if near:
            return f"{where}: unknown field {_shown(key)} (did you mean {near[0]!r}?)"
    return None


def isfinite(x) -> bool:
    """``math.isfinite``, False for an integer too large for a float (JSON's integers have no
    bound: ``"fx": 1e400`` reads as inf, but ``"fx": 1000…0`` (400 digits) as an int that
    ``math.isfinite`` refuses with OverflowError)."""
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


def _shown(value: Any) -> str:
    """A value for a message, cut to 40 characters (a 400-digit number is not a line)."""
    r = repr(value)
    return r if len(r) <= 40 else r[:37] + "..."


def _number(value: Any, where: str, field: str) -> float:
    # (numbers.Real: numpy's too — a float32 fx, an int64 width were refused as "not a number")
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real) or not isfinite(value):
        raise SpecError(f"{where}: field {field!r} must be a finite number, got {_shown(value)}")
    return float(value)


def camera_from_dict(data: Any, where: str = "camera") -> PinholeCamera:
    """A camera from the contract's JSON object ``{width, height, fx, fy, cx, cy[, dist_coeffs]}``."""
    if not isinstance(data, dict):
        raise SpecError(f"{where}: a camera must be a JSON object, got {type(data).__name__}")
    if (msg := misspelt_field(data, where=where)) is not None:
        raise SpecError(msg)
    missing = [k for k in (*_KEYS, "width", "height") if k not in data]
    if missing:
        raise SpecError(f"{where}: missing field(s) {', '.join(missing)}")
    fx, fy, cx, cy = (_number(data[k], where, k) for k in _KEYS)
    if fx <= 0 or fy <= 0:
        raise SpecError(f"{where}: focal lengths must be positive, got fx={fx:g}, fy={fy:g}")
    size = []
    for k in ("width", "height"):
        v = data[k]
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real) or not isfinite(v) or v != int(v) or v <= 0:
            raise SpecError(f"{where}: field {k!r} must be a positive integer, got {_shown(v)}")
        size.append(int(v))
    dist = data.get("dist_coeffs", [0.0] * 5)
    if dist is None:
        dist = [0.0] * 5
    if isinstance(dist, (tuple, np.ndarray)) and np.ndim(dist) <= 2 and (np.ndim(dist) < 2 or 1 in np.shape(dist)):
        dist = np.ravel(np.asarray(dist, dtype=object)).tolist()  # (cv2.calibrateCamera's (1, 5) array)
    if not isinstance(dist, list) or not all(
        isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_)) and isfinite(x) for x in dist
    ):
        raise SpecError(f"{where}: field 'dist_coeffs' must be a list of numbers")
    if len(dist) not in (0, 4, 5, 8):
        raise SpecError(f"{where}: field 'dist_coeffs' must have 4, 5 or 8 entries (OpenCV order), got {len(dist)}")
    return _make(fx, fy, cx, cy, dist, size[0], size[1], where)


# Plausibility: beyond these a camera is a typo or an attack (fx = 1e308 made a request compute
# for a second before failing), not a lens. A focal length f (px) gives a field of view of
# 2·atan(w / 2f): f = 0.02·w is ~176° (past any pinhole-modelled lens), f = 1000·w is ~0.06°
# (past a 2000 mm telephoto on a small sensor, ~350·w). Pixels are near square (fx/fy within
# 1/8..8, anamorphic lenses are ~2). The principal point lies within half an image of the image.
FOCAL_PER_SIZE = (0.02, 1000.0)
MAX_ASPECT = 8.0
MAX_SIDE = 100_000  # pixels


def check_plausible(fx: float, fy: float, cx: float, cy: float, width: int | None, height: int | None,
                    where: str = "camera") -> None:
    """Raise :class:`SpecError` (naming ``where`` and the field) unless the intrinsics can be a
    real camera's for a ``width`` × ``height`` image (both None: a camera sized by its images,
    whose focal lengths alone are checked here; training checks it again at its photo's size).
    The one place both the CLI and the service
    check a camera: every parser ends here."""
    for name, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not isfinite(v):
            raise SpecError(f"{where}: field {name!r} must be a finite number, got {_shown(v)}")
    if width is None and height is None:  # (a camera sized by its images: an OpenCV YAML without its size)
        if not (fx > 0 and fy > 0 and 1 / MAX_ASPECT <= fx / fy <= MAX_ASPECT):
            raise SpecError(f"{where}: fx = {fx:g}, fy = {fy:g} are not the focal lengths of a camera")
        return
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 < v <= MAX_SIDE:
            raise SpecError(f"{where}: field {name!r} must be an integer 1..{MAX_SIDE}, got {_shown(v)}")
    side = max(width, height)
    lo, hi = FOCAL_PER_SIZE[0] * side, FOCAL_PER_SIZE[1] * side
    for name, f in (("fx", fx), ("fy", fy)):
        if not lo <= f <= hi:
            raise SpecError(f"{where}: field {name!r} = {f:g} px is not a focal length for a {width}×{height} image "
                            f"(expected {lo:g}..{hi:g} px)")
    if not 1 / MAX_ASPECT <= fx / fy <= MAX_ASPECT:
        raise SpecError(f"{where}: fx/fy = {fx / fy:g}: pixels that far from square are a typo (fx={fx:g}, fy={fy:g})")
    for name, c, n in (("cx", cx, width), ("cy", cy, height)):
        if not -0.5 * n <= c <= 1.5 * n:
            raise SpecError(f"{where}: field {name!r} = {c:g} px is not near the {width}×{height} image "
                            f"(expected {-0.5 * n:g}..{1.5 * n:g} px)")


def lens_reach_px(camera: PinholeCamera) -> tuple[float, float]:
    """How far (pixels, along x and along y) from the principal point the lens model reaches
    before it turns back (:attr:`~quatrack.tracking.camera.PinholeCamera.valid_r2`: its radial
    polynomial stops growing); inf for a camera without distortion or a lens that never does.

    >>> lens_reach_px(PinholeCamera(600.0, 600.0, 320.0, 240.0, [-0.45, 0.0, 0.0, 0.0]))   # r_d ≤ 0.5738
    (344.26..., 344.26...)
    """
    if not math.isfinite(camera.valid_r2):
        return math.inf, math.inf
    r = math.sqrt(camera.valid_r2)
    (ux, vx), (uy, vy) = camera.project([[r, 0.0, 1.0], [0.0, r, 1.0]])  # the last valid points on the axes
    return (camera.fx * math.hypot((ux - camera.cx) / camera.fx, (vx - camera.cy) / camera.fy),
            camera.fy * math.hypot((uy - camera.cx) / camera.fx, (vy - camera.cy) / camera.fy))


def check_lens(camera: PinholeCamera, where: str = "camera") -> None:
    """Raise :class:`SpecError` when the lens model turns back before it reaches the image's
    nearest side (:func:`lens_reach_px`): then points well outside the field of view have the
    same pixels as points in the middle of the image, and no calibration fitted to the image's
    pixels gives that — typed coefficients in the wrong order or scale (``k1 = 1e6``, or
    ``k1 = -50``), which made every search "not found" without a word. A model that turns back
    only towards the corners is accepted (its corners' rays are continued outwards). A camera
    sized by its images (no size) is not checked here."""
    if not camera.has_distortion or camera.width is None or camera.height is None:
        return
    ax, ay = lens_reach_px(camera)
    near_x = min(camera.cx + 0.5, camera.width - 0.5 - camera.cx)
    near_y = min(camera.cy + 0.5, camera.height - 0.5 - camera.cy)
    if ax < near_x or ay < near_y:
        raise SpecError(f"{where}: field 'dist_coeffs' = {_shown([float(v) for v in camera.dist_coeffs])}: this lens "
                        f"model turns back {min(ax, ay):.3g} px from the principal point, inside the "
                        f"{camera.width}×{camera.height} image (points outside the view would be seen in it); "
                        f"check the coefficients and their order (k1, k2, p1, p2[, k3[, k4, k5, k6]])")


def _make(fx, fy, cx, cy, dist, width, height, where) -> PinholeCamera:
    check_plausible(fx, fy, cx, cy, width, height, where)
    try:
        camera = PinholeCamera(fx, fy, cx, cy, np.asarray(dist, float), width=width, height=height)
    except ValueError as exc:
        raise SpecError(f"{where}: {exc}") from None
    check_lens(camera, where)
    return camera


def _opencv_detail(exc: BaseException) -> str:
    """What OpenCV says is wrong with a file, as `` (…)`` to append, or "": a parsing error's
    place and reason (OpenCV puts them in the error's ``func``: ``"cam.yml(1): Missing , between
    the elements"``); an assertion's text means nothing to a user and is left out. A SystemError
    is OpenCV's binding raising with the cv2.error as its cause."""
    import cv2

    cause = exc.__cause__ or exc.__context__
    if isinstance(exc, SystemError) and cause is not None:
        exc = cause
    if getattr(exc, "code", None) == cv2.Error.StsParseError and getattr(exc, "func", ""):
        where = re.match(r"^.*\((\d+)\):\s*(.*)$", str(exc.func).strip(), re.S)  # "<path>(line): reason"
        return f" (line {where[1]}: {where[2][:200]})" if where else f" ({str(exc.func).strip()[:200]})"
    return ""


def _camera_from_yaml(path: Path) -> PinholeCamera:
    import cv2

    # OpenCV's parser raises cv2.error on a malformed file, and SystemError (an exception set
    # inside its binding) on text that is not YAML at all: both are the user's file, not a bug
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        raise SpecError(f"{path}: not a valid OpenCV YAML/XML camera file{_opencv_detail(exc)}") from None
    try:
        if not fs.isOpened():
            raise SpecError(f"{path}: cannot read camera file (not JSON nor OpenCV YAML)")
        K = fs.getNode("camera_matrix").mat()
        D = fs.getNode("distortion_coefficients").mat()
        w = fs.getNode("image_width")
        h = fs.getNode("image_height")
        # (a string's real() is 1.8e308: "'width' must be an integer 1..100000, got 17976931348623157...")
        not_numbers = [k for k, n in (("image_width", w), ("image_height", h)) if not (n.empty() or n.isInt() or n.isReal())]
        w_empty, h_empty = w.empty(), h.empty()
        width = int(w.real()) if not w_empty else 0
        height = int(h.real()) if not h_empty else 0
    except (cv2.error, SystemError, TypeError, ValueError) as exc:
        raise SpecError(f"{path}: not a valid OpenCV camera file: 'camera_matrix', 'distortion_coefficients', "
                        f"'image_width' and 'image_height' must be a 3×3 matrix, a vector and two numbers"
                        f"{_opencv_detail(exc)}") from None
    finally:
        fs.release()
    if not_numbers:
        raise SpecError(f"{path}: field {not_numbers[0]!r} must be a number of pixels")
    if K is None or K.shape != (3, 3):
        raise SpecError(f"{path}: field 'camera_matrix' missing or not 3×3")
    if (width > 0) != (height > 0) or min(width, height) < 0 or (width == 0 and not (w_empty and h_empty)):
        raise SpecError(f"{path}: fields 'image_width' and 'image_height' must both be given (positive), or neither")
    if width == 0:  # neither: the contract's "camera_matrix / distortion_coefficients" alone (the size
        width = height = None  # is the images' own, checked for plausibility when the first one comes)
    dist = [] if D is None else [float(x) for x in D.ravel()]
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise SpecError(f"{path}: focal lengths must be positive and finite, got fx={fx:g}, fy={fy:g}")
    return _make(fx, fy, cx, cy, dist, width, height, str(path))


def within_pixels(image: np.ndarray, camera: PinholeCamera, max_pixels: int,
                  min_side: int = 1) -> tuple[np.ndarray, PinholeCamera, float]:
    """``image`` and its ``camera`` brought to at most ``max_pixels`` pixels: ``(image, camera,
    scale)``, downscaled (area averaging) by ``scale`` = new width / old, each side at least
    ``min_side``, the camera scaled with it (:meth:`PinholeCamera.scaled`: pixel centres kept);
    as given, scale 1, when it has no more. One rule for what training keeps of a large photo and
    what recognition keeps of a large query."""
    import cv2

    h, w = image.shape[:2]
    if w * h <= max_pixels:
        return image, camera, 1.0
    s = float(np.sqrt(max_pixels / (w * h)))
    nw, nh = max(min_side, int(w * s)), max(min_side, int(h * s))
    return cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA), camera.scaled(nw / w, nw, nh), nw / w


def _unreadable(exc: OSError) -> str:
    """Why a file could not be read, in plain words: "no such file", "it is a directory",
    "permission denied", else the system's words (``strerror``). A missing camera file said
    "cannot read camera file (FileNotFoundError: [Errno 2] No such file or directory: …)"."""
    if isinstance(exc, FileNotFoundError):
        return "no such file"
    if isinstance(exc, IsADirectoryError):
        return "it is a directory"
    if isinstance(exc, PermissionError):
        return "permission denied"
    return (exc.strerror or str(exc) or exc.__class__.__name__).lower()


def load_camera(path: str | Path) -> PinholeCamera:
    """A camera from a JSON file (contract format) or an OpenCV YAML/XML calibration file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")  # (a BOM, as Windows tools write, is not part of the JSON)
    except UnicodeDecodeError:  # (a mesh or an image given as --camera: Python's codec error was shown)
        raise SpecError(f"{path}: not a camera file (JSON or OpenCV YAML): it is not text") from None
    except OSError as exc:
        raise SpecError(f"cannot read camera file {path}: {_unreadable(exc)}") from None
    if path.suffix.lower() in (".yml", ".yaml", ".xml") or text.lstrip().startswith("%YAML"):
        return _camera_from_yaml(path)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SpecError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except RecursionError:
        raise SpecError(f"{path}: not valid JSON (nested too deeply)") from None
    return camera_from_dict(data, str(path))


def camera_to_dict(camera: PinholeCamera) -> dict:
    """The contract's JSON form of a camera (for manifests and round trips)."""
    return {
        "width": camera.width, "height": camera.height,
        "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
        "dist_coeffs": [float(x) for x in camera.dist_coeffs],
    }


RESIZE_ASPECT_TOLERANCE = 0.01  # relative difference of the two scale factors still read as one resize


def resized_for(camera: PinholeCamera, width: int, height: int,
                what: str = "a resized video") -> tuple[PinholeCamera, str | None]:
    """The camera for ``width`` × ``height`` images when they are its own images resized (the
    same aspect ratio, the two scale factors within 1 %): its intrinsics scaled
    (:meth:`~quatrack.tracking.camera.PinholeCamera.scaled`, pixel centres kept), with a note
    saying so; otherwise the camera as it is and None (a camera sized by its images, the same
    size, or another aspect ratio, which the caller refuses as before). Why: a video recorded
    at 1280 × 720 and shared at 640 × 360 was refused frame by frame with a camera calibrated at
    full size, while the browser viewer scaled it.

    >>> cam = PinholeCamera(1000.0, 1000.0, 639.5, 359.5, width=1280, height=720)
    >>> small, note = resized_for(cam, 640, 360)
    >>> small.fx, small.cx, small.width, note
    (500.0, 319.5, 640, 'the camera is for 1280×720 px images and these are 640×360 px: its intrinsics scaled by 0.5 (a resized video)')
    >>> resized_for(cam, 640, 480)[1] is None
    True
    """
    if camera.width is None or camera.height is None or (camera.width, camera.height) == (width, height):
        return camera, None
    sx, sy = width / camera.width, height / camera.height
    if abs(sx - sy) > RESIZE_ASPECT_TOLERANCE * max(sx, sy):
        return camera, None
    s = 0.5 * (sx + sy)
    return (replace(camera.scaled(sx, width, height), fy=camera.fy * sy, cy=sy * (camera.cy + 0.5) - 0.5),
            f"the camera is for {camera.width}×{camera.height} px images and these are {width}×{height} px: "
            f"its intrinsics scaled by {s:.3g} ({what})")


# A principal point within this share of the image's size from its centre is "at the centre";
# one this far from the stated size's centre is "not" (a calibration's lies within a few %).
CENTRE_NEAR, CENTRE_FAR = 0.05, 0.15


def stated_size_doubt(camera: PinholeCamera, width: int, height: int) -> str | None:
    """Why the camera's stated size, not the image, is wrong, or None: its principal point is the
    centre of the ``width`` × ``height`` image as it is and far from the centre of the size the
    camera states — the intrinsics of this image under another image's width and height (a
    camera file copied from another resolution), which scaling would halve or double (``locate``
    found nothing, a warning about a resized video its one clue).

    >>> cam = PinholeCamera(600.0, 600.0, 319.5, 239.5, width=1280, height=960)
    >>> stated_size_doubt(cam, 640, 480)
    'the camera states 1280×960 px images but its principal point (319.5, 239.5) is the centre of this 640×480 px image: are its width and height wrong?'
    >>> stated_size_doubt(PinholeCamera(1200.0, 1200.0, 639.5, 479.5, width=1280, height=960), 640, 480) is None
    True
    """
    if camera.width is None or camera.height is None or (camera.width, camera.height) == (width, height):
        return None
    here = max(abs((camera.cx + 0.5) / width - 0.5), abs((camera.cy + 0.5) / height - 0.5))
    stated = max(abs((camera.cx + 0.5) / camera.width - 0.5), abs((camera.cy + 0.5) / camera.height - 0.5))
    if here > CENTRE_NEAR or stated < CENTRE_FAR:
        return None
    return (f"the camera states {camera.width}×{camera.height} px images but its principal point "
            f"({camera.cx:g}, {camera.cy:g}) is the centre of this {width}×{height} px image: are its width and "
            f"height wrong?")

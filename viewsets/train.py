"""Offline training: object spec → RFCH model + SIFT viewsets (registered and novel views).

Every input is checked before any work is stored; the model reaches the store only through
:func:`quatrack.viewsets.store.save_model`, which is atomic.
"""

from __future__ import annotations

import dataclasses
import platform
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Callable

import cv2
import numpy as np

from .camera import check_lens, check_plausible, within_pixels
from .errors import SpecError
from .imagefile import truncated
from .mesh import Mesh, load_mesh
from .novel import NovelViewParams, novel_poses, render_textured_view
from .register import check_clicked_view
from .render import RenderBuffers, render
from .rfch import RFCHParams, train_rfch
from .spec import ObjectSpec, ViewSpec
from .store import ObjectModel
from .texture import crop_reference
from .viewset import Viewset, ViewsetParams, build_viewset

__all__ = ["TrainParams", "train_object", "check_pose", "keypoint_density", "read_mask"]


@dataclass(frozen=True)
class TrainParams:
    """All training options; ``novel=None`` trains on the registered views only."""

    rfch: RFCHParams = field(default_factory=RFCHParams)
    viewsets: ViewsetParams = field(default_factory=ViewsetParams)
    novel: NovelViewParams | None = field(default_factory=NovelViewParams)
    jobs: int = 1
    min_keypoints: int = 20
    # Weak texture: while the registered views give fewer SIFT keypoints than this per 10 000 px
    # of the object's box (the median over the views: :func:`keypoint_density`), SIFT's contrast
    # threshold is halved, down to ``min_contrast_threshold``, and the viewsets are built again
    # (the threshold is stored with the model, so its queries and the tracker use it too).
    # None: never lowered. See :func:`train_object`.
    min_keypoint_density: float | None = 10.0
    min_contrast_threshold: float = 0.01

    def __post_init__(self) -> None:
        # (min_keypoints="20" ended in "'<' not supported between 'int' and 'str'" after the
        # viewsets were built; a dict for rfch in AttributeError 'n_clusters' deep in training)
        for name, kind in (("rfch", RFCHParams), ("viewsets", ViewsetParams)):
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"{name}: a {kind.__name__}, got {type(getattr(self, name)).__name__}")
        if self.novel is not None and not isinstance(self.novel, NovelViewParams):
            raise TypeError(f"novel: a NovelViewParams or None, got {type(self.novel).__name__}")
        for name in ("jobs", "min_keypoints"):
            v = getattr(self, name)
            if not (_real(v) and float(v).is_integer() and v >= 0):
                raise ValueError(f"{name} must be a whole number >= 0, not {v!r}"[:120])
            object.__setattr__(self, name, int(v))
        if self.min_keypoint_density is not None and not (_real(self.min_keypoint_density)
                                                          and self.min_keypoint_density >= 0):
            raise ValueError(f"min_keypoint_density must be None or a number >= 0, not {self.min_keypoint_density!r}"[:120])
        if not (_real(self.min_contrast_threshold) and self.min_contrast_threshold > 0):
            raise ValueError(f"min_contrast_threshold must be a number above 0, not {self.min_contrast_threshold!r}"[:120])


def _real(v) -> bool:
    """A finite real number, not a bool or a string."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_)) \
        and bool(np.isfinite(v))


@dataclass(frozen=True)
class _View:
    spec: ViewSpec
    image: np.ndarray
    mask: np.ndarray  # uint8 0/255: object pixels (user mask, else the projected mesh)
    buffers: RenderBuffers


def _read(path, flags: int, where: str) -> np.ndarray:
    """An image file decoded by OpenCV (``flags``: as ``cv2.imread``'s, EXIF orientation applied),
    or a :class:`SpecError` naming ``where``: missing, not a file, truncated, not an image."""
    if not path.exists():
        raise SpecError(f"{where}: file not found")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SpecError(f"{where}: cannot read ({exc.strerror or exc})") from None
    if truncated(data):  # (OpenCV decodes it anyway, its missing part grey: the model would learn the grey)
        raise SpecError(f"{where}: the file is truncated (its end is missing)")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    if img is None:
        raise SpecError(f"{where}: unreadable image")
    return img


def _read_image(view: ViewSpec) -> np.ndarray:
    where = f"view {view.index}: image {view.image_path}"
    img = _read(view.image_path, cv2.IMREAD_COLOR, where)
    cam = view.camera
    if cam.width is None and cam.height is None:  # (a camera sized by its images: _sized_by)
        return img
    if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
        turned, hint = "", ""  # (a phone's portrait photo: its pixels stored sideways, an EXIF tag to turn them)
        if (img.shape[0], img.shape[1]) == (cam.width, cam.height):
            stored = cv2.imread(str(view.image_path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
            if stored is not None and stored.shape[:2] != img.shape[:2]:
                turned = f" as shown (its EXIF orientation turns the {stored.shape[1]}×{stored.shape[0]} pixels it stores)"
                hint = ": give the camera and pose of the photo as shown"
        raise SpecError(
            f"{where}: image is {img.shape[1]}×{img.shape[0]}{turned} but the view's camera is {cam.width}×{cam.height}{hint}"
        )
    return img


MIN_VIEW_PIXELS = 1024  # object pixels a view must show to be worth learning from (32 × 32)


def check_pose(mesh: Mesh, view: ViewSpec, buffers: RenderBuffers | None = None, min_pixels: int = MIN_VIEW_PIXELS) -> RenderBuffers:
    """Refuse poses that put the object behind the camera, or a view that shows too little of it.

    A view with part of the object outside the image (or covered, with a mask) is accepted: its
    visible part is learned. Only a view whose visible silhouette has fewer than ``min_pixels``
    pixels is refused, with the numbers (how much is inside, of how much)."""
    X = view.pose.apply(mesh.vertices)
    if np.any(X[:, 2] <= 0):
        hint = _xyzw_hint(mesh, view, min_pixels) or "is the pose object → camera, and its t in the mesh's units?"
        raise SpecError(f"view {view.index}: pose puts the object (partly) behind the camera (min z = {X[:, 2].min():.3g}): "
                        f"{hint}")
    buffers = buffers or render(mesh, view.camera, view.pose)
    seen = int(np.count_nonzero(buffers.face >= 0))
    if seen < min_pixels:
        uv = view.camera.project(X).astype(np.float32)
        hull_area = cv2.contourArea(cv2.convexHull(uv))
        hint = _xyzw_hint(mesh, view, min_pixels) or "is the pose right (object → camera, its t in the mesh's units)?"
        raise SpecError(
            f"view {view.index}: the object shows only {seen} pixels inside the image (of ~{hull_area:.0f} "
            f"for its whole silhouette; at least {min_pixels} are needed to learn from): {hint}"
        )
    return buffers


XYZW_HINT = "is the quaternion in [x, y, z, w] order? the spec wants [w, x, y, z]"


def _xyzw_hint(mesh: Mesh, view: ViewSpec, min_pixels: int) -> str:
    """:data:`XYZW_HINT` with what the other reading gives, when the view's ``q_wxyz`` read as
    ``[x, y, z, w]`` puts the object in front of the camera and shows it (``min_pixels``), else ""
    (a spec in scipy's order was told of units and of the pose's direction only)."""
    alt = view.xyzw_pose
    if alt is None or np.any(alt.apply(mesh.vertices)[:, 2] <= 0):
        return ""
    seen = int(np.count_nonzero(render(mesh, view.camera, alt).face >= 0))
    if seen < min_pixels:
        return ""
    return f"{XYZW_HINT} (read so, {seen} pixels of the object are inside the image)"


# A photo larger than this is trained downscaled, its camera with it, as `locate` reads a query
# (recognition.images.DEFAULT_MAX_PIXELS): at 6000×4000 px training took 10 GB of memory and 80 s
# for a model of keypoints and colour pairs at scales no query (≤ 4 MP) shows.
MAX_PHOTO_PIXELS = 4_000_000


def _within_pixels(view: ViewSpec, image: np.ndarray) -> tuple[ViewSpec, np.ndarray]:
    """The view and its photo, downscaled with its camera when over :data:`MAX_PHOTO_PIXELS`
    (:func:`~.camera.within_pixels`, as recognition reads a query)."""
    small, camera, _ = within_pixels(image, view.camera, MAX_PHOTO_PIXELS)
    return dataclasses.replace(view, camera=camera), small


def _sized_by(view: ViewSpec, image: np.ndarray) -> ViewSpec:
    """The view with its camera sized by its photo when the camera file gives no size (an OpenCV
    YAML with only ``camera_matrix`` / ``distortion_coefficients``, as the contract allows),
    checked for plausibility at that size."""
    cam = view.camera
    if cam.width is not None or cam.height is not None:
        return view
    h, w = image.shape[:2]
    check_plausible(cam.fx, cam.fy, cam.cx, cam.cy, w, h, f"view {view.index}: camera")
    sized = dataclasses.replace(cam, width=w, height=h)
    check_lens(sized, f"view {view.index}: camera")  # (its lens model at the photo's size, as a sized camera's)
    return dataclasses.replace(view, camera=sized)


def read_mask(view: ViewSpec, shape: tuple[int, int]) -> np.ndarray:
    """The view's mask as stored, one channel (non-zero: the object), checked against its photo's
    ``shape`` (h, w) — a :class:`SpecError` naming it otherwise. Read as stored: a 16-bit mask's
    labels (1 = object) were 0 once brought to 8 bits; a colour mask's any channel non-zero, with
    transparency its alpha channel (a cut-out)."""
    m = _read(view.mask_path, cv2.IMREAD_UNCHANGED, f"view {view.index}: mask {view.mask_path}")
    if m.ndim == 3:
        m = m[..., 3] if m.shape[2] == 4 else m.max(axis=2)
    if m.shape != tuple(shape):
        raise SpecError(f"view {view.index}: mask {view.mask_path}: size {m.shape[::-1]} differs from the image's")
    return m


def _prepare_view(mesh: Mesh, view: ViewSpec, warn=None) -> _View:
    image = _read_image(view)
    view = _sized_by(view, image)
    if view.pose_from_points:  # (its pose solved from clicks by load_spec: checked now its camera is sized)
        check_clicked_view(view, mesh, warn)
    full = image.shape[:2]
    view, image = _within_pixels(view, image)
    buffers = check_pose(mesh, view)
    mask = buffers.mask
    if view.mask_path is not None:
        m = read_mask(view, full)
        if m.shape != mask.shape:  # (the photo was downscaled)
            m = cv2.resize((m > 0).astype(np.uint8), mask.shape[::-1], interpolation=cv2.INTER_NEAREST)
        mask = np.where(m > 0, 255, 0).astype(np.uint8)
        if not np.any(mask):
            raise SpecError(f"view {view.index}: mask {view.mask_path}: empty (no non-zero pixel)")
        visible = int(np.count_nonzero((mask > 0) & (buffers.face >= 0)))
        if visible < MIN_VIEW_PIXELS:
            raise SpecError(
                f"view {view.index}: mask {view.mask_path}: only {visible} pixels of the object are unmasked and "
                f"inside the image (at least {MIN_VIEW_PIXELS} are needed to learn from)"
            )
    return _View(view, image, mask, buffers)


def _tasks(mesh: Mesh, views: list[_View], novel: NovelViewParams | None):
    """(label, view, pose or None): None = the registered view itself."""
    out = []
    for v in views:
        out.append((f"view{v.spec.index}", v, None))
        if novel is not None:
            for label, pose in novel_poses(mesh, v.spec.pose, novel):
                out.append((f"view{v.spec.index}-{label}", v, pose))
    return out


def _run_task(mesh: Mesh, params: TrainParams, task, run_buffers: dict) -> Viewset:
    """One viewset: a registered view's keypoints lifted onto ``mesh``; a synthetic view rendered,
    textured from its photo and lifted on ``mesh.run_time`` (``run_buffers``: the photo's
    z-buffer on it, by view index, when it is not ``mesh``: :func:`_build_viewsets`).

    Why the decimation there: a scan's facets, each a plane of its own and (at 10⁵–10⁶ faces)
    under a photo pixel wide, with normals the jitter scatters, are textured from the photo only
    where a neighbour turns by less than 30° (render_textured_view): the cookie box as 786 432
    jittered triangles kept no synthetic view, as 49 152 half the keypoints; its decimation's
    facets are the surface's, a few pixels wide. A planar or coarse mesh is its own run-time
    mesh: nothing changes for it."""
    label, v, pose = task
    if pose is None:
        feature_mask = cv2.bitwise_and(v.mask, v.buffers.mask)
        return build_viewset(label, v.spec.index, False, v.image, feature_mask, v.spec.camera, v.spec.pose,
                             mesh, v.buffers, params.viewsets)
    run = mesh.run_time
    src_buffers = v.buffers if run is mesh else run_buffers[v.spec.index]
    cam = dataclasses.replace(v.spec.camera, dist_coeffs=np.zeros(5))  # novel views: ideal pinhole
    min_cos = params.novel.min_source_cos if params.novel else 0.3
    img, textured, buf = render_textured_view(run, run.plane_ids, v.image, v.spec.camera, v.spec.pose, src_buffers,
                                              cam, pose, min_cos, v.mask if v.spec.mask_path is not None else None)
    return build_viewset(label, v.spec.index, True, img, textured, cam, pose, run, buf, params.viewsets)


def _versions() -> dict:
    """Library versions for the manifest (the package's from its metadata: the viewsets layer does
    not import the application package)."""
    from importlib.metadata import PackageNotFoundError, version

    import trimesh

    try:
        qv = version("quatrack")
    except PackageNotFoundError:
        qv = "unknown"
    return {"quatrack": qv, "numpy": np.__version__, "opencv": cv2.__version__,
            "trimesh": trimesh.__version__, "python": platform.python_version()}


def train_object(
    spec: ObjectSpec,
    params: TrainParams = TrainParams(),
    progress: Callable[[int], None] | None = None,
    warn: Callable[[str], None] | None = None,
    on_total: Callable[[int], None] | None = None,
    check: Callable[[ObjectSpec, Mesh], list[str]] | None = None,
) -> ObjectModel:
    """Train the object of ``spec``; raises :class:`SpecError` (naming the culprit) on bad input.

    ``on_total(n)`` is told the number of viewsets to build and ``progress(1)`` is called after
    each one (for a progress bar); ``warn`` receives non-fatal problems (a view with few keypoints),
    first those ``check(spec, mesh)`` (optional) returns once the views are read — or raises, a
    :class:`SpecError` refusing a view before any viewset is built (the CLI's: a ``q_wxyz``
    that fits its photo only read ``[x, y, z, w]``).
    Three steps: the views are read and checked against the mesh, the viewsets (registered and
    synthetic) are built — again, with SIFT's contrast threshold halved, while the registered
    views show too little texture (:func:`keypoint_density` under ``params.min_keypoint_density``,
    down to ``params.min_contrast_threshold``; one warning says so) — then the RFCH model, sized
    by the viewsets' boxes.
    """
    if not isinstance(spec, ObjectSpec):  # (a spec file's path: AttributeError 'mesh_path')
        raise TypeError(f"spec: an ObjectSpec (quatrack.viewsets.spec.load_spec(path) reads one), "
                        f"got {type(spec).__name__}")
    if not isinstance(params, TrainParams):  # (a dict: AttributeError 'viewsets')
        raise TypeError(f"params: a TrainParams (quatrack.viewsets.train), got {type(params).__name__}")
    t0 = time.perf_counter()
    mesh = load_mesh(spec.mesh_path, warn=warn)
    views = [_prepare_view(mesh, v, warn) for v in spec.views]
    doubts = check(spec, mesh) if check is not None else []  # (run without warn too: it may refuse)
    asked = params.viewsets.contrast_threshold
    viewsets, params, weak = _viewsets_for_texture(mesh, _tasks(mesh, views, params.novel), params, progress, on_total)
    viewsets, thin = _checked(viewsets, params)  # (raises: nothing to learn even at the lowest threshold)
    for msg in doubts if warn else ():  # the poses' doubts before the texture's (a wrong pose makes weak
        warn(msg)  # texture too), but after the refusal of a view with nothing to learn: bad input is one line
    if warn and thin:  # (the thin viewsets, in one line)
        warn(thin[0])
    if warn and params.viewsets.contrast_threshold != asked:  # (one warning, once the model is sure)
        warn(f"weak texture: {weak:.1f} keypoints per 10 000 px of the object in its registered views "
             f"(fewer than {params.min_keypoint_density:g}); trained with SIFT's contrast threshold lowered to "
             f"{params.viewsets.contrast_threshold:g} ({keypoint_density(viewsets):.1f} keypoints per 10 000 px)")
    for msg in thin[1:] if warn else ():  # (what it means, last: the model will hardly be found elsewhere)
        warn(msg)
    rfch = _train_rfch(views, viewsets, params)
    if progress:
        progress(1)
    manifest = _manifest(spec, params, mesh, views, viewsets, rfch, time.perf_counter() - t0)
    appearance = [crop_reference(v.image, v.spec.camera, v.spec.pose, cv2.bitwise_and(v.mask, v.buffers.mask))
                  for v in views]
    return ObjectModel(spec.name, rfch, viewsets, mesh, manifest, [r for r in appearance if r is not None])


def keypoint_density(viewsets: list[Viewset]) -> float:
    """SIFT keypoints (with 3-D points) per 10 000 px of the object's box, the median over the
    registered (not synthetic) viewsets: ``median(10⁴ · n_v / (w_v · h_v))``. It says how
    textured the object looks, whatever its size in the photos; the zoo's objects read 31–62 and
    the bundled cookie box 65, the weakly textured tall box (a night sky) 3 (bench/RESULTS.md,
    session 46). 0 when no registered view kept any.

    >>> from types import SimpleNamespace as V
    >>> keypoint_density([V(synthetic=False, keypoints=range(50), bbox=(0, 0, 100, 100)),
    ...                   V(synthetic=True, keypoints=range(5), bbox=(0, 0, 100, 100))])
    50.0
    """
    d = [1e4 * len(vs.keypoints) / max(vs.bbox[2] * vs.bbox[3], 1) for vs in viewsets if not vs.synthetic]
    return float(np.median(d)) if d else 0.0


def _viewsets_for_texture(mesh: Mesh, tasks: list, params: TrainParams, progress,
                          on_total) -> tuple[list[Viewset], TrainParams, float]:
    """The viewsets of ``tasks``, built again with SIFT's contrast threshold halved while the
    registered views give fewer than ``params.min_keypoint_density`` keypoints per 10 000 px
    (:func:`keypoint_density`), down to ``params.min_contrast_threshold``. Returns them, the
    parameters they were built with (the threshold the model keeps) and the density at the
    threshold first asked for. Why: SIFT's threshold is a share of the full grey scale, so a
    dark or weakly textured object keeps a handful of keypoints a view at the default (the zoo's
    tall box: 11–22, found in 10 % of its scenes; at 0.01: 49–107, 27 %; bench/RESULTS.md, session 46)."""
    # the threshold is decided on the registered views alone; the synthetic ones (the bulk) are
    # built once, at the threshold kept
    registered = [i for i, t in enumerate(tasks) if t[2] is None]
    total = len(tasks) + 1  # (+ the RFCH model)
    if on_total:
        on_total(total)
    built = _build_viewsets(mesh, [tasks[i] for i in registered], params, progress)
    first = density = keypoint_density(built)
    while (params.min_keypoint_density is not None and density < params.min_keypoint_density
           and not _capped(built, params.viewsets.max_features)
           and params.viewsets.contrast_threshold / 2 >= params.min_contrast_threshold * (1 - 1e-9)):
        params = dataclasses.replace(params, viewsets=dataclasses.replace(
            params.viewsets, contrast_threshold=params.viewsets.contrast_threshold / 2))
        total += len(registered)
        if on_total:
            on_total(total)
        built = _build_viewsets(mesh, [tasks[i] for i in registered], params, progress)
        density = keypoint_density(built)
    synthetic = [i for i, t in enumerate(tasks) if t[2] is not None]
    built += _build_viewsets(mesh, [tasks[i] for i in synthetic], params, progress)
    order = np.argsort(registered + synthetic, kind="stable")  # (back in the tasks' order)
    return [built[k] for k in order], params, first


def _capped(viewsets: list[Viewset], max_features: int) -> bool:
    """Whether the registered views keep at least half the keypoints SIFT may give (the median
    over them, of ``max_features``): a lower contrast threshold cannot add many, however few they
    are per pixel of a large box (a high-resolution photo: 6000×4000 px read 1.5 per 10 000 px
    with 1384 keypoints, and was built three times more for nothing, with a false warning).

    >>> from types import SimpleNamespace as V
    >>> _capped([V(synthetic=False, keypoints=range(1400))], 1500), _capped([V(synthetic=False, keypoints=range(20))], 1500)
    (True, False)
    """
    n = [len(vs.keypoints) for vs in viewsets if not vs.synthetic]
    return bool(n) and float(np.median(n)) >= 0.5 * max_features


def _build_viewsets(mesh: Mesh, tasks: list, params: TrainParams, progress) -> list[Viewset]:
    """One viewset per task (``_tasks``: each registered view and each synthetic view), built
    on ``params.jobs`` threads (OpenCV releases the GIL)."""
    # each photo's z-buffer on the run-time mesh, once for all its synthetic views (_run_task)
    photos = {v.spec.index: v for _, v, pose in tasks if pose is not None}
    run_mesh = mesh.run_time if photos else mesh
    run_buffers = {} if run_mesh is mesh else {i: render(run_mesh, v.spec.camera, v.spec.pose) for i, v in photos.items()}

    def run(task):
        vs = _run_task(mesh, params, task, run_buffers)
        if progress:
            progress(1)
        return vs

    jobs = max(1, int(params.jobs))
    if jobs == 1:
        viewsets = [run(t) for t in tasks]
    else:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            viewsets = list(pool.map(run, tasks))
    return viewsets


def _checked(viewsets: list[Viewset], params: TrainParams) -> tuple[list[Viewset], list[str]]:
    """The viewsets with keypoints, and what to warn of the thin ones (:func:`_thin_notes`);
    raises when no registered view has any."""
    if not any(len(vs) for vs in viewsets if not vs.synthetic):
        raise SpecError("no keypoints in any registered view (SIFT's contrast threshold down to "
                        f"{params.viewsets.contrast_threshold:g}): is the object textured, and the pose right?")
    return [vs for vs in viewsets if len(vs) > 0], _thin_notes(viewsets, params.min_keypoints)


def _thin_notes(viewsets: list[Viewset], min_keypoints: int) -> list[str]:
    """What to say of the viewsets with fewer than ``min_keypoints`` keypoints (with 3-D
    points): one line for them all — how many, their counts, which were dropped for having none
    — and, when most synthetic views (those around the photos) are so thin, a plain line that
    the model will hardly be found from other viewpoints than its photos'. Why one line: a
    textureless box gave 15 lines, one per viewset, while the two dropped went unsaid (the
    summary's "13 viewsets" then disagreed with them) and nothing said what it meant.
    """
    thin = [vs for vs in viewsets if len(vs) < min_keypoints]
    if not thin:
        return []
    registered = [f"{vs.label}: {len(vs)}" for vs in thin if not vs.synthetic]
    synthetic = [len(vs) for vs in thin if vs.synthetic]
    if synthetic:
        registered.append(f"{len(synthetic)} synthetic: {min(synthetic)}–{max(synthetic)}" if len(synthetic) > 1
                          else f"1 synthetic: {synthetic[0]}")
    has = "has" if len(thin) == 1 else "have"
    line = (f"{len(thin)} of {len(viewsets)} viewset{'s' if len(viewsets) > 1 else ''} {has} fewer than "
            f"{min_keypoints} keypoints with 3-D points ({'; '.join(registered)})")
    empty = [vs.label for vs in thin if len(vs) == 0]
    if empty:
        named = ", ".join(empty[:4]) + (", …" if len(empty) > 4 else "")
        line += (f"; {len(empty)} with none {'is' if len(empty) == 1 else 'are'} dropped ({named}): "
                 f"nothing in {'it' if len(empty) == 1 else 'them'} to match")
    out = [line]
    n_synthetic = sum(vs.synthetic for vs in viewsets)
    if n_synthetic and len(synthetic) > n_synthetic / 2:
        out.append(f"most views around the photos ({len(synthetic)} of {n_synthetic} synthetic) show almost none "
                   f"of the object's texture: the model will hardly be found from other viewpoints than the photos'")
    return out


def _train_rfch(views: list[_View], viewsets: list[Viewset], params: TrainParams):
    """The RFCH model of the registered views' object pixels, with the window sizes the search
    may try: from the smallest to the largest viewset box."""
    rfch = train_rfch([v.image for v in views], [v.mask for v in views], params.rfch)
    sizes = np.array([vs.bbox[2:] for vs in viewsets])
    return dataclasses.replace(rfch, size_min=tuple(int(x) for x in sizes.min(0)),
                               size_max=tuple(int(x) for x in sizes.max(0)))


def _manifest(spec: ObjectSpec, params: TrainParams, mesh: Mesh, views: list[_View], viewsets: list[Viewset],
              rfch, elapsed: float) -> dict:
    """What was trained from what, with which parameters and libraries (the store's manifest.json)."""
    summary = {
        "views": len(views),
        "viewsets": len(viewsets),
        "synthetic_viewsets": sum(vs.synthetic for vs in viewsets),
        "keypoints_per_viewset": {vs.label: len(vs) for vs in viewsets},
        "points3d_total": int(sum(len(vs) for vs in viewsets)),
        "histogram_bins": int(rfch.histogram.size),
        "train_seconds": round(elapsed, 3),
    }
    return {
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "spec": {"path": str(spec.path), "sha256": spec.checksum},
        "parameters": {
            "rfch": dataclasses.asdict(params.rfch),
            "viewsets": dataclasses.asdict(params.viewsets),
            "novel_views": dataclasses.asdict(params.novel) if params.novel else None,
            "jobs": max(1, int(params.jobs)),
        },
        "rfch": {"size_min": list(rfch.size_min), "size_max": list(rfch.size_max)},
        "library_versions": _versions(),
        "training_summary": summary,
        "mesh": {"path": str(spec.mesh_path), "vertices": len(mesh.vertices), "faces": len(mesh.faces)},
    }

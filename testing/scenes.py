"""Rendered scenes with known poses: the ground truth for recognition and tracking benchmarks.

The object is rendered at a chosen pose, textured from its registered photo (faces the photo
does not show get the photo's median object colour), and composited over a background. The
backgrounds are real: frames of the bundled ``box.mp4`` with the real box inpainted away (where
it is, is known from a verified pose per frame), stored as files (:mod:`.backgrounds`). Then the
image is degraded as a camera would: colour cast and gain, blur, noise, JPEG, and optionally an
occluding patch.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from quatrack.examples import example_dir
from quatrack.tracking import quaternion as quat
from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.mesh import Mesh, load_mesh
from quatrack.viewsets.novel import render_textured_view, rotate_about_centre
from quatrack.viewsets.render import render
from quatrack.tracking.pose import Pose
from quatrack.viewsets.spec import ObjectSpec, load_spec

EXAMPLE = example_dir()


@dataclass(frozen=True)
class Scene:
    """An image with its truth: pose (object → camera), silhouette mask, bounding box (x, y, w, h)."""

    image: np.ndarray
    pose: Pose
    mask: np.ndarray
    bbox: tuple[float, float, float, float]
    view_angle_deg: float  # rotation away from the registered view
    occluded: float  # fraction of the silhouette hidden by the occluder


@dataclass
class Renderer:
    """Renders one object (from its spec) into a camera."""

    spec: ObjectSpec
    mesh: Mesh
    groups: np.ndarray
    photo: np.ndarray
    photo_buffers: object
    fill: np.ndarray  # BGR for faces the photo does not show

    @classmethod
    def from_spec(cls, spec_path: str | Path) -> "Renderer":
        spec = load_spec(spec_path)
        mesh = load_mesh(spec.mesh_path)
        view = spec.views[0]
        photo = cv2.imread(str(view.image_path), cv2.IMREAD_COLOR)
        buffers = render(mesh, view.camera, view.pose)
        fill = np.median(photo[buffers.face >= 0], axis=0)
        return cls(spec, mesh, mesh.plane_ids, photo, buffers, fill)

    def render(self, camera: PinholeCamera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """The object alone (BGR) and its silhouette mask (bool)."""
        view = self.spec.views[0]
        img, textured, buf = render_textured_view(
            self.mesh, self.groups, self.photo, view.camera, view.pose, self.photo_buffers, camera, pose
        )
        sil = buf.face >= 0
        img = img.copy()
        img[sil & (textured == 0)] = self.fill
        return img, sil


def bbox_of(mask: np.ndarray) -> tuple[float, float, float, float]:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return (0.0, 0.0, 0.0, 0.0)
    return (float(xs.min()), float(ys.min()), float(xs.max() - xs.min() + 1), float(ys.max() - ys.min() + 1))


def video_backgrounds(limit: int = 20) -> tuple[np.ndarray, ...]:
    """The first ``limit`` (at most 20) room backgrounds: frames of the bundled video with the real
    box inpainted away, frozen as files (:mod:`quatrack.testing.backgrounds`), so that a change
    to recognition does not redraw the scenes. Read-only arrays shared by every caller."""
    from .backgrounds import frozen_backgrounds

    return frozen_backgrounds()[:limit]


def inpaint_video_backgrounds(video: str = str(EXAMPLE / "box.mp4"), every: int = 23, limit: int = 20) -> tuple[np.ndarray, ...]:
    """Frames of the bundled video with the real box inpainted away, computed now (~10 s CPU; what
    ``python -m quatrack.testing.backgrounds`` stores).

    The box is found in each frame by whole-image recognition; frames where it is not verified
    are skipped (the box could not be removed from them). The result depends on where
    recognition puts the box: benchmarks and tests use the stored :func:`video_backgrounds`.
    """
    from quatrack.recognition.locate import LocateParams, locate
    from quatrack.recognition.match import index_for
    from quatrack.viewsets.camera import load_camera

    model = _example_model()
    cam = load_camera(EXAMPLE / "camera.json")
    index = index_for(model)
    cap = cv2.VideoCapture(video)
    out = []
    i = 0
    while len(out) < limit:
        ok, frame = cap.read()
        if not ok:
            break
        if i % every == 0:
            r = locate(frame, cam, model, LocateParams(use_window=False), index=index)
            if r.found:
                sil = render(model.mesh, cam, Pose(r.q_wxyz, r.t)).face >= 0
                hole = cv2.dilate(sil.astype(np.uint8) * 255, np.ones((25, 25), np.uint8))
                out.append(cv2.inpaint(frame, hole, 7, cv2.INPAINT_TELEA))
        i += 1
    cap.release()
    return tuple(out)


@lru_cache(maxsize=1)
def example_store() -> Path:
    """A temporary model store holding the bundled example trained with the default parameters,
    trained once per process (benchmarks and tests must not depend on the user's store). Treat it
    as read-only: every caller in the process shares it."""
    import atexit
    import shutil
    import tempfile

    from quatrack.viewsets.store import save_model
    from quatrack.viewsets.train import train_object

    store = Path(tempfile.mkdtemp(prefix="quatrack-bench-"))
    # (removed when the process ends: every bench locate/track run and test session left one behind)
    atexit.register(shutil.rmtree, store, True)
    save_model(store, train_object(load_spec(EXAMPLE / "object.json")))
    return store


@lru_cache(maxsize=1)
def _example_model():
    from quatrack.viewsets.store import load_model

    return load_model(example_store(), load_spec(EXAMPLE / "object.json").name)


def example_model():
    """The bundled cookie box, trained with the default parameters (cached per process)."""
    return _example_model()


@dataclass(frozen=True)
class SceneParams:
    max_angle_deg: float = 60.0
    distance_scale: tuple[float, float] = (0.7, 1.3)  # × the distance that makes the object fill ~45 % of the width
    occlusion: float = 0.25  # probability of an occluder
    blur_sigma: tuple[float, float] = (0.0, 1.2)
    noise_sigma: tuple[float, float] = (1.0, 4.0)
    colour_cast: float = 0.15  # per-channel gain spread
    jpeg_quality: tuple[int, int] = (70, 95)


def random_scene(
    rng: np.random.Generator, renderer: Renderer, camera: PinholeCamera, backgrounds, params: SceneParams = SceneParams(),
    angle_deg: float | None = None,
) -> Scene:
    """One scene: the object turned by ``angle_deg`` (random if None) about a random axis away from
    its registered view, at a random distance and place, over a random background."""
    view = renderer.spec.views[0]
    mesh = renderer.mesh
    angle = rng.uniform(0.0, params.max_angle_deg) if angle_deg is None else angle_deg
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    turned = rotate_about_centre(view.pose, mesh.centre, np.radians(angle) * axis)
    # place: the object's centre on a ray through a random pixel, at a distance that makes it
    # about 45 % of the image width (times a random scale)
    extent = mesh.extent
    z = camera.fx * extent / (0.45 * camera.width) * rng.uniform(*params.distance_scale)
    for _ in range(20):
        u = rng.uniform(0.3, 0.7) * camera.width
        v = rng.uniform(0.3, 0.7) * camera.height
        ray = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
        c_cam = ray * z
        t = c_cam - turned.R @ mesh.centre
        pose = Pose(turned.q_wxyz, t)
        obj, sil = renderer.render(camera, pose)
        if sil.any() and sil[[0, -1], :].sum() + sil[:, [0, -1]].sum() == 0:
            break
    bg = backgrounds[int(rng.integers(len(backgrounds)))]
    bg = cv2.resize(bg, (camera.width, camera.height))
    if rng.uniform() < 0.5:
        bg = bg[:, ::-1]
    img = bg.copy()
    img[sil] = obj[sil]
    # a shading gradient across the object (light falls off), as a multiplicative ramp
    ramp = np.linspace(rng.uniform(0.75, 1.0), rng.uniform(1.0, 1.15), camera.width, dtype=np.float32)
    if rng.uniform() < 0.5:
        ramp = ramp[::-1]
    img = img.astype(np.float32)
    img[sil] *= ramp[None, :].repeat(camera.height, 0)[sil][:, None]
    occluded = 0.0
    if rng.uniform() < params.occlusion:
        x0, y0, bw, bh = bbox_of(sil)
        ow, oh = bw * rng.uniform(0.2, 0.45), bh * rng.uniform(0.2, 0.45)
        ox, oy = x0 + rng.uniform(-0.1, 0.9) * bw, y0 + rng.uniform(-0.1, 0.9) * bh
        patch = np.zeros(sil.shape, bool)
        patch[int(max(oy, 0)) : int(max(oy + oh, 0)), int(max(ox, 0)) : int(max(ox + ow, 0))] = True
        occluded = float((patch & sil).sum() / sil.sum())
        other = backgrounds[int(rng.integers(len(backgrounds)))]
        img[patch] = cv2.resize(other, (camera.width, camera.height))[patch]
    gains = 1.0 + rng.uniform(-params.colour_cast, params.colour_cast, size=3)
    img = img * gains * rng.uniform(0.8, 1.2)
    sigma = rng.uniform(*params.blur_sigma)
    if sigma > 0.3:
        img = cv2.GaussianBlur(img, (0, 0), sigma)
    img = img + rng.normal(0.0, rng.uniform(*params.noise_sigma), size=img.shape)
    img = np.clip(img, 0, 255).astype(np.uint8)
    ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(*params.jpeg_quality))])
    img = cv2.imdecode(enc, cv2.IMREAD_COLOR)
    return Scene(img, pose, sil, bbox_of(sil), float(angle), occluded)


def pose_errors(t_est, q_est, pose: Pose, mesh: Mesh) -> tuple[float, float]:
    """(translation error of the object's centre in mesh units, rotation error in degrees)."""
    R_est = quat.to_matrix(q_est)
    c = mesh.centre
    dt = float(np.linalg.norm((R_est @ c + t_est) - (pose.R @ c + pose.t)))
    dq = quat.angle_between(np.asarray(q_est), quat.from_matrix(pose.R))
    return dt, float(np.degrees(dq))

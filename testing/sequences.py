"""Rendered video sequences with ground truth: a smooth trajectory, each frame the object rendered
at its true pose over a real background with sensor noise, kept as JPEG bytes (the camera's
compression, and compact in memory).

Used by the tracking tests and ``quatrack bench track``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose

from .scenes import Renderer


@dataclass(frozen=True)
class Trajectory:
    """Object pose over time: the registered view's orientation turned about the object's centre
    by a rotation vector (object frame), the centre at ``centre(t)`` in the camera frame."""

    R0: np.ndarray
    mesh_centre: np.ndarray
    c0: np.ndarray
    pos_amp: np.ndarray  # (3,) mesh units
    pos_freq: np.ndarray  # (3,) Hz
    pos_phase: np.ndarray
    rot_amp: np.ndarray  # (3,) rad
    rot_freq: np.ndarray
    rot_phase: np.ndarray

    def pose(self, t: float) -> Pose:
        c = self.c0 + self.pos_amp * np.sin(2 * np.pi * self.pos_freq * t + self.pos_phase)
        rv = self.rot_amp * np.sin(2 * np.pi * self.rot_freq * t + self.rot_phase)
        R = self.R0 @ quat.to_matrix(quat.from_rotvec(rv))
        return Pose.from_matrix(R, c - R @ self.mesh_centre)


def lively_trajectory(renderer: Renderer, depth: float = 60.0, scale: float = 1.0, seed: int = 0) -> Trajectory:
    """A smooth, lively trajectory near the registered view; ``scale`` multiplies the motion."""
    rng = np.random.default_rng(seed)
    R0 = renderer.spec.views[0].pose.R
    return Trajectory(
        R0, renderer.mesh.centre, np.array([0.0, 0.0, depth]),
        scale * np.array([8.0, 5.0, 8.0]), np.array([0.23, 0.31, 0.17]), rng.uniform(0, 2 * np.pi, 3),
        scale * np.radians([22.0, 22.0, 18.0]), np.array([0.27, 0.19, 0.33]), rng.uniform(0, 2 * np.pi, 3),
    )


def compose(renderer: Renderer, camera: PinholeCamera, pose: Pose, background: np.ndarray,
            rng: np.random.Generator, noise: float = 2.0) -> np.ndarray:
    """The rendered object over ``background`` with sensor noise."""
    obj, sil = renderer.render(camera, pose)
    img = cv2.resize(background, (camera.width, camera.height)).astype(np.float32)
    img[sil] = obj[sil]
    img += rng.normal(0.0, noise, img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


def render_sequence(renderer: Renderer, camera: PinholeCamera, trajectory: Trajectory, n: int, fps: float,
                    background: np.ndarray, seed: int = 0, jpeg: int = 90) -> tuple[list[bytes], list[Pose]]:
    """``n`` frames as JPEG bytes (the camera's compression, and compact in memory) and their
    true poses."""
    rng = np.random.default_rng(seed)
    frames, poses = [], []
    for k in range(n):
        pose = trajectory.pose(k / fps)
        img = compose(renderer, camera, pose, background, rng)
        frames.append(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, jpeg])[1].tobytes())
        poses.append(pose)
    return frames, poses


def clutter_background(seed: int, height: int = 480, width: int = 640, blobs: int = 25) -> np.ndarray:
    """A cluttered but deterministic background: blurred colour noise stretched to 30–220, plus
    ``blobs`` filled circles of random colours (texture that is not the object's)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (height, width, 3)).astype(np.float32), (0, 0), 3.0)
    img = cv2.normalize(img, None, 30, 220, cv2.NORM_MINMAX)
    for _ in range(blobs):
        c = tuple(int(v) for v in rng.uniform(0, 255, 3))
        cv2.circle(img, (int(rng.uniform(0, width)), int(rng.uniform(0, height))), int(rng.uniform(5, 40)), c, -1)
    return img.astype(np.uint8)


@dataclass(frozen=True)
class BoxSequence:
    """The bundled cookie box along a lively trajectory: the trained model, the camera, the
    renderer, and per frame the true pose and the rendered image (decoded, BGR)."""

    model: object
    camera: PinholeCamera
    renderer: Renderer
    poses: list
    frames: list


def box_sequence(n: int, trajectory_seed: int, noise_seed: int, background: np.ndarray,
                 fps: float = 30.0) -> BoxSequence:
    """``n`` frames of the cookie box moving along :func:`lively_trajectory` (``trajectory_seed``)
    over ``background``, with sensor noise drawn from ``noise_seed``; the tracking tests' scene."""
    from quatrack.viewsets.camera import load_camera

    from .scenes import EXAMPLE, example_model

    camera = load_camera(EXAMPLE / "camera.json")
    renderer = Renderer.from_spec(EXAMPLE / "object.json")
    trajectory = lively_trajectory(renderer, seed=trajectory_seed)
    rng = np.random.default_rng(noise_seed)
    poses = [trajectory.pose(k / fps) for k in range(n)]
    frames = [compose(renderer, camera, p, background, rng) for p in poses]
    return BoxSequence(example_model(), camera, renderer, poses, frames)

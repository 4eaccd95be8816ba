"""A camera walking round an object: the rendered sequences of ``quatrack bench track-zoo``
(issue 12) and of the tests that follow an object to faces no photo shows.

The camera orbits the object's centre once (azimuth 360° about the object's z axis, starting at
the zoo's training view, azimuth 35°, elevation 25°), its elevation swinging between +25° and
−25° (so the top and the bottom come into view too), its distance breathing so that the object's
apparent size changes ×3 (``fill`` of the image width from ``fill/√3`` to ``fill·√3``). On top,
in phases given as fractions of the duration (:class:`OrbitParams`):

- **out of frame**: the object slides sideways until about ``out_share`` of it has left the image,
  and back;
- **lighting change**: the whole image's gain falls to ``light_gain`` with a colour cast and a
  ramp across the image (a lamp switched off), and stays so;
- **motion blur**: a hand's shake (a few degrees at a few Hz about the camera's x and y axes) and
  every frame blurred along the object's image motion during the exposure (a line kernel of
  that length and direction; all frames have it, the shake makes it long);
- **a passing occluder**: a blurred-edged patch of another background (a hand) sweeping across
  the object.

Per frame the truth: the pose, and how much of the object the camera really sees: ``visible`` =
pixels of the silhouette inside the image and not occluded / pixels of the whole silhouette
(rendered in a camera enlarged by an image on every side), with ``inside`` and ``occluded``
apart. Frames are kept as JPEG bytes (the camera's compression, compact in memory). Everything
is seeded.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.viewsets.render import render

from .zoo import TexturedObject, look_at, viewing_distance


@dataclass(frozen=True)
class OrbitParams:
    """The walk round the object; phases are ``(start, end)`` fractions of the duration."""

    seconds: float = 10.0
    fps: float = 30.0
    azimuth0_deg: float = 35.0  # the zoo's training view
    turns: float = 1.0
    elevation_deg: float = 25.0  # amplitude: +25° → −25° → +25° … (1.5 swings)
    elevation_swings: float = 1.5
    fill: float = 0.42  # object diameter / image width at the middle distance
    size_ratio: float = 3.0  # apparent size from fill/√ratio to fill·√ratio
    size_cycles: float = 1.25
    out_phase: tuple[float, float] = (0.27, 0.40)
    out_share: float = 0.65  # of the silhouette leaves the image at the phase's middle
    light_phase: tuple[float, float] = (0.45, 0.52)  # the ramp; the new light stays after it
    light_gain: float = 0.6
    light_cast: tuple[float, float, float] = (0.85, 1.0, 1.15)  # B, G, R gains of the new light
    blur_phase: tuple[float, float] = (0.58, 0.70)
    shake_deg: float = 1.5
    shake_hz: float = 4.0
    exposure: float = 0.5  # of the frame interval
    occluder_phase: tuple[float, float] = (0.76, 0.90)
    occluder_size: tuple[float, float] = (0.35, 0.9)  # × the silhouette's bounding box (w, h)
    noise: float = 2.0
    jpeg: int = 90


@dataclass
class OrbitSequence:
    """A rendered sequence with its truth (per frame: pose, visible/inside/occluded shares and
    the phases it is in)."""

    name: str
    camera: PinholeCamera
    fps: float
    frames: list[bytes]
    poses: list[Pose]
    visible: np.ndarray
    inside: np.ndarray
    occluded: np.ndarray
    phases: list[tuple[str, ...]] = field(default_factory=list)
    grey: bool = False  # frames handed out as one channel (a monochrome camera), converted from colour

    def __len__(self) -> int:
        return len(self.frames)

    def image(self, k: int) -> np.ndarray:
        img = cv2.imdecode(np.frombuffer(self.frames[k], np.uint8), cv2.IMREAD_COLOR)
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if self.grey else img


def _bump(x: float, phase: tuple[float, float]) -> float:
    """0 outside ``phase``, a smooth 0 → 1 → 0 (sin²) inside it."""
    a, b = phase
    if not a < x < b:
        return 0.0
    return float(np.sin(np.pi * (x - a) / (b - a)) ** 2)


def _ramp(x: float, phase: tuple[float, float]) -> float:
    """0 before ``phase``, 1 after, smooth (cosine) in between."""
    a, b = phase
    return float(np.clip(0.5 - 0.5 * np.cos(np.pi * np.clip((x - a) / (b - a), 0.0, 1.0)), 0.0, 1.0))


def orbit_pose_at(obj: TexturedObject, camera: PinholeCamera, t: float, params: OrbitParams = OrbitParams(),
                  seed: int = 0) -> Pose:
    """The true pose at time ``t`` (s): orbit, elevation swing, breathing distance, the slide out
    of the frame and the hand's shake (see the module)."""
    p = params
    x = t / p.seconds
    rng = np.random.default_rng(seed)
    sphase = rng.uniform(0, 2 * np.pi, 2)  # the shake's phases (per sequence)
    az = p.azimuth0_deg + 360.0 * p.turns * x
    el = p.elevation_deg * np.cos(2 * np.pi * p.elevation_swings * x)
    fill = p.fill * p.size_ratio ** (0.5 * np.sin(2 * np.pi * p.size_cycles * x))
    c = obj.mesh.centre
    d = viewing_distance(obj, camera, fill)
    a, e = np.radians(az), np.radians(el)
    eye = c + d * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    pose = look_at(eye, c)
    R, tr = pose.R, pose.t
    shake = _bump(x, p.blur_phase)
    if shake > 0:  # the camera turns a little about its own x and y axes (the hand's shake)
        w = 2 * np.pi * p.shake_hz * t
        rv = np.radians(p.shake_deg) * shake * np.array([np.sin(w + sphase[0]), np.cos(w + sphase[1]), 0.0])
        Rs = cv2.Rodrigues(rv)[0]
        R, tr = Rs @ R, Rs @ tr
    out = _bump(x, p.out_phase)
    if out > 0:  # slide right: the centre's pixel goes from cx to beyond the border
        depth = (R @ c + tr)[2]
        d_px = fill * camera.width  # the diameter's apparent size
        shift_px = out * (0.5 * camera.width + (p.out_share - 0.35) * d_px)
        tr = tr + np.array([shift_px * depth / camera.fx, 0.0, 0.0])
    return Pose.from_matrix(R, tr)


def full_silhouette_area(obj: TexturedObject, camera: PinholeCamera, pose: Pose, scale: float = 0.5) -> float:
    """Pixels (at full resolution) of the whole silhouette, inside the image or not: rendered at
    ``scale`` in a camera enlarged by one image size on every side."""
    w, h = int(round(camera.width * scale)), int(round(camera.height * scale))
    big = PinholeCamera(camera.fx * scale, camera.fy * scale, (camera.cx + 0.5) * scale - 0.5 + w,
                        (camera.cy + 0.5) * scale - 0.5 + h, np.zeros(5), width=3 * w, height=3 * h)
    return float(np.count_nonzero(render(obj.mesh, big, pose).face >= 0)) / (scale * scale)


def _line_blur(img: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Blur along the image displacement ``d`` (px) during the exposure: a normalised line kernel."""
    n = float(np.hypot(*d))
    if n < 1.0:
        return img
    k = int(np.ceil(n)) | 1
    ker = np.zeros((k, k), np.float32)
    c = k // 2
    for s in np.linspace(-0.5, 0.5, 4 * k):
        ker[int(round(c + s * d[1])), int(round(c + s * d[0]))] += 1.0
    return cv2.filter2D(img, -1, ker / ker.sum(), borderType=cv2.BORDER_REFLECT)


def _occluder(shape, bbox, x: float, phase, size) -> np.ndarray:
    """The passing occluder's alpha (float, blurred edge) over the silhouette's bounding box
    ``bbox`` (x, y, w, h): a rounded patch that sweeps from left of it to right."""
    h, w = shape
    a, b = phase
    alpha = np.zeros((h, w), np.float32)
    if not a < x < b or bbox[2] <= 0:
        return alpha
    bx, by, bw, bh = bbox
    ow, oh = max(size[0] * bw, 8.0), max(size[1] * bh, 8.0)
    s = (x - a) / (b - a)
    cx = bx - ow + s * (bw + 2 * ow)
    cy = by + 0.55 * bh
    cv2.ellipse(alpha, (int(cx), int(cy)), (int(ow / 2), int(oh / 2)), 0.0, 0.0, 360.0, 1.0, -1)
    return cv2.GaussianBlur(alpha, (0, 0), 2.0)


def render_orbit(obj: TexturedObject, camera: PinholeCamera, backgrounds, params: OrbitParams = OrbitParams(),
                 seed: int = 0, name: str | None = None) -> OrbitSequence:
    """Render the walk (see the module) over ``backgrounds[seed % len]`` (the occluder is cut from
    another one)."""
    p = params
    rng = np.random.default_rng(seed)
    n = int(round(p.seconds * p.fps))
    W, H = int(camera.width), int(camera.height)
    bg = cv2.resize(backgrounds[seed % len(backgrounds)], (W, H)).astype(np.float32)
    hand = cv2.resize(backgrounds[(seed + 1) % len(backgrounds)], (W, H))
    hand = cv2.GaussianBlur(hand, (0, 0), 3.0).astype(np.float32) * 0.8  # out of focus, nearer, darker
    ramp = np.linspace(1.1, 0.8, W, dtype=np.float32)[None, :, None]
    cast = np.array(p.light_cast, np.float32)
    frames, poses, vis, ins, occ, phases = [], [], [], [], [], []
    e = p.exposure / p.fps
    for k in range(n):
        t = k / p.fps
        x = t / p.seconds
        pose = orbit_pose_at(obj, camera, t, p, seed)
        obj_img, sil = obj.render(camera, pose)
        img = bg.copy()
        img[sil] = obj_img[sil]
        # motion blur along the object's image motion during the exposure
        c = obj.mesh.centre[None]
        u0 = camera.project(orbit_pose_at(obj, camera, t - e / 2, p, seed).apply(c))[0]
        u1 = camera.project(orbit_pose_at(obj, camera, t + e / 2, p, seed).apply(c))[0]
        img = _line_blur(img, u1 - u0)
        # the occluder passes in front (the camera's focus: blurred with the frame)
        ys, xs = np.nonzero(sil)
        bbox = (float(xs.min()), float(ys.min()), float(np.ptp(xs) + 1), float(np.ptp(ys) + 1)) if len(xs) else (0, 0, 0, 0)
        alpha = _occluder((H, W), bbox, x, p.occluder_phase, p.occluder_size)
        if alpha.any():
            img = img * (1 - alpha[..., None]) + hand * alpha[..., None]
        # lighting: gain, colour cast and a ramp across the image fade in and stay
        L = _ramp(x, p.light_phase)
        if L > 0:
            gain = (1 - L) + L * p.light_gain * cast[None, None, :] * ramp
            img = img * gain
        img = img + rng.normal(0.0, p.noise, img.shape).astype(np.float32)
        img = np.clip(img, 0, 255).astype(np.uint8)
        frames.append(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, p.jpeg])[1].tobytes())
        poses.append(pose)
        n_in = int(sil.sum())
        touches = n_in and (sil[0].any() or sil[-1].any() or sil[:, 0].any() or sil[:, -1].any())
        total = full_silhouette_area(obj, camera, pose) if touches or n_in == 0 else float(n_in)
        total = max(total, float(n_in), 1.0)
        hidden = float((alpha[sil] >= 0.5).sum())
        ins.append(n_in / total)
        occ.append(hidden / max(n_in, 1))
        vis.append((n_in - hidden) / total)
        ph = tuple(nm for nm, ph_ in (("out", p.out_phase), ("blur", p.blur_phase), ("occluder", p.occluder_phase))
                   if ph_[0] < x < ph_[1])
        phases.append(ph + (("dim",) if L > 0.5 else ()))
    return OrbitSequence(name or obj.obj.name, camera, p.fps, frames, poses, np.array(vis), np.array(ins),
                         np.array(occ), phases)


def short_orbit(seconds: float = 2.5, fps: float = 30.0, turn_deg: float = 150.0) -> OrbitParams:
    """A short walk for tests: ``turn_deg`` round the object in ``seconds`` (to faces the
    training photo does not show), the distance breathing ×1.5, no slide, blur, light or hand."""
    return replace(OrbitParams(), seconds=seconds, fps=fps, turns=turn_deg / 360.0, elevation_swings=0.5,
                   elevation_deg=20.0, size_ratio=1.5, size_cycles=0.5, out_phase=(2.0, 2.0), light_phase=(2.0, 2.1),
                   blur_phase=(2.0, 2.0), occluder_phase=(2.0, 2.0))


def calm_orbit(seconds: float = 10.0) -> OrbitParams:
    """The zoo's walk without its hard phases (``quatrack bench track-zoo --calm``): one turn
    round the object with the elevation swinging once through ±25° and the apparent size
    breathing ×1.5, and no slide out of the frame, blur, change of light or occluder. Why: it
    isolates what the harsh walks mix with their phases — a track carried round sides no photo
    shows by its own points and views (a zoo cylinder's calm orbit once reported poses 5–11°
    off, drifted about its axis, which no outline shows; bench/RESULTS.md, session 65)."""
    return replace(OrbitParams(), seconds=seconds, turns=1.0, elevation_swings=1.0, elevation_deg=25.0,
                   size_ratio=1.5, size_cycles=0.5, out_phase=(2.0, 2.0), light_phase=(2.0, 2.1),
                   blur_phase=(2.0, 2.0), occluder_phase=(2.0, 2.0))

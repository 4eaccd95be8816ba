"""The object zoo: rendered objects of several shapes, sizes and mesh units, textured from real
photographs, shared by ``quatrack bench locate`` and the tracking benchmark.

Each :class:`ZooObject` is a closed mesh (a box of given proportions, a cube, a cylinder or a
prism) built with trimesh in millimetres, centimetres or metres, and a texture atlas: every face
maps to a region of one real photograph (``testing/data/textures/``, licences in the README there;
the cookie box's registered photo is one). :class:`TexturedObject` renders it at any pose through
the project's own z-buffer (:func:`quatrack.viewsets.render.render`), so the ground truth is the
same geometry recognition uses. :func:`write_spec` writes a training spec (``object.json`` +
mesh + 1 or 4 rendered "photos" with their cameras and poses, per docs/contract.md) that
``train_object(load_spec(...))`` trains.

Texture mapping: each triangle carries the texture coordinates of its corners; the affine map
``uv = A·X + b`` of its plane (the normal direction maps to 0) gives the texture pixel of every
rendered pixel's 3-D point ``X = R⁻¹(z·ray − t)``. Faces are shaded Lambert-like,
``s = 0.55 + 0.45·|n·l|`` with a fixed light in the camera frame, so edges between faces show.

Everything is deterministic: geometry and textures have no randomness; scenes take a seeded
``numpy.random.Generator``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

import cv2
import numpy as np

from quatrack.examples import example_dir
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import Mesh, make_mesh, outward_faces
from quatrack.viewsets.render import pixel_rays, render

TEXTURES = Path(__file__).resolve().parent / "data" / "textures"
UNITS = {"mm": 10.0, "cm": 1.0, "m": 0.01}  # mesh units per centimetre
_LIGHT = np.array([-0.3, -0.5, -1.0]) / np.linalg.norm([-0.3, -0.5, -1.0])


def texture_path(name: str) -> Path:
    """A texture file by name: ``cookie-box`` is the bundled registered photo."""
    if name == "cookie-box":
        return example_dir() / "resized_IMG_3875.JPG"
    return TEXTURES / f"{name}.jpg"


@dataclass(frozen=True)
class ZooObject:
    """A shape in centimetres, expressed in ``unit``. ``shape`` is ``box`` (``size`` = x, y, z
    extents) or ``cylinder``/``prism`` (``size`` = radius, height; ``sides`` facets round)."""

    name: str
    shape: str
    size: tuple[float, ...]
    unit: str
    texture: str
    sides: int = 4

    @property
    def scale(self) -> float:
        """Mesh units per centimetre."""
        return UNITS[self.unit]


ZOO: tuple[ZooObject, ...] = (
    ZooObject("cube-m", "box", (10.0, 10.0, 10.0), "m", "chelsea"),
    ZooObject("flat-box-mm", "box", (24.0, 16.0, 4.0), "mm", "ihc"),
    ZooObject("tall-box-cm", "box", (8.0, 6.0, 22.0), "cm", "rocket"),  # weak texture: mostly night sky
    ZooObject("cookie-slab-cm", "box", (16.0, 11.0, 6.0), "cm", "cookie-box"),
    ZooObject("cylinder-mm", "cylinder", (4.0, 12.0), "mm", "coffee", sides=24),
    ZooObject("hex-prism-m", "prism", (5.0, 9.0), "m", "brick", sides=6),
    ZooObject("small-cube-cm", "box", (6.0, 6.0, 6.0), "cm", "camera"),
    ZooObject("wide-box-cm", "box", (20.0, 14.0, 9.0), "cm", "astronaut"),
)


def zoo_object(name: str) -> ZooObject:
    for o in ZOO:
        if o.name == name:
            return o
    raise KeyError(f"no zoo object {name!r}; known: {', '.join(o.name for o in ZOO)}")


def _box_geometry(size):
    """Vertices, faces and corner texture coordinates (face, corner, (atlas region, u, v))."""
    import trimesh

    tm = trimesh.creation.box(extents=size)
    V, F = np.asarray(tm.vertices), outward_faces(np.asarray(tm.vertices), np.asarray(tm.faces))
    lo, ext = V.min(0), np.ptp(V, 0)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    axis = np.argmax(np.abs(n), axis=1)
    region = axis * 2 + (n[np.arange(len(n)), axis] > 0)  # one atlas region per box side
    uv = np.zeros((len(F), 3, 2))
    for f in range(len(F)):
        a, b = [k for k in range(3) if k != axis[f]]
        P = (V[F[f]] - lo) / ext
        uv[f] = np.stack([P[:, a], 1.0 - P[:, b]], axis=1)
    return V, F, region, uv


def _round_geometry(radius, height, sides):
    """A prism of ``sides`` facets (a cylinder when many): the side wraps round the texture's
    upper two thirds (u = angle), the caps are planar crops."""
    import trimesh

    tm = trimesh.creation.cylinder(radius=radius, height=height, sections=sides)
    V, F = np.asarray(tm.vertices), outward_faces(np.asarray(tm.vertices), np.asarray(tm.faces))
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    uv = np.zeros((len(F), 3, 2))
    region = np.zeros(len(F), int)
    for f in range(len(F)):
        P = V[F[f]]
        if abs(n[f, 2]) > 0.9:  # cap
            region[f] = 1 if n[f, 2] > 0 else 2
            uv[f] = np.stack([0.5 + 0.5 * P[:, 0] / radius, 0.5 - 0.5 * P[:, 1] / radius], axis=1)
        else:
            ang = np.arctan2(P[:, 1], P[:, 0])
            ang = np.unwrap(ang)  # a facet never spans the seam
            uv[f] = np.stack([ang / (2 * np.pi), 0.5 - P[:, 2] / height], axis=1)
            uv[f, :, 0] -= np.floor(uv[f, :, 0].min())  # into [0, 1 + 1/sides]: clipped at the texture's edge
    return V, F, region, uv


def _atlas_regions(texture: np.ndarray, n_regions: int, shape: str) -> list[tuple[float, float, float, float]]:
    """Texture pixel rectangles (x0, y0, w, h), one per region: overlapping crops at different
    places, so different sides look different (a cube must not be ambiguous)."""
    h, w = texture.shape[:2]
    if shape != "box":
        side = (0.0, 0.0, w - 1.0, (2.0 / 3.0) * (h - 1))
        cap_w = min(w, h) / 3.0
        return [side, (0.0, h - 1 - cap_w, cap_w, cap_w), (w - 1 - cap_w, h - 1 - cap_w, cap_w, cap_w)]
    out = []
    for r in range(n_regions):
        fx, fy = (r % 3) / 3.0, (r // 3) / 2.0
        out.append((fx * w * 0.5, fy * h * 0.45, 0.5 * w, 0.55 * h))
    return out


@lru_cache(maxsize=16)
def _texture(name: str) -> np.ndarray:
    img = cv2.imread(str(texture_path(name)), cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(f"zoo texture {texture_path(name)} is missing")
    return img


class TexturedObject:
    """A zoo object's mesh (in its unit) with its texture atlas; renders at any pose."""

    def __init__(self, obj: ZooObject) -> None:
        self.obj = obj
        s = obj.scale
        if obj.shape == "box":
            V, F, region, uv = _box_geometry(tuple(x * s for x in obj.size))
        else:
            V, F, region, uv = _round_geometry(obj.size[0] * s, obj.size[1] * s, obj.sides)
        self.mesh: Mesh = make_mesh(V, F, obj.name)
        self.texture = _texture(obj.texture)
        rects = _atlas_regions(self.texture, int(region.max()) + 1, obj.shape)
        px = np.zeros_like(uv)
        for f in range(len(F)):
            x0, y0, rw, rh = rects[region[f]]
            px[f, :, 0] = x0 + uv[f, :, 0] * rw
            px[f, :, 1] = y0 + uv[f, :, 1] * rh
        self._affine = self._face_affines(self.mesh, px)

    @staticmethod
    def _face_affines(mesh: Mesh, px: np.ndarray) -> np.ndarray:
        """(m, 2, 4): per triangle, texture pixel = A @ [X, 1] (constant along the normal)."""
        tri = mesh.triangles
        n = mesh.face_normals
        out = np.zeros((len(tri), 2, 4))
        for f in range(len(tri)):
            P = np.vstack([tri[f], tri[f, 0] + n[f] * mesh.extent])
            Y = np.vstack([px[f], px[f, 0]])
            A = np.column_stack([P, np.ones(4)])
            out[f] = np.linalg.solve(A, Y).T
        return out

    @cached_property
    def diameter(self) -> float:
        """The bounding box's diagonal in mesh units (the error scale of the benchmarks)."""
        return self.mesh.extent

    def render(self, camera: PinholeCamera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """The object alone (BGR uint8, black background) and its silhouette mask (bool): the
        same interface as :class:`quatrack.testing.scenes.Renderer`."""
        buf = render(self.mesh, camera, pose)
        sil = buf.face >= 0
        out = np.zeros((int(camera.height), int(camera.width), 3), np.uint8)
        if not sil.any():
            return out, sil
        ys, xs = np.nonzero(sil)
        f = buf.face[ys, xs]
        rays = pixel_rays(camera)[ys, xs]
        z = buf.depth[ys, xs]
        Xc = np.column_stack([rays * z[:, None], z])
        X = (Xc - pose.t) @ pose.R  # R^T (Xc - t), row-wise
        A = self._affine[f]
        uv = np.einsum("nij,nj->ni", A[:, :, :3], X) + A[:, :, 3]
        th, tw = self.texture.shape[:2]
        n, cols = len(uv), 1024  # remap wants maps below 32767 on a side
        pad = (-n) % cols
        mx = np.pad(np.clip(uv[:, 0], 0, tw - 1), (0, pad)).astype(np.float32).reshape(-1, cols)
        my = np.pad(np.clip(uv[:, 1], 0, th - 1), (0, pad)).astype(np.float32).reshape(-1, cols)
        col = cv2.remap(self.texture, mx, my, cv2.INTER_LINEAR).reshape(-1, 3)[:n].astype(np.float32)
        ncam = self.mesh.face_normals[f] @ pose.R.T
        shade = 0.55 + 0.45 * np.abs(ncam @ _LIGHT)
        out[ys, xs] = np.clip(col * shade[:, None], 0, 255).astype(np.uint8)
        return out, sil


@lru_cache(maxsize=16)
def textured(name: str) -> TexturedObject:
    """The zoo object ``name`` built once per process (read-only)."""
    return TexturedObject(zoo_object(name))


# -- cameras, poses, scenes ------------------------------------------------------------------------

def zoo_camera(width: int = 640, height: int = 480, fov_deg: float = 56.0) -> PinholeCamera:
    """A pinhole camera of ``width`` × ``height`` with horizontal field of view ``fov_deg``."""
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return PinholeCamera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, np.zeros(5), width=width, height=height)


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> Pose:
    """Object → camera pose of a camera at ``eye`` (object frame) looking at ``target``, its
    image's up along ``up``: rows of R are the camera axes x (right), y (down), z (forward)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, (0.0, 1.0, 0.0))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return Pose.from_matrix(R, -R @ np.asarray(eye, float))


def viewing_distance(obj: TexturedObject, camera: PinholeCamera, fill: float = 0.45) -> float:
    """Distance at which the object's diameter spans ``fill`` of the image width."""
    return camera.fx * obj.diameter / (fill * camera.width)


def orbit_pose(obj: TexturedObject, camera: PinholeCamera, azimuth_deg: float, elevation_deg: float = 25.0,
               fill: float = 0.45) -> Pose:
    """The camera on a sphere round the object's centre (azimuth about the object's z axis)."""
    c = obj.mesh.centre
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    d = viewing_distance(obj, camera, fill)
    eye = c + d * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return look_at(eye, c)


def training_poses(obj: TexturedObject, camera: PinholeCamera, n_views: int) -> list[Pose]:
    """1 view (three sides seen obliquely) or 4 views (every 90° round the object)."""
    if n_views not in (1, 4):
        raise ValueError("a zoo spec has 1 or 4 views")
    return [orbit_pose(obj, camera, 35.0 + 90.0 * k, 25.0) for k in range(n_views)]


def compose(obj_img: np.ndarray, sil: np.ndarray, background: np.ndarray, grey: bool = False) -> np.ndarray:
    """The object over a background (resized to the image); grey → one-channel uint8."""
    h, w = sil.shape
    bg = background if background.shape[:2] == (h, w) else cv2.resize(background, (w, h), interpolation=cv2.INTER_AREA)
    if bg.ndim == 2:
        bg = cv2.cvtColor(bg, cv2.COLOR_GRAY2BGR)
    img = bg.copy()
    img[sil] = obj_img[sil]
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if grey else img


def degrade(img: np.ndarray, rng: np.random.Generator, noise=(1.0, 3.0), blur=(0.0, 0.8), jpeg=(80, 95)) -> np.ndarray:
    """A camera's blur, noise and JPEG, drawn from ``rng``."""
    x = img.astype(np.float32)
    s = rng.uniform(*blur)
    if s > 0.3:
        x = cv2.GaussianBlur(x, (0, 0), s)
    x = np.clip(x + rng.normal(0.0, rng.uniform(*noise), size=x.shape), 0, 255).astype(np.uint8)
    ok, enc = cv2.imencode(".jpg", x, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(*jpeg))])
    return cv2.imdecode(enc, cv2.IMREAD_UNCHANGED)


def real_backgrounds() -> tuple[np.ndarray, ...]:
    """Real backgrounds: frames of the bundled ``box.mp4`` with the real box inpainted away,
    frozen as files (:func:`quatrack.testing.scenes.video_backgrounds`,
    :mod:`quatrack.testing.backgrounds`), so a change to recognition leaves the zoo's scenes and
    models as they were. Crops of the raw frames are no substitute: the box shows up in them, and
    one zoo object is textured from a photo of that box."""
    from .scenes import video_backgrounds

    return video_backgrounds()


# -- training specs --------------------------------------------------------------------------------

def write_spec(name: str, directory: str | Path, n_views: int = 1, grey: bool = False, seed: int = 0,
               backgrounds: tuple[np.ndarray, ...] | None = None, camera: PinholeCamera | None = None,
               poses: list[Pose] | None = None, masks: bool = False) -> Path:
    """Write ``object.json``, the mesh (PLY, in the object's unit) and ``n_views`` rendered
    photos (JPEG; grey → one channel) with their cameras and poses into ``directory``; returns
    the spec's path. ``poses`` overrides the default training poses; ``masks`` also writes each
    view's silhouette as a mask PNG (for views where the object is partly outside or covered)."""
    import trimesh

    obj = textured(name)
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    cam = camera or zoo_camera()
    poses = poses if poses is not None else training_poses(obj, cam, n_views)
    bgs = backgrounds if backgrounds is not None else real_backgrounds()
    rng = np.random.default_rng(seed)
    mesh_file = f"{name}.ply"
    trimesh.Trimesh(obj.mesh.vertices, obj.mesh.faces, process=False).export(str(d / mesh_file))
    views = []
    for i, pose in enumerate(poses):
        img, sil = obj.render(cam, pose)
        photo = degrade(compose(img, sil, bgs[int(rng.integers(len(bgs)))], grey), rng, noise=(0.5, 1.5), blur=(0.0, 0.3), jpeg=(92, 96))
        cv2.imwrite(str(d / f"view{i}.jpg"), photo, [cv2.IMWRITE_JPEG_QUALITY, 95])
        v = {
            "image": f"view{i}.jpg",
            "camera": {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                       "cy": cam.cy, "dist_coeffs": [float(x) for x in cam.dist_coeffs]},
            "pose": {"q_wxyz": [float(x) for x in pose.q_wxyz], "t": [float(x) for x in pose.t]},
        }
        if masks:
            cv2.imwrite(str(d / f"mask{i}.png"), sil.astype(np.uint8) * 255)
            v["mask"] = f"mask{i}.png"
        views.append(v)
    spec = {"name": name, "mesh": mesh_file, "views": views,
            "zoo": {"unit": obj.obj.unit, "texture": obj.obj.texture, "grey": grey}}
    path = d / "object.json"
    path.write_text(json.dumps(spec, indent=1))
    return path


# -- benchmark scenes ------------------------------------------------------------------------------

@dataclass(frozen=True)
class ZooScene:
    """A rendered image with its truth. ``outside``: share of the silhouette outside the image;
    ``angle_deg``: the viewing direction's angle from the nearest training view."""

    image: np.ndarray
    pose: Pose
    mask: np.ndarray
    outside: float
    angle_deg: float


def _silhouette_area(obj: TexturedObject, camera: PinholeCamera, pose: Pose, pad: int) -> int:
    """Silhouette pixels in a camera enlarged by ``pad`` on every side (the whole silhouette)."""
    big = PinholeCamera(camera.fx, camera.fy, camera.cx + pad, camera.cy + pad, np.zeros(5),
                        width=int(camera.width) + 2 * pad, height=int(camera.height) + 2 * pad)
    return int(np.count_nonzero(render(obj.mesh, big, pose).face >= 0))


def shifted_out(obj: TexturedObject, camera: PinholeCamera, pose: Pose, outside: float, direction: float) -> tuple[Pose, float]:
    """The pose moved sideways (image direction ``direction`` radians) until about ``outside``
    of its silhouette leaves the image; returns the pose and the share actually outside."""
    if outside <= 0:
        return pose, 0.0
    pad = int(camera.width)
    full = max(_silhouette_area(obj, camera, pose, pad), 1)
    c = pose.R @ obj.mesh.centre + pose.t
    step = np.array([np.cos(direction), np.sin(direction), 0.0]) * c[2] / camera.fx  # 1 px at the centre's depth
    lo, hi = 0.0, float(camera.width)
    best = (pose, 0.0)
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        p = Pose(pose.q_wxyz, pose.t + step * mid)
        inside = np.count_nonzero(render(obj.mesh, camera, p).face >= 0)
        share = 1.0 - inside / full
        best = (p, share)
        if share < outside:
            lo = mid
        else:
            hi = mid
    return best


def turned(pose: Pose, centre: np.ndarray, angle_deg: float, rng: np.random.Generator) -> Pose:
    """The pose turned by ``angle_deg`` about a random axis through the object's centre, in the
    camera frame (the camera orbits the object)."""
    axis = rng.normal(size=3)
    axis[2] *= 0.3  # mostly turns that show other sides, less roll
    axis /= np.linalg.norm(axis)
    Rd = cv2.Rodrigues(axis * np.radians(angle_deg))[0]
    c = pose.R @ centre + pose.t
    R = Rd @ pose.R
    return Pose.from_matrix(R, c - R @ centre)


def random_scene(rng: np.random.Generator, obj: TexturedObject, camera: PinholeCamera, base: Pose,
                 backgrounds, angle_deg: float = 0.0, outside: float = 0.0, grey: bool = False,
                 distance_scale: tuple[float, float] = (0.8, 1.25)) -> ZooScene:
    """The object seen ``angle_deg`` away from the training pose ``base`` (turned about its
    centre), at a random distance, with about ``outside`` of it out of the frame."""
    p = turned(base, obj.mesh.centre, angle_deg, rng) if angle_deg > 0 else base
    c = p.R @ obj.mesh.centre + p.t
    s = rng.uniform(*distance_scale)
    p = Pose(p.q_wxyz, p.t + c * (s - 1.0))
    p, share = shifted_out(obj, camera, p, outside, rng.uniform(0, 2 * np.pi))
    img, sil = obj.render(camera, p)
    bg = backgrounds[int(rng.integers(len(backgrounds)))]
    image = degrade(compose(img, sil, bg, grey), rng)
    return ZooScene(image, p, sil, share, float(angle_deg))


def two_object_scene(rng, a: str, b: str, trained: dict, cam, bgs):
    """Objects ``a`` (left half) and ``b`` (right half), each at one of its training views turned
    a little, composited over a background; returns the image and the true poses."""
    truths = {}
    sil_all = np.zeros((cam.height, cam.width), bool)
    layers = []
    for name, u in ((a, 0.3), (b, 0.7)):
        obj = textured(name)
        _, poses = trained[name]
        p = turned(poses[0], obj.mesh.centre, 10.0, rng)
        d = viewing_distance(obj, cam, 0.3)
        ray = np.array([(u * cam.width - cam.cx) / cam.fx, 0.0, 1.0])
        p = Pose(p.q_wxyz, ray * d - p.R @ obj.mesh.centre)
        o_img, sil = obj.render(cam, p)
        layers.append((o_img, sil))
        truths[name] = p
    bg = bgs[int(rng.integers(len(bgs)))]
    img = bg.copy() if bg.shape[:2] == (cam.height, cam.width) else cv2.resize(bg, (cam.width, cam.height))
    for o_img, sil in layers:
        img[sil & ~sil_all] = o_img[sil & ~sil_all]
        sil_all |= sil
    return degrade(img, rng), truths

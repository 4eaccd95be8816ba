"""RFCH defaults study (issue 3): how well do N, d and the scales separate object windows from
background windows on rendered scenes?

Scenes: the bundled cookie box rendered at novel poses (homography texturing from its photo)
composited onto synthetic clutter (random coloured shapes, stripes and noise, with the box's
own colours among them). For each configuration the model is trained on the photo; in each scene
the χ² distance of the object's bounding box is compared with every same-size window that
overlaps the object by < 20 %. Reported: AUC = P(χ²_object < χ²_background) over all pairs, the
median gap (median background − object) and the worst-case margin (min background − object).

Run: ``python -m quatrack.bench.rfch_study`` (a few minutes on 2 cores).
"""

from __future__ import annotations

import itertools
import time
from quatrack.examples import example_dir

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.mesh import load_mesh
from quatrack.viewsets.novel import render_textured_view, rotate_about_centre, scale_pose
from quatrack.viewsets.render import render
from quatrack.viewsets.rfch import RFCHParams, chi2, cooccurrence, label_image, train_rfch
from quatrack.viewsets.spec import load_spec

EXAMPLE = example_dir()


def clutter(rng: np.random.Generator, h: int, w: int, palette: np.ndarray) -> np.ndarray:
    img = cv2.GaussianBlur(rng.integers(40, 220, (h, w, 3)).astype(np.uint8), (0, 0), 8)
    for _ in range(60):
        colour = tuple(int(c) for c in (palette[rng.integers(len(palette))] if rng.random() < 0.4 else rng.integers(0, 255, 3)))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(10, 120)), y + int(rng.integers(10, 120))), colour, -1)
        else:
            cv2.ellipse(img, (x, y), (int(rng.integers(5, 60)), int(rng.integers(5, 60))), float(rng.uniform(0, 180)), 0, 360, colour, -1)
    for _ in range(4):  # stripes: strong gradients like text and edges
        x = int(rng.integers(0, w - 60))
        y = int(rng.integers(0, h - 60))
        for k in range(0, 60, 6):
            cv2.line(img, (x + k, y), (x + k, y + 60), (0, 0, 0), 2)
    noise = rng.normal(0, 6, img.shape)
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def scenes(seed: int = 0, count: int = 8):
    spec = load_spec(EXAMPLE / "object.json")
    v = spec.views[0]
    mesh = load_mesh(spec.mesh_path)
    photo = cv2.imread(str(v.image_path))
    buf = render(mesh, v.camera, v.pose)
    palette = photo[buf.mask > 0][:: 997]
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(v.camera.fx, v.camera.fy, 320.0, 240.0, width=640, height=480)
    groups = mesh.plane_ids
    out = []
    for _ in range(count):
        pose = rotate_about_centre(v.pose, mesh.centre, rng.normal(0, 0.35, 3))
        pose = scale_pose(pose, mesh.centre, float(rng.uniform(0.35, 0.6)))
        img, tex, _ = render_textured_view(mesh, groups, photo, v.camera, v.pose, buf, cam, pose)
        # shift the object to a random place in the frame
        ys, xs = np.nonzero(tex)
        dx = int(rng.integers(-xs.min(), 640 - xs.max()))
        dy = int(rng.integers(-ys.min(), 480 - ys.max()))
        M = np.float32([[1, 0, dx], [0, 1, dy]])
        img = cv2.warpAffine(img, M, (640, 480))
        tex = cv2.warpAffine(tex, M, (640, 480), flags=cv2.INTER_NEAREST)
        bg = clutter(rng, 480, 640, palette)
        scene = np.where(tex[..., None] > 0, img, bg)
        scene = np.clip(scene.astype(np.float32) * rng.uniform([0.8, 0.8, 0.8], [1.2, 1.2, 1.2]), 0, 255).astype(np.uint8)
        out.append((scene, tex))
    return photo, buf.mask, out


def evaluate(photo, mask, scene_list, n, d, scales):
    model = train_rfch([photo], [mask], RFCHParams(n_clusters=n, distance=d, scales=scales))
    pairs, gaps, margins = [], [], []
    for scene, tex in scene_list:
        lab = label_image(scene, model)
        ys, xs = np.nonzero(tex)
        x0, y0, w, h = xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1
        obj = chi2(cooccurrence(lab[y0 : y0 + h, x0 : x0 + w], None, n, d), model.histogram)
        bgs = []
        for x in range(0, 640 - w + 1, max(16, w // 3)):
            for y in range(0, 480 - h + 1, max(16, h // 3)):
                if np.count_nonzero(tex[y : y + h, x : x + w]) < 0.2 * np.count_nonzero(tex):
                    bgs.append(chi2(cooccurrence(lab[y : y + h, x : x + w], None, n, d), model.histogram))
        if not bgs:
            continue
        bgs = np.array(bgs)
        pairs.append(np.mean(obj < bgs))
        gaps.append(np.median(bgs) - obj)
        margins.append(bgs.min() - obj)
    return float(np.mean(pairs)), float(np.median(gaps)), float(np.min(margins))


def main() -> None:
    t0 = time.perf_counter()
    photo, mask, scene_list = scenes()
    rows = []
    for n, d, scales in itertools.product((16, 24, 32, 40), (4, 8, 16), ((1.0, 2.0), (1.0, 2.0, 4.0))):
        t = time.perf_counter()
        auc, gap, margin = evaluate(photo, mask, scene_list, n, d, scales)
        rows.append((n, d, scales, auc, gap, margin, time.perf_counter() - t))
    print("| N | d (px) | scales (px) | AUC | median gap | worst margin | time (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for n, d, scales, auc, gap, margin, t in rows:
        print(f"| {n} | {d} | {', '.join(f'{s:g}' for s in scales)} | {auc:.3f} | {gap:.3f} | {margin:+.3f} | {t:.1f} |")
    best = max(rows, key=lambda r: (round(r[3], 3), r[5], -r[0]))
    print(f"\nbest: N = {best[0]}, d = {best[1]}, scales = {best[2]} ({len(scene_list)} scenes, {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()

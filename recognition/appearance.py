"""Evidence from the object's appearance: does the image look, at a pose, as the object looked before?

SIFT consensus and the model's edges can both be fooled by an object whose sides share texture
or outline: a cube whose faces carry overlapping crops of one print is matched on the wrong
face, and turned by 90° its outline is the same. What such a pose cannot fake is the rest of the
texture: where a trusted view of the object (a training photo, a keyframe) saw a face, the image
at the pose must show that face's texture. Where the texture truly repeats — the matched face
carries the very pixels of the face it is taken for — it can: a zoo walk's cube re-found 90° off
on a synthetic keyframe view reads 0.98 here (session 36); nothing in the image tells it apart.

:func:`texture_agreement` renders each *reference* (an image of the object with the camera
and the pose it was seen at: a keyframe's crop) at the candidate pose — every planar face warped
by the homography it induces (:func:`quatrack.viewsets.novel.render_textured_view`, training's own
novel-view renderer), only where the reference saw that face at ``|cos| ≥ min_source_cos`` and
unoccluded — and correlates it with the image over those pixels inside the image:

    ρ_k = Σ (a − ā)(b − b̄) / √(Σ (a − ā)² · Σ (b − b̄)²)

(normalised cross-correlation: blind to a change of gain and offset, so to the light's
brightness), block by block, a block being an eighth of the object's apparent size. Both are
blurred by ``blur_px`` first and the textured mask is eroded by ``erode_px`` (the warped
reference's edge is not compared), so that the pose errors of a tracked frame (a pixel or two)
and mild motion blur do not count as disagreement. The answer is the median of the blocks' ρ
over every reference, and the pixels of the blocks compared: a hand over part of the object
spoils the blocks it covers, not the answer (a whole-window NCC read 0.37 for a right pose of the
zoo cube behind the walks' passing hand). A right pose scores near 1 (≥ 0.78, 1st percentile
0.93, on 349 right poses of the zoo's stress scenes); texture from another face near 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.jit import lazily_compiled
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import Mesh
from quatrack.viewsets.novel import render_textured_view
from quatrack.viewsets.render import footprint
from quatrack.viewsets.texture import TextureReference


@dataclass(frozen=True)
class TextureAgreement:
    ncc: float  # the median correlation of the blocks compared (nan: too few, no evidence)
    pixels: int  # pixels of the blocks compared (0: no evidence)
    per_reference: tuple[tuple[float, int], ...] = ()  # (median ρ, pixels) of each reference's blocks


def _grey(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img


def _facing(mesh: Mesh, pose: Pose) -> np.ndarray:
    """Per face, the cosine between its normal and the ray from its centroid to the camera."""
    centroids = pose.apply(mesh.face_centroids)
    return -np.einsum("ij,ij->i", mesh.face_normals @ pose.R.T, centroids) / np.linalg.norm(centroids, axis=1)


def tile_correlations(a: np.ndarray, b: np.ndarray, mask: np.ndarray, tile: int, min_fill: float = 0.5,
                      min_std: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """NCC of ``a`` and ``b`` over ``mask`` in each ``tile`` × ``tile`` block, and each block's
    pixels; only blocks at least ``min_fill`` masked and with a standard deviation of at least
    ``min_std`` grey levels on both sides (a flat block carries no evidence either way). From
    the block's sums over its n masked pixels (one compiled pass, :func:`_tile_sums`):
    ``ρ = (Σab/n − ā b̄) / √((Σa²/n − ā²)(Σb²/n − b̄²))``.

    >>> rng = np.random.default_rng(0)
    >>> a = rng.normal(0, 20, (32, 32)).astype(np.float32)
    >>> rho, n = tile_correlations(a, 3 * a + 7, np.ones((32, 32), bool), 16)
    >>> np.round(rho, 3).tolist(), n.tolist()
    ([1.0, 1.0, 1.0, 1.0], [256, 256, 256, 256])
    """
    h, w = mask.shape
    sums = np.zeros((6, -(-h // tile), -(-w // tile)))
    _compiled_tile_sums()(np.ascontiguousarray(a, np.float32), np.ascontiguousarray(b, np.float32),
                          np.ascontiguousarray(mask, np.bool_), int(tile), sums)
    n, sa, sb, saa, sbb, sab = sums.reshape(6, -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ma, mb = sa / n, sb / n
        va, vb, cov = saa / n - ma * ma, sbb / n - mb * mb, sab / n - ma * mb
        ok = (n >= min_fill * tile * tile) & (va >= min_std**2) & (vb >= min_std**2)
        rho = cov[ok] / np.sqrt(va[ok] * vb[ok])
    return np.clip(rho, -1.0, 1.0), n[ok].astype(int)


def _tile_sums(a, b, mask, tile, out):  # pragma: no cover (compiled)
    """Per ``tile`` × ``tile`` block of the masked pixels: their count, Σa, Σb, Σa², Σb², Σab
    (float64), into ``out[0..5]``: one pass, where the numpy version
    (:func:`_tile_correlations_numpy`) made ten block-padded float64 copies of the crop (3 of a
    large audit's ~7 ms per reference, session 48). The sums run in another order than numpy's,
    so the answer agrees to ~1e-12, not bit for bit (tests/test_appearance.py)."""
    h, w = mask.shape
    for y in range(h):
        ty = y // tile
        for x in range(w):
            if mask[y, x]:
                tx = x // tile
                av = np.float64(a[y, x])
                bv = np.float64(b[y, x])
                out[0, ty, tx] += 1.0
                out[1, ty, tx] += av
                out[2, ty, tx] += bv
                out[3, ty, tx] += av * av
                out[4, ty, tx] += bv * bv
                out[5, ty, tx] += av * bv


_compiled_tile_sums = lazily_compiled(_tile_sums)


def _tile_correlations_numpy(a: np.ndarray, b: np.ndarray, mask: np.ndarray, tile: int, min_fill: float = 0.5,
                             min_std: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`tile_correlations` in numpy, as it was until session 48 (the reference of its test)."""
    h, w = mask.shape
    H, W = -(-h // tile) * tile, -(-w // tile) * tile
    m = np.zeros((H, W), np.float64)
    m[:h, :w] = mask
    A = np.zeros((H, W), np.float64)
    B = np.zeros((H, W), np.float64)
    A[:h, :w], B[:h, :w] = a, b

    def sums(x):
        return x.reshape(H // tile, tile, W // tile, tile).sum(axis=(1, 3)).ravel()

    n = sums(m)
    Am, Bm = A * m, B * m  # (m is 0 or 1: (A·m)·A is A·A·m exactly)
    with np.errstate(invalid="ignore", divide="ignore"):
        ma, mb = sums(Am) / n, sums(Bm) / n
        va = sums(Am * A) / n - ma * ma
        vb = sums(Bm * B) / n - mb * mb
        cov = sums(Am * B) / n - ma * mb
        ok = (n >= min_fill * tile * tile) & (va >= min_std**2) & (vb >= min_std**2)
        rho = cov[ok] / np.sqrt(va[ok] * vb[ok])
    return np.clip(rho, -1.0, 1.0), n[ok].astype(int)


def texture_agreement(image: np.ndarray, camera: PinholeCamera, pose: Pose, mesh: Mesh, groups: np.ndarray,
                      references, blur_px: float = 1.0, erode_px: int = 2, tiles: int = 8, min_tiles: int = 4,
                      min_source_cos: float = 0.3) -> TextureAgreement:
    """How well ``image`` (grey or BGR, seen by ``camera``) agrees at ``pose`` with the object's
    texture as the ``references`` (:class:`TextureReference`) saw it; see the module.
    ``groups``: the mesh's planar groups (:func:`quatrack.viewsets.mesh.planar_groups`).

    Correlated block by block (:func:`tile_correlations`, blocks 1/``tiles`` of the object's
    apparent size, at least 8 px) and summed up by the median over every block of every
    reference: a hand over part of the object, a highlight or a shadow spoils the blocks it
    covers, not the answer, as long as it covers fewer than half of them. Fewer than
    ``min_tiles`` blocks with texture on both sides: no evidence (nan, 0)."""
    box = footprint(mesh, camera, pose, erode_px + 2)
    if box is None:
        return TextureAgreement(float("nan"), 0)
    x0, y0, x1, y1 = box
    win = camera.cropped(x0, y0, x1, y1)
    tile = max(8, int(round(max(x1 - x0, y1 - y0) / tiles)))
    a_img = _grey(image)[y0:y1, x0:x1].astype(np.float32)
    if blur_px > 0:
        a_img = cv2.GaussianBlur(a_img, (0, 0), blur_px)
    kernel = np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8) if erode_px > 0 else None
    facing = _facing(mesh, pose) >= min_source_cos
    seen_well = np.append(facing, False)  # (index −1: background)
    per, all_rho, total, buf = [], [], 0, None
    for ref in references:
        if not np.any(facing & (_facing(mesh, ref.pose) >= min_source_cos)):
            per.append((float("nan"), 0))  # no face both see well: nothing to compare, nothing rendered
            continue
        ref = ref.rendered(mesh)
        b_img, textured, buf = render_textured_view(mesh, groups, _grey(ref.image), ref.camera, ref.pose, ref.buffers,
                                                    win, pose, min_source_cos, ref.mask, buf)
        mask = ((textured > 0) & seen_well[buf.face]).astype(np.uint8)
        if kernel is not None:
            mask = cv2.erode(mask, kernel)
        b = _grey(b_img).astype(np.float32)
        if blur_px > 0:
            b = cv2.GaussianBlur(b, (0, 0), blur_px)
        rho, n = tile_correlations(a_img, b, mask > 0, tile)
        per.append((float(np.median(rho)) if len(rho) else float("nan"), int(n.sum())))
        all_rho.append(rho)
        total += int(n.sum())
    rho = np.concatenate(all_rho) if all_rho else np.zeros(0)
    if len(rho) < min_tiles:
        return TextureAgreement(float("nan"), 0, tuple(per))
    return TextureAgreement(float(np.median(rho)), total, tuple(per))

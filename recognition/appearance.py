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

from dataclasses import dataclass, field

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.jit import lazily_compiled
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import Mesh
from quatrack.viewsets.novel import BACKGROUND, render_textured_view
from quatrack.viewsets.render import RenderBuffers, footprint, lift_keypoints
from quatrack.viewsets.texture import TextureReference


@dataclass(frozen=True)
class RenderedAt:
    """References rendered at one pose over one pixel box of the image (``box``: x0, y0, x1, y1),
    with the box's z-buffer: what :func:`texture_agreement` rendered, for :func:`texture_refit`
    at the same pose to reuse instead of rendering the same views again (the tracker's audit runs
    both in one frame: ~2–5 ms of renders a refit)."""

    pose: Pose
    box: tuple[int, int, int, int]
    buffers: RenderBuffers
    views: dict  # id(reference) → (the reference, its image rendered, its textured mask)


@dataclass(frozen=True)
class TextureAgreement:
    ncc: float  # the median correlation of the blocks compared (nan: too few, no evidence)
    pixels: int  # pixels of the blocks compared (0: no evidence)
    per_reference: tuple[tuple[float, int], ...] = ()  # (median ρ, pixels) of each reference's blocks
    # what was rendered (None: nothing); not part of the answer
    rendered: RenderedAt | None = field(default=None, compare=False, repr=False)


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
    per, all_rho, total, buf, views, seen_px = [], [], 0, None, {}, None
    for ref in references:
        if not np.any(facing & (_facing(mesh, ref.pose) >= min_source_cos)):
            per.append((float("nan"), 0))  # no face both see well: nothing to compare, nothing rendered
            continue
        given, ref = ref, ref.rendered(mesh)
        b_img, textured, buf = render_textured_view(mesh, groups, _grey(ref.image), ref.camera, ref.pose, ref.buffers,
                                                    win, pose, min_source_cos, ref.mask, buf)
        views[id(given)] = (given, b_img, textured)  # (the reference kept: its id stays its own)
        if seen_px is None:  # (every reference is rendered over the same buffers: read once)
            seen_px = seen_well[buf.face]
        mask = ((textured > 0) & seen_px).astype(np.uint8)
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
    rendered = RenderedAt(pose, box, buf, views) if min_source_cos == _REFIT_MIN_COS and buf is not None else None
    if len(rho) < min_tiles:
        return TextureAgreement(float("nan"), 0, tuple(per), rendered)
    return TextureAgreement(float(np.median(rho)), total, tuple(per), rendered)


def _rendered_here(rendered: RenderedAt | None, pose: Pose, box) -> bool:
    """Whether ``rendered`` was rendered at ``pose`` over a box inside ``box``."""
    if rendered is None or not (np.array_equal(rendered.pose.t, pose.t) and np.array_equal(rendered.pose.q_wxyz, pose.q_wxyz)):
        return False
    rx0, ry0, rx1, ry1 = rendered.box
    return box[0] <= rx0 and box[1] <= ry0 and rx1 <= box[2] and ry1 <= box[3]


@dataclass(frozen=True)
class TextureRefit:
    pose: Pose | None  # the pose the references' texture puts the object at (None: too few points)
    tracked: int  # corners of the rendered texture followed into the image (both ways)
    inliers: int  # of those, the PnP consensus
    # the consensus: object points (n, 3) — where the references saw that texture on the mesh —
    # and their pixels in the image (n, 2); None without a pose
    X: np.ndarray | None = None
    uv: np.ndarray | None = None


_REFIT_MIN_COS = 0.3  # texture_refit renders the faces the references saw at |cos| ≥ this


def texture_refit(image: np.ndarray, camera: PinholeCamera, pose: Pose, mesh: Mesh, groups: np.ndarray,
                  references, max_corners: int = 120, max_references: int = 2, margin_px: int = 24,
                  erode_px: int = 3, fb_px: float = 1.0, reprojection_px: float = 2.0,
                  min_points: int = 12, rendered: RenderedAt | None = None) -> TextureRefit:
    """Where the object's texture, as the ``references`` saw it, says the object is, starting
    from ``pose``: render, follow, solve. Each reference is rendered at ``pose`` (as
    :func:`texture_agreement` does); its corners (``cv2.goodFeaturesToTrack`` inside its
    textured, eroded mask) are lifted onto the mesh at ``pose``
    (:func:`quatrack.viewsets.render.lift_keypoints`) and followed by pyramidal KLT from the
    render into the image (the render's grey levels first matched to the image's mean and
    spread over the mask, for a changed light; kept if followed back to within ``fb_px``) —
    the ``max_references`` references that saw the object from nearest the pose's direction,
    ``max_corners`` corners in all; the
    pose is then solved from those 2-D–3-D pairs (``cv2.solvePnPRansac`` from ``pose``,
    ``reprojection_px``; refined by Levenberg–Marquardt on the consensus). Where the render
    shows no texture (round the object, faces the reference did not see) it takes the frame's
    own pixels: KLT's coarse pyramid levels see the object with its surroundings, and a flat
    grey there lost 90 % of a prism's corners at the true pose (10 % with the frame's pixels).

    Why: points born on the mesh at a pose that is off agree with that pose, and so does the
    edge refit that includes them, while the pose drifts (a zoo flat box, second-hand after a
    loss, drifted 1.5 → 5.4 % of its diameter in depth over nine frames, every test passed). The
    keyframes' texture rendered at such a pose is the object seen from slightly elsewhere, a
    pattern KLT follows to where the image shows it; the pose solved there moved those drifted
    poses back to within 0.1–1.1 % (bench/RESULTS.md, session 49). A right pose stays where it is.
    The consensus is returned too (``X``, ``uv``): the tracker follows it as anchors (session 50).
    ``rendered``: :func:`texture_agreement`'s renders at this very pose
    (:attr:`TextureAgreement.rendered`), reused: the object lies inside their box, so a render
    over the wider window here is theirs with the render's background round it (the same
    pixels where the rays are the same: a principal point of whole or half pixels).

    >>> from quatrack.viewsets.mesh import make_mesh
    >>> from quatrack.viewsets.render import render
    >>> from quatrack.viewsets.texture import TextureReference
    >>> rng = np.random.default_rng(1)
    >>> mesh = make_mesh(np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float),
    ...                  np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
    ...                            [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]))
    >>> cam = PinholeCamera(500.0, 500.0, 160.0, 120.0, width=320, height=240)
    >>> truth = Pose.from_rvec([0.5, -0.6, 0.2], [-0.5, -0.5, 4.0])
    >>> tex = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.uint8), (0, 0), 1.5)
    >>> ref = TextureReference(tex, cam, truth)
    >>> frame = render_textured_view(mesh, mesh.plane_ids, tex, cam, truth, render(mesh, cam, truth), cam, truth)[0]
    >>> off = Pose(truth.q_wxyz, truth.t + [0.03, -0.02, 0.15])  # 15 % of the side deeper
    >>> fit = texture_refit(frame, cam, off, mesh, mesh.plane_ids, [ref])
    >>> bool(np.linalg.norm(fit.pose.t - truth.t) < 0.03), fit.inliers >= 12
    (True, True)
    >>> bool(np.abs(cam.project(truth.apply(fit.X)) - fit.uv).max() < 1.0)  # where the truth puts them
    True
    """
    box = footprint(mesh, camera, pose, margin_px)
    if box is None:
        return TextureRefit(None, 0, 0)
    x0, y0, x1, y1 = box
    win = camera.cropped(x0, y0, x1, y1)
    a_img = np.ascontiguousarray(_grey(image)[y0:y1, x0:x1])
    kernel = np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8) if erode_px > 0 else None
    from_all, to_all, buf = [], [], None
    reuse = rendered if _rendered_here(rendered, pose, box) else None
    if reuse is not None:  # (their box inside this window: theirs pasted into it, see the docstring)
        rx0, ry0, rx1, ry1 = reuse.box
        inner = (slice(ry0 - y0, ry1 - y0), slice(rx0 - x0, rx1 - x0))
        depth = np.full((y1 - y0, x1 - x0), np.inf)
        face = np.full((y1 - y0, x1 - x0), -1, np.int32)
        depth[inner], face[inner] = reuse.buffers.depth, reuse.buffers.face
        buf = RenderBuffers(depth, face)
    here = pose.viewing_direction(mesh.centre)
    references = sorted(references, key=lambda r: -float(r.pose.viewing_direction(mesh.centre) @ here))
    references = references[:max(int(max_references), 1)]
    per_ref = max(int(max_corners) // len(references), min_points) if references else 0
    lk = dict(winSize=(21, 21), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    for ref in references:
        given, ref = ref, ref.rendered(mesh)
        if reuse is None:
            b_img, textured, buf = render_textured_view(mesh, groups, _grey(ref.image), ref.camera, ref.pose,
                                                        ref.buffers, win, pose, _REFIT_MIN_COS, ref.mask, buf)
        else:
            got = reuse.views.get(id(given), (None,))
            if got[0] is given:
                got = got[1:]
            else:  # (one the agreement did not render: rendered over its box)
                got = render_textured_view(mesh, groups, _grey(ref.image), ref.camera, ref.pose, ref.buffers,
                                           camera.cropped(*reuse.box), pose, _REFIT_MIN_COS, ref.mask,
                                           reuse.buffers)[:2]
            b_img = np.full(buf.face.shape, BACKGROUND, got[0].dtype)
            textured = np.zeros(buf.face.shape, np.uint8)
            b_img[inner], textured[inner] = got
        mask = textured if kernel is None else cv2.erode(textured, kernel)
        on = mask > 0
        if np.count_nonzero(on) < 64:
            continue
        b = _grey(b_img).astype(np.float32)
        a_on, b_on = a_img[on], b[on]  # (gathered once: their spreads and means)
        sa, sb = float(a_on.std()), float(b_on.std())
        if sa < 2.0 or sb < 2.0:
            continue
        b = np.clip((b - b_on.mean()) * (sa / sb) + float(a_on.mean()), 0, 255).astype(np.uint8)
        corners = cv2.goodFeaturesToTrack(b, per_ref, 0.01, 5, mask=mask)
        b = np.where(textured > 0, b, a_img)  # (round the object, the frame itself: see the docstring)
        if corners is None or len(corners) < min_points:
            continue
        corners = corners.reshape(-1, 2).astype(np.float32)
        fwd, st, _ = cv2.calcOpticalFlowPyrLK(b, a_img, corners, None, **lk)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(a_img, b, fwd, None, **lk)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - corners, axis=1) <= fb_px)
        from_all.append(corners[ok])
        to_all.append(fwd[ok])
    followed = sum(len(f) for f in from_all)
    if followed < min_points:
        return TextureRefit(None, followed, 0)
    # every reference was rendered at the same pose in the same window: one lifting for all
    X, keep = lift_keypoints(mesh, win, pose, np.concatenate(from_all), buffers=buf)
    X, uv = X[keep], np.concatenate(to_all)[keep]
    if len(X) < min_points:
        return TextureRefit(None, len(X), 0)
    K, dist = win.matrix, np.asarray(win.dist_coeffs, float)  # (solved in the window's pixels)
    rvec, tvec = pose.rvec.reshape(3, 1).copy(), np.asarray(pose.t, float).reshape(3, 1).copy()
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X.astype(np.float64), uv.astype(np.float64), K, dist, rvec, tvec,
                                             useExtrinsicGuess=True, iterationsCount=100,
                                             reprojectionError=reprojection_px, confidence=0.99,
                                             flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or inl is None or len(inl) < min_points:
        return TextureRefit(None, len(X), 0 if inl is None else len(inl))
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(X[inl].astype(np.float64), uv[inl].astype(np.float64), K, dist, rvec, tvec)
    return TextureRefit(Pose.from_rvec(rvec.ravel(), tvec.ravel()), len(X), len(inl), X[inl].astype(float),
                        uv[inl].astype(float) + np.array([x0, y0], float))  # (window → image pixels)

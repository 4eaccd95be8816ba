"""Pinhole camera with OpenCV's lens distortion: projection and its Jacobian.

Camera frame as in OpenCV (x right, y down, z forward); pixel coordinates are continuous with
the centre of the top-left pixel at (0, 0), as ``cv2.projectPoints`` gives them. Distortion
coefficients are OpenCV's ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``.

A camera may sit anywhere in a rig: ``R_rig, t_rig`` map the *reference* camera frame (the frame
in which the filter's pose is expressed) into this camera, ``X_this = R_rig X_ref + t_rig``.
That is the sum over cameras ``j`` in Ude's eq. 24.

>>> cam = PinholeCamera(fx=800.0, fy=800.0, cx=320.0, cy=240.0, width=640, height=480)
>>> cam.project([[0.1, -0.05, 2.0]])                 # u = fx·x/z + cx, v = fy·y/z + cy
array([[360., 220.]])
"""


from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from quatrack.tracking.jit import lazily_compiled

__all__ = ["PinholeCamera"]

_MAX_DIST = 8  # k1 k2 p1 p2 k3 k4 k5 k6 (thin-prism and tilt terms are not supported)


@lru_cache(maxsize=64)
def valid_radius2(d: tuple) -> float:
    """The squared normalised radius ``r²`` (``r = |(x, y)|``, ``x = X/Z``) up to which OpenCV's
    radial model ``r_d = r·(1 + k1 r² + k2 r⁴ + k3 r⁶)/(1 + k4 r² + k5 r⁴ + k6 r⁶)`` still
    grows with ``r`` (inf when it always does). Why: beyond it the polynomial turns back, so a
    point far outside the field of view lands inside the image (k1 = −0.42, k2 = 0.2,
    k3 = −0.05 put a point 62° off the axis at pixel (202, 154) of a 640 × 480 image). ``d``:
    the 8 coefficients as a tuple (cached: cameras are rebuilt by every crop and resize).
    The tangential terms move a point along its direction by ``3r²(p1·sin θ + p2·cos θ)``, so the
    radius is where ``d r_d/d r`` falls to their worst slope, ``6r·√(p1² + p2²)``: the distance
    from the principal point grows along every direction within it.

    >>> round(valid_radius2((-0.45, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)), 6)   # d(r − 0.45 r³)/dr = 0
    0.740741
    >>> valid_radius2((-0.35, 0.15, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))            # 1 − 1.05 r² + 0.75 r⁴ > 0
    inf
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = (float(v) for v in d)
    p = math.hypot(p1, p2)

    def turns(s: float) -> bool:
        # d r_d / d r = ((N + 2sN')·D − 2s·N·D')/D² (s = r²); a denominator reaching zero is the
        # model's end too (the radius runs off to infinity and returns from the far side)
        N, dN = 1.0 + s * (k1 + s * (k2 + s * k3)), k1 + s * (2.0 * k2 + 3.0 * k3 * s)
        D, dD = 1.0 + s * (k4 + s * (k5 + s * k6)), k4 + s * (2.0 * k5 + 3.0 * k6 * s)
        return D <= 0.0 or ((N + 2.0 * s * dN) * D - 2.0 * s * N * dD) / (D * D) <= 6.0 * math.sqrt(s) * p

    grid = np.geomspace(1e-6, 1e4, 2001)  # r from 0.001 to 100 (89.4° off the axis)
    k = next((i for i, s in enumerate(grid) if turns(float(s))), None)
    if k is None:
        return math.inf
    lo, hi = (0.0 if k == 0 else float(grid[k - 1])), float(grid[k])
    for _ in range(60):  # (bisection to the last bits: the same radius on every machine)
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if turns(mid) else (mid, hi)
    return max(lo, 1e-300)  # (above 0: it divides; a model turning back at once projects to NaN)


def _rig_array(value, shape: tuple, name: str) -> np.ndarray:
    """``value`` as a float array of ``shape``, or a ValueError naming ``name`` (numpy's own said
    "cannot reshape array of size 2 into shape (3,)")."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers, got {value!r}"[:120]) from None
    if a.size != int(np.prod(shape)):
        raise ValueError(f"{name} must be {'3 numbers' if len(shape) == 1 else 'a 3×3 matrix'}, got shape {a.shape}")
    return a.reshape(shape)


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics (pixels), distortion, image size (pixels) and rig extrinsics of one camera."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist_coeffs: np.ndarray = field(default_factory=lambda: np.zeros(5))
    width: int | None = None
    height: int | None = None
    R_rig: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_rig: np.ndarray = field(default_factory=lambda: np.zeros(3))
    # derived once: they are asked on every projection
    has_distortion: bool = field(init=False, repr=False, compare=False)
    # r² (normalised) beyond which the radial model turns back (valid_radius2; inf without
    # distortion or when it never does): points beyond it are projected outwards, see project()
    valid_r2: float = field(init=False, repr=False, compare=False)
    is_reference: bool = field(init=False, repr=False, compare=False)
    # set by cropped(): (x0, y0, width, height) of this crop in the whole image, so that the
    # per-pixel rays of a distorted camera's crops are sliced from the whole image's, computed
    # once (viewsets/render.py: pixel_rays), not undistorted again for every window
    crop_of: tuple[int, int, int, int] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if isinstance(v, (str, bytes, bool)) or not np.ndim(v) == 0:
                raise ValueError(f"{name} must be a number, got {v!r}"[:120])
            object.__setattr__(self, name, float(v))
        try:
            d = np.asarray(self.dist_coeffs, dtype=float).ravel()
        except (TypeError, ValueError):
            raise ValueError(f"dist_coeffs must be numbers, got {self.dist_coeffs!r}"[:120]) from None
        if d.size > _MAX_DIST:
            if np.any(d[_MAX_DIST:] != 0.0):
                raise ValueError("only OpenCV distortion terms k1..k6, p1, p2 are supported")
            d = d[:_MAX_DIST]
        # (OpenCV reads 4, 5 or 8 terms; 1 or 3 were passed on and silently misread: "not found")
        if d.size not in (0, 4, 5, 8) or not np.all(np.isfinite(d)):
            raise ValueError(f"dist_coeffs must be 4, 5 or 8 finite numbers (k1, k2, p1, p2[, k3[, k4, k5, k6]]), "
                             f"got {d.size}: {np.round(d, 6).tolist()}"[:200])
        if not (np.isfinite(self.fx) and np.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (np.isfinite(self.cx) and np.isfinite(self.cy)):
            raise ValueError(f"the principal point must be finite, got cx={self.cx}, cy={self.cy}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if v is None:
                continue
            # (a string or a float was kept as given: width "640" raised TypeError '<=' not supported,
            # and 640.0 stayed a float, which np.zeros((height, width)) refuses)
            whole = (isinstance(v, numbers.Real) and not isinstance(v, bool) and np.isfinite(v)
                     and float(v).is_integer() and v > 0)
            if not whole:
                raise ValueError(f"{name} must be a whole number of pixels above 0, got {v!r}"[:120])
            object.__setattr__(self, name, int(v))
        object.__setattr__(self, "dist_coeffs", d)
        object.__setattr__(self, "R_rig", _rig_array(self.R_rig, (3, 3), "R_rig"))
        object.__setattr__(self, "t_rig", _rig_array(self.t_rig, (3,), "t_rig"))
        # True when there are distortion terms to apply
        object.__setattr__(self, "has_distortion", bool(np.any(d != 0.0)))
        object.__setattr__(self, "valid_r2", valid_radius2(tuple(np.pad(d, (0, _MAX_DIST - d.size)).tolist()))
                           if self.has_distortion else math.inf)
        # True when this camera *is* the reference frame (no rig transform to apply)
        object.__setattr__(
            self, "is_reference", bool(np.array_equal(self.R_rig, np.eye(3)) and not np.any(self.t_rig))
        )
        if not self.is_reference:  # (a rig's pose: a rotation and a finite shift, as a Pose's)
            R, t = self.R_rig, self.t_rig
            if not (np.all(np.isfinite(R)) and np.allclose(R @ R.T, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0):
                raise ValueError("R_rig is not a rotation matrix (orthonormal, det +1)")
            if not np.all(np.isfinite(t)):
                raise ValueError(f"t_rig must be finite, got {t.tolist()}")

    def _key(self) -> tuple:
        """What a camera is compared and hashed by (the fields; its arrays by value, -0.0 as 0.0)."""
        return (self.fx, self.fy, self.cx, self.cy, tuple(self.dist_coeffs + 0.0), self.width, self.height,
                tuple(self.R_rig.ravel() + 0.0), tuple(self.t_rig + 0.0))

    # (the dataclass's own __eq__ compared the arrays as a tuple: two equal cameras raised "the truth
    # value of an array ... is ambiguous", and hash() "unhashable type: 'numpy.ndarray'")
    def __eq__(self, other: object) -> bool:
        return self._key() == other._key() if isinstance(other, PinholeCamera) else NotImplemented

    def __hash__(self) -> int:
        return hash(self._key())

    @property
    def matrix(self) -> np.ndarray:
        """The 3×3 camera matrix ``K``."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def cropped(self, x0: int, y0: int, x1: int, y1: int) -> "PinholeCamera":
        """The same camera seeing only the pixel box ``[x0, x1) × [y0, y1)``: the principal point
        moves by the box's corner, so every pixel of the crop has the ray it had in the image.

        >>> PinholeCamera(800.0, 800.0, 320.0, 240.0, width=640, height=480).cropped(100, 50, 300, 250).project([[0.0, 0.0, 1.0]])
        array([[220., 190.]])
        """
        if self.crop_of is not None:  # (a crop of a crop: placed in the whole image)
            whole = (self.crop_of[0] + int(x0), self.crop_of[1] + int(y0), *self.crop_of[2:])
        else:
            whole = None if self.width is None or self.height is None else (int(x0), int(y0), int(self.width),
                                                                             int(self.height))
        return replace(self, cx=self.cx - x0, cy=self.cy - y0, width=int(x1 - x0), height=int(y1 - y0), crop_of=whole)

    def scaled(self, s: float, width: int | None = None, height: int | None = None, pad: int = 0) -> "PinholeCamera":
        """The camera of its image resized by ``s`` (pixel centres preserved: ``u' = s(u + ½) − ½``),
        then enlarged by ``pad`` pixels (of the resized image) on every side. The new size is
        ``width`` × ``height`` when given (the resized image's own), else the old one × ``s``,
        rounded. Distortion acts on normalised coordinates, so it is unchanged.

        >>> cam = PinholeCamera(800.0, 800.0, 319.5, 239.5, width=640, height=480).scaled(0.5)
        >>> (cam.fx, cam.cx, cam.cy, cam.width, cam.height)
        (400.0, 159.5, 119.5, 320, 240)
        """
        if width is None or height is None:
            if self.width is None or self.height is None:
                raise ValueError("the camera needs an image size to be scaled")
            width, height = max(1, int(round(self.width * s))), max(1, int(round(self.height * s)))
        return replace(self, fx=self.fx * s, fy=self.fy * s, cx=s * (self.cx + 0.5) - 0.5 + pad,
                       cy=s * (self.cy + 0.5) - 0.5 + pad, width=int(width) + 2 * pad, height=int(height) + 2 * pad,
                       crop_of=None)

    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (n, 2) of points (n, 3) given in *this* camera's frame.

        With distortion, a point beyond the radius where the lens model turns back
        (:attr:`valid_r2`, :func:`valid_radius2`) takes the model's last valid point in its
        direction, scaled outwards in proportion to its radius (``(x_d, y_d) = (r/r_max)·
        distort((x, y)·r_max/r)``): continuous and growing with ``r``, so outside the image the
        model describes, where the polynomial itself folds it back into the image (as
        cv2.projectPoints does). Within that radius: OpenCV's model exactly."""
        return self.project_with_jacobian(X_cam, jacobian=False)[0]

    def project_with_jacobian(
        self, X_cam: np.ndarray, jacobian: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Pixels (n, 2) and, if asked, ``∂uv/∂X_cam`` (n, 2, 3) for points in this camera's frame."""
        X = np.asarray(X_cam, dtype=float).reshape(-1, 3)
        iz = 1.0 / X[:, 2]
        x = X[:, 0] * iz
        y = X[:, 1] * iz
        if not self.has_distortion:
            uv = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=-1)
            if not jacobian:
                return uv, None
            J = np.zeros((X.shape[0], 2, 3))
            J[:, 0, 0] = self.fx * iz
            J[:, 0, 2] = -self.fx * x * iz
            J[:, 1, 1] = self.fy * iz
            J[:, 1, 2] = -self.fy * y * iz
            return uv, J
        return self._project_distorted(x, y, iz, jacobian)

    def _project_distorted(self, x, y, iz, jacobian: bool):
        """Distorted pixels of the normalised points ``(x, y)`` (``iz = 1/z``) and ``∂uv/∂X_cam``,
        in one compiled pass (:func:`_distorted_pass`). Why: written in numpy, ~30 whole-array
        operations on a few dozen points, it cost ~70–85 µs a call (now ~5), and the tracker
        projects ~35 times a frame: ``box.mp4``'s step through a lens took 13.3–13.5 ms p50
        against 11.5 ms now (bench/RESULTS.md, session 51). The same expressions, the same bits."""
        d = np.zeros(_MAX_DIST)
        d[: self.dist_coeffs.size] = self.dist_coeffs
        n = x.shape[0]
        uv = np.empty((n, 2))
        J = np.empty((n, 2, 3)) if jacobian else np.empty((0, 2, 3))
        _compiled_distorted_pass()(np.ascontiguousarray(x, np.float64), np.ascontiguousarray(y, np.float64),
                                   np.ascontiguousarray(iz, np.float64), d, float(self.fx), float(self.fy),
                                   float(self.cx), float(self.cy), bool(jacobian), uv, J, float(self.valid_r2))
        return uv, (J if jacobian else None)

    def _project_distorted_numpy(self, x, y, iz, jacobian: bool):
        """:meth:`_project_distorted` in numpy, as it was until session 51 (the reference of its
        test: tests/test_measurements.py), with the outward projection beyond :attr:`valid_r2`."""
        d = np.zeros(_MAX_DIST)
        d[: self.dist_coeffs.size] = self.dist_coeffs
        k1, k2, p1, p2, k3, k4, k5, k6 = d
        x_in, y_in = x, y
        r2 = x * x + y * y
        beyond = r2 > self.valid_r2
        if beyond.any():  # (the model at the last valid point of the same direction)
            k = np.ones_like(r2)
            k[beyond] = np.sqrt(r2[beyond] / self.valid_r2)
            c = 1.0 / k
            x, y = np.where(beyond, x * c, x), np.where(beyond, y * c, y)
            r2 = np.where(beyond, self.valid_r2, r2)  # (on the circle: not rounded past it)
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = num / den
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        if beyond.any():
            xq, yq = xd, yd
            xd, yd = np.where(beyond, xd * k, xd), np.where(beyond, yd * k, yd)
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)
        if not jacobian:
            return uv, None
        dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d num / d r2
        dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        dradial = (dnum * den - num * dden) / (den * den)  # d radial / d r2
        # ∂(xd, yd)/∂(x, y), with ∂r2/∂x = 2x, ∂r2/∂y = 2y
        dxd_dx = radial + x * dradial * 2 * x + 2 * p1 * y + p2 * 6 * x
        dxd_dy = x * dradial * 2 * y + 2 * p1 * x + p2 * 2 * y
        dyd_dx = y * dradial * 2 * x + p1 * 2 * x + 2 * p2 * y
        dyd_dy = radial + y * dradial * 2 * y + p1 * 6 * y + 2 * p2 * x
        if beyond.any():  # ∂/∂(x, y) of (r/r_max)·distort(u·r_max): distort·uᵀ/r_max + J_distort (I − u uᵀ)
            x, y = x_in, y_in
            b = np.flatnonzero(beyond)
            a00, a01, a10, a11 = (v[b].copy() for v in (dxd_dx, dxd_dy, dyd_dx, dyd_dy))
            u0, u1 = _outward(a00, a01, a10, a11, xq[b], yq[b], x[b], y[b], self.valid_r2)
            for out, val in zip((dxd_dx, dxd_dy, dyd_dx, dyd_dy), (*u0, *u1)):
                out[b] = val
        n = x.shape[0]
        J = np.empty((n, 2, 3))
        # ∂(x, y)/∂X = iz [[1, 0, -x], [0, 1, -y]]
        J[:, 0, 0] = self.fx * dxd_dx * iz
        J[:, 0, 1] = self.fx * dxd_dy * iz
        J[:, 0, 2] = -self.fx * (dxd_dx * x + dxd_dy * y) * iz
        J[:, 1, 0] = self.fy * dyd_dx * iz
        J[:, 1, 1] = self.fy * dyd_dy * iz
        J[:, 1, 2] = -self.fy * (dyd_dx * x + dyd_dy * y) * iz
        return uv, J


def _outward(a00, a01, a10, a11, xq, yq, x, y, r2max):
    """The Jacobian ``∂(x_d, y_d)/∂(x, y)`` of the outward projection ``(r/r_m)·distort(u·r_m)``
    (``u = (x, y)/r``, ``r_m² = r2max``) from the model's own ``[[a00, a01], [a10, a11]]`` and
    value ``(xq, yq)`` at ``u·r_m``: ``distort·uᵀ/r_m + J (I − u uᵀ)``, as two rows of two."""
    r = np.sqrt(x * x + y * y)
    rm = np.sqrt(r2max)
    ux, uy = x / r, y / r
    pxx, pxy, pyy = 1.0 - ux * ux, -ux * uy, 1.0 - uy * uy
    return ((xq * ux / rm + a00 * pxx + a01 * pxy, xq * uy / rm + a00 * pxy + a01 * pyy),
            (yq * ux / rm + a10 * pxx + a11 * pxy, yq * uy / rm + a10 * pxy + a11 * pyy))


def _distorted_pass(x, y, iz, d, fx, fy, cx, cy, jacobian, uv, J, r2max):  # pragma: no cover (compiled)
    """Per point, :meth:`PinholeCamera._project_distorted_numpy`'s expressions term for term
    (OpenCV's model: ``r² = x² + y²``, ``radial = (1 + k1 r² + k2 r⁴ + k3 r⁶)/(1 + k4 r² + k5 r⁴
    + k6 r⁶)``, ``x_d = x·radial + 2p1·x·y + p2(r² + 2x²)``, ``y_d = y·radial + p1(r² + 2y²) +
    2p2·x·y``, ``u = fx x_d + cx``, ``v = fy y_d + cy``), and the chain rule through
    ``∂(x, y)/∂X = 1/z [[1, 0, −x], [0, 1, −y]]`` into ``J`` when ``jacobian``. A point beyond
    ``r2max`` (:func:`valid_radius2`) takes the model at ``(x, y)/k``, ``k = √(r²/r2max)``,
    times ``k`` (and :func:`_outward`'s Jacobian)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]
    for i in range(x.shape[0]):
        xi, yi, izi = x[i], y[i], iz[i]
        r2 = xi * xi + yi * yi
        beyond = r2 > r2max
        k = 1.0
        x0, y0 = xi, yi
        if beyond:  # (no division by a quantity that can be 0: numba raises where numpy gives inf)
            k = np.sqrt(r2 / r2max)
            c = 1.0 / k
            xi, yi = xi * c, yi * c
            r2 = r2max  # (on the circle: not rounded past it, where a denominator may be 0)
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = num / den
        xd = xi * radial + 2.0 * p1 * xi * yi + p2 * (r2 + 2.0 * xi * xi)
        yd = yi * radial + p1 * (r2 + 2.0 * yi * yi) + 2.0 * p2 * xi * yi
        xq, yq = xd, yd
        if beyond:
            xd, yd = xd * k, yd * k
        uv[i, 0] = fx * xd + cx
        uv[i, 1] = fy * yd + cy
        if not jacobian:
            continue
        dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        dradial = (dnum * den - num * dden) / (den * den)
        dxd_dx = radial + xi * dradial * 2.0 * xi + 2.0 * p1 * yi + p2 * 6.0 * xi
        dxd_dy = xi * dradial * 2.0 * yi + 2.0 * p1 * xi + p2 * 2.0 * yi
        dyd_dx = yi * dradial * 2.0 * xi + p1 * 2.0 * xi + 2.0 * p2 * yi
        dyd_dy = radial + yi * dradial * 2.0 * yi + p1 * 6.0 * yi + 2.0 * p2 * xi
        if beyond:
            xi, yi = x0, y0
            rr = np.sqrt(xi * xi + yi * yi)
            rm = np.sqrt(r2max)
            ux, uy = xi / rr, yi / rr
            pxx, pxy, pyy = 1.0 - ux * ux, -ux * uy, 1.0 - uy * uy
            a00, a01, a10, a11 = dxd_dx, dxd_dy, dyd_dx, dyd_dy
            dxd_dx = xq * ux / rm + a00 * pxx + a01 * pxy
            dxd_dy = xq * uy / rm + a00 * pxy + a01 * pyy
            dyd_dx = yq * ux / rm + a10 * pxx + a11 * pxy
            dyd_dy = yq * uy / rm + a10 * pxy + a11 * pyy
        J[i, 0, 0] = fx * dxd_dx * izi
        J[i, 0, 1] = fx * dxd_dy * izi
        J[i, 0, 2] = -fx * (dxd_dx * xi + dxd_dy * yi) * izi
        J[i, 1, 0] = fy * dyd_dx * izi
        J[i, 1, 1] = fy * dyd_dy * izi
        J[i, 1, 2] = -fy * (dyd_dx * xi + dyd_dy * yi) * izi


_compiled_distorted_pass = lazily_compiled(_distorted_pass)

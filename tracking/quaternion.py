"""Unit quaternions for rotations: the algebra of Ude (1999), eqs. 3–10 and A.1–A.2.

Conventions, stated once for the whole project:

- ``q = [w, x, y, z]``: scalar first, Hamilton product (eq. 3), unit norm.
- ``rotate(q, v) = q * v * conj(q)`` (eq. 5) turns a vector of the object frame into the camera
  frame when ``q`` is the pose's orientation: ``X_cam = R(q) X_obj + t``.
- ``exp``/``log`` are Ude's (eqs. 6 and 9): ``exp(r) = (cos‖r‖, sin‖r‖ r/‖r‖)`` is a rotation by
  **2‖r‖**. A *rotation vector* (full angle, as in OpenCV's ``rvec``) ``phi`` is therefore
  ``exp(phi / 2)``; see :func:`from_rotvec` / :func:`to_rotvec`.
- Outputs meant for users are made canonical with ``w ≥ 0`` (:func:`canonical`).

Every function is vectorised over leading axes: quaternions are ``(..., 4)``, vectors ``(..., 3)``.

Examples
--------
A quarter turn about z, as a full rotation vector, then as Ude's half-angle ``exp``:

>>> q = from_rotvec([0.0, 0.0, np.pi / 2])
>>> q.round(4)
array([0.7071, 0.    , 0.    , 0.7071])
>>> bool(np.allclose(q, exp([0.0, 0.0, np.pi / 4])))          # exp(r) turns by 2‖r‖
True
>>> rotate(q, [1.0, 0.0, 0.0]).round(6)                       # x goes to y
array([0., 1., 0.])
>>> float(np.degrees(angle_between(q, IDENTITY)).round(6))
90.0
"""


from __future__ import annotations

import numpy as np

from .rotation import cross, skew

_SMALL = 1e-8  # below this ‖u‖ (or ‖r‖) series expansions replace the closed forms
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def _f(a) -> np.ndarray:
    return np.asarray(a, dtype=float)


def multiply(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product ``q1 * q2 = (w w' - u·u', w u' + w' u + u × u')`` (eq. 3)."""
    q1, q2 = _f(q1), _f(q2)
    w1, u1 = q1[..., :1], q1[..., 1:]
    w2, u2 = q2[..., :1], q2[..., 1:]
    w = w1 * w2 - np.sum(u1 * u2, axis=-1, keepdims=True)
    out = np.empty(np.broadcast_shapes(q1.shape, q2.shape))
    out[..., :1] = w
    out[..., 1:] = w1 * u2 + w2 * u1 + cross(u1, u2)
    return out


def conjugate(q: np.ndarray) -> np.ndarray:
    """``conj(q) = (w, -u)`` (eq. 4); the inverse of a unit quaternion."""
    q = _f(q)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def norm(q: np.ndarray) -> np.ndarray:
    """``|q| = sqrt(w² + uᵀu)`` (eq. 4)."""
    return np.linalg.norm(_f(q), axis=-1)


def canonical(q: np.ndarray) -> np.ndarray:
    """The same rotation with ``w ≥ 0`` (``q`` and ``-q`` rotate alike).

    For a half-turn (``w = 0``) the first non-zero of ``x, y, z`` is made positive, so that every
    rotation has exactly one canonical quaternion.
    """
    q = _f(q)
    lead = q[..., 0]
    for k in (1, 2, 3):
        lead = np.where(lead == 0.0, q[..., k], lead)
    return np.where(lead[..., None] < 0.0, -q, q)


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``q * v * conj(q)`` (eq. 5), computed as ``v + 2w (u × v) + 2 u × (u × v)``."""
    q, v = _f(q), _f(v)
    w, u = q[..., :1], q[..., 1:]
    uv = cross(u, v)
    return v + 2.0 * w * uv + 2.0 * cross(u, uv)


def exp(r: np.ndarray) -> np.ndarray:
    """Ude's exponential map (eq. 6): ``exp(r) = (cos‖r‖, sin‖r‖ · r/‖r‖)``, ``exp(0) = 1``.

    It is a rotation by ``2‖r‖`` about ``r``: ``exp(phi/2)`` is the rotation vector ``phi``.
    """
    r = _f(r)
    n = np.linalg.norm(r, axis=-1, keepdims=True)
    # sin(n)/n == np.sinc(n/π): exact at 0, no division.
    return np.concatenate([np.cos(n), np.sinc(n / np.pi) * r], axis=-1)


def log(q: np.ndarray) -> np.ndarray:
    """Ude's logarithm (eq. 9): ``log(q) = arccos(w) u/‖u‖``, the inverse of :func:`exp`.

    Defined on ``S³`` minus ``-1``, with values ``‖log q‖ < π``. Computed as
    ``atan2(‖u‖, w)/‖u‖ · u`` (stable for every ``w``), with the limit ``u/w`` at ``u → 0``.
    """
    q = _f(q)
    w, u = q[..., :1], q[..., 1:]
    s = np.linalg.norm(u, axis=-1, keepdims=True)
    # the limit u/w holds near +1 only: near -1 (w < 0) ‖log q‖ → π, and atan2(s, w)/s is exact
    # there for every s > 0 (u/w would give a near-zero log, i.e. -1 taken for +1)
    small = (s < _SMALL) & (w > 0)
    safe = np.where(s == 0, 1.0, s)
    factor = np.where(small, 1.0 / np.where(small, w, 1.0), np.arctan2(s, w) / safe)
    return factor * u


def exp_q(q: np.ndarray, r_q: np.ndarray) -> np.ndarray:
    """The exponential map at ``q`` (eq. 8): ``exp_q(r_q) = exp(r_q * conj(q)) * q``.

    ``r_q`` is a tangent vector of ``S³`` at ``q`` (a 4-vector orthogonal to ``q``); then
    ``r_q * conj(q)`` has a zero scalar part and is a tangent vector at ``1``.
    """
    q, r_q = _f(q), _f(r_q)
    r = multiply(r_q, conjugate(q))[..., 1:]
    return multiply(exp(r), q)


def distance(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Ude's angular metric on ``S³`` (eq. 10): ``d = 2‖log(q1 * conj(q2))‖``, ``2π`` at ``-1``.

    This is the geodesic length on the *sphere*: ``q`` and ``-q`` lie ``2π`` apart although they
    are one rotation. For the angle between two rotations use :func:`angle_between`.
    """
    c = multiply(q1, conjugate(q2))
    antipodal = np.all(np.isclose(c, -IDENTITY, rtol=0.0, atol=1e-15), axis=-1)
    d = 2.0 * np.linalg.norm(log(np.where(antipodal[..., None], IDENTITY, c)), axis=-1)
    return np.where(antipodal, 2.0 * np.pi, d)


def angle_between(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """The angle (rad, in ``[0, π]``) of the rotation taking ``q2`` to ``q1``: eq. 10 on ``SO(3)``."""
    c = canonical(multiply(q1, conjugate(q2)))
    return 2.0 * np.arctan2(np.linalg.norm(c[..., 1:], axis=-1), c[..., 0])


def from_rotvec(phi: np.ndarray) -> np.ndarray:
    """Quaternion of a full rotation vector (OpenCV ``rvec``, radians): ``exp(phi / 2)`` (eq. 7)."""
    return exp(0.5 * _f(phi))


def to_rotvec(q: np.ndarray) -> np.ndarray:
    """Full rotation vector (``‖phi‖ ≤ π``) of a unit quaternion: ``2 log(canonical(q))``."""
    return 2.0 * log(canonical(q))


def to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``R(q)`` with ``R(q) v = q * v * conj(q)``. Shape (..., 3, 3)."""
    q = _f(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (``w ≥ 0``) of a rotation matrix, by Shepperd's method.

    Picks, per matrix, the largest of ``4w², 4x², 4y², 4z²`` to divide by, so no branch loses
    precision: a half-turn (``w = 0``, e.g. ``diag(1, −1, −1)``) is as exact as any other
    rotation, and its quaternion is made canonical by :func:`canonical`. The result is
    renormalised only to absorb a slightly non-orthogonal input (``RRᵀ = I`` within 1e-3).

    Anything else is not a rotation and has no quaternion: a ``ValueError`` (``−I`` or another
    reflection, ``det R < 0``, was read as a half-turn; a zero matrix as the identity).

    >>> from_matrix(np.diag([1.0, -1.0, -1.0]))                  # a half-turn about x
    array([0., 1., 0., 0.])
    >>> from_matrix(-np.eye(3))
    Traceback (most recent call last):
    ...
    ValueError: not a rotation matrix (orthonormal within 0.001, det +1): det = -1
    """
    R = _f(R)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"a rotation matrix is 3×3, got shape {R.shape}")
    _check_rotation(R)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack(
        [
            np.stack([1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
            np.stack([R[..., 2, 1] - R[..., 1, 2], 1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
            np.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1]], -1),
            np.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        -2,
    )  # row k is 4·q_k·q
    k = np.argmax(np.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1), axis=-1)
    q = np.take_along_axis(cand, k[..., None, None], axis=-2)[..., 0, :]
    return canonical(q / np.linalg.norm(q, axis=-1, keepdims=True))


def _check_rotation(R: np.ndarray, atol: float = 1e-3) -> None:
    """ValueError unless every matrix of ``R`` (..., 3, 3) is finite, orthonormal within ``atol``
    and of determinant +1 (the tolerance of :meth:`tracking.pose.Pose.from_matrix`)."""
    if not np.all(np.isfinite(R)):
        raise ValueError("not a rotation matrix: it holds a NaN or an infinity")
    det = np.linalg.det(R)
    off = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(axis=(-2, -1))
    bad = (off > atol) | (det <= 0.0)
    if np.any(bad):
        first = np.argwhere(np.atleast_1d(bad))[0]
        d = float(np.atleast_1d(det)[tuple(first)])
        where = "" if R.ndim == 2 else f" at index {tuple(int(i) for i in first)}"
        raise ValueError(f"not a rotation matrix (orthonormal within {atol:g}, det +1){where}: det = {d:.4g}")


def left_matrix(q: np.ndarray) -> np.ndarray:
    """``L(q)`` with ``q * p = L(q) p``. Shape (..., 4, 4)."""
    return _product_matrix(q, 1.0)


def right_matrix(q: np.ndarray) -> np.ndarray:
    """``R(q)`` with ``p * q = R(q) p``. Shape (..., 4, 4)."""
    return _product_matrix(q, -1.0)


def _product_matrix(q: np.ndarray, side: float) -> np.ndarray:
    """``[[w, -uᵀ], [u, w I + side·[u]×]]``: the Hamilton product with ``q`` as a matrix, on the
    left (side +1) or on the right (side −1): only the cross-product term changes sign."""
    q = _f(q)
    w, u = q[..., 0], q[..., 1:]
    out = np.empty(q.shape[:-1] + (4, 4))
    out[..., 0, 0] = w
    out[..., 0, 1:] = -u
    out[..., 1:, 0] = u
    out[..., 1:, 1:] = w[..., None, None] * np.eye(3) + side * skew(u)
    return out


def dlog(q: np.ndarray) -> np.ndarray:
    """Jacobian of :func:`log` with respect to ``q = (w, x, y, z)`` in R⁴ (eqs. A.1, A.2). Shape (..., 3, 4).

    With ``a = arctan(‖u‖/w)/‖u‖`` (A.1): column 0 is ``-u`` and the 3×3 block is
    ``a I + (w - a) u uᵀ/‖u‖²``; at ``q = 1`` it is ``[0 | I]`` (A.2). A.1 uses ``w² + ‖u‖² = 1``,
    so it holds on the unit sphere. ``arctan(‖u‖/w)`` is taken as ``atan2(‖u‖, w)`` so that it
    also holds for ``w < 0``.
    """
    q = _f(q)
    w, u = q[..., 0], q[..., 1:]
    s2 = np.sum(u * u, axis=-1)
    s = np.sqrt(s2)
    small = s < _SMALL
    safe = np.where(small, 1.0, s)
    a = np.where(small, 1.0 / np.where(small, w, 1.0), np.arctan2(s, w) / safe)
    # (w - a)/‖u‖² tends to -2/3 as u → 0, and multiplies u uᵀ = O(‖u‖²): dropping it there is exact
    # to double precision.
    coeff = np.where(small, 0.0, (w - a) / np.where(small, 1.0, s2))
    out = np.empty(q.shape[:-1] + (3, 4))
    out[..., :, 0] = -u
    out[..., :, 1:] = a[..., None, None] * np.eye(3) + coeff[..., None, None] * (u[..., :, None] * u[..., None, :])
    return out


def dexp(r: np.ndarray) -> np.ndarray:
    """Jacobian of :func:`exp` with respect to ``r``. Shape (..., 4, 3).

    ``∂w/∂r = -sin‖r‖ r/‖r‖``; ``∂(sin‖r‖ r/‖r‖)/∂r = (sin‖r‖/‖r‖) I + (cos‖r‖ - sin‖r‖/‖r‖) n nᵀ``
    with ``n = r/‖r‖``; at ``r = 0`` it is ``[0; I]`` (cf. Kim, Kim & Shin 1996, cited as [4]).
    """
    r = _f(r)
    n = np.linalg.norm(r, axis=-1)
    small = n < 1e-6
    safe = np.where(small, 1.0, n)
    sinc = np.sinc(n / np.pi)
    # (cos n - sin n / n)/n² → -1/3 as n → 0
    c = np.where(small, -1.0 / 3.0 + n**2 / 30.0, (np.cos(safe) - np.sin(safe) / safe) / safe**2)
    out = np.empty(r.shape[:-1] + (4, 3))
    out[..., 0, :] = -sinc[..., None] * r
    out[..., 1:, :] = sinc[..., None, None] * np.eye(3) + c[..., None, None] * (r[..., :, None] * r[..., None, :])
    return out

"""The one pose type of quatrack: a rigid transform object → camera, ``X_cam = R(q) · X_obj + t``.

Every layer passes poses as :class:`Pose`; they become JSON (``{"t", "q_wxyz"}``), CSV columns,
OpenCV ``rvec``/``tvec`` or 4×4 matrices only at the edges. The filter state keeps Ude's ``p, q``
and converts with :attr:`tracking.state.FilterState.pose`.

The group is SE(3) written as a unit quaternion and a translation, as jaxlie's ``SE3`` and
Sophus' ``SE3d``:

- composition ``(a ∘ b).apply(X) = a.apply(b.apply(X))``: ``q = q_a ⊗ q_b``, ``t = R_a t_b + t_a``;
- inverse: ``q⁻¹ = q̄``, ``t⁻¹ = −R(q)ᵀ t``;
- the quaternion is kept unit and canonical (``w ≥ 0``): ``q`` and ``−q`` are one rotation.

>>> import numpy as np
>>> a = Pose.from_rvec([0.0, 0.0, np.pi / 2], [1.0, 0.0, 0.0])
>>> a.apply([1.0, 0.0, 0.0]).round(6)            # rotate x onto y, then shift by t
array([1., 1., 0.])
>>> bool(np.allclose((a @ a.inverse()).as_matrix(), np.eye(4)))
True
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from . import quaternion as quat


def _numbers(value: Any, shape, name: str) -> np.ndarray:
    """``value`` as a float array of ``shape`` (an int: a vector of that length), or a ValueError
    that says so (numpy's own says "cannot reshape array of size 3 into shape (4,)")."""
    want = (shape,) if isinstance(shape, int) else tuple(shape)
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {_shape_words(want)}, got {type(value).__name__}") from None
    if a.shape == want:  # (the usual case, first: a pose is made ~100 times a frame)
        return a
    if a.size != int(np.prod(want)) or (a.ndim > 1 and len(want) > 1):
        raise ValueError(f"{name} must be {_shape_words(want)}, got shape {a.shape}")
    return a.reshape(want)


def _shape_words(shape: tuple) -> str:
    return f"{shape[0]} numbers" if len(shape) == 1 else "a " + "×".join(map(str, shape)) + " matrix of numbers"


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Pose:
    """Object → camera: ``X_cam = R(q_wxyz) · X_obj + t``; ``t`` in the object mesh's units.

    ``q_wxyz`` is normalised and made canonical (``w ≥ 0``) on construction; both arrays are
    read-only, so a pose can be shared freely. Construct from other forms with
    :meth:`from_matrix`, :meth:`from_rvec` or :meth:`from_homogeneous`. Poses compare by value,
    exactly (``==``; :meth:`allclose` with a tolerance), and hash alike when equal.
    """

    q_wxyz: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        q = _numbers(self.q_wxyz, 4, "q_wxyz")
        t = _numbers(self.t, 3, "t")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
            raise ValueError("a pose must be finite")
        big = max(abs(v) for v in q.tolist())
        if big > 1e150:  # (‖q‖ of 1e300s would overflow: brought to order 1 first)
            q = q / big
        n = float(np.linalg.norm(q))
        if not n > 1e-12:
            raise ValueError("a pose's quaternion must not be zero")
        object.__setattr__(self, "q_wxyz", _readonly(quat.canonical(q / n)))
        object.__setattr__(self, "t", _readonly(t))

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def identity(cls) -> "Pose":
        """``R = I``, ``t = 0``."""
        return cls(quat.IDENTITY, np.zeros(3))

    @classmethod
    def from_matrix(cls, R: Any, t: Any = None) -> "Pose":
        """From a 3×3 rotation matrix (rows) and a translation. ``R`` must be a rotation:
        orthonormal within 1e-3 (``RRᵀ ≈ I``) and ``det R > 0`` — a reflection or a scaled
        matrix has no quaternion, and was read as some rotation without a word. A 4×4 (or 3×4)
        matrix alone, as :meth:`as_matrix` gives, is :meth:`from_homogeneous`'s (it was
        "missing 't'").

        >>> Pose.from_matrix(np.diag([1.0, 1.0, -1.0]), [0.0, 0.0, 1.0])
        Traceback (most recent call last):
        ...
        ValueError: R is not a rotation matrix (orthonormal, det +1)
        """
        if t is None:
            if np.shape(R) in ((4, 4), (3, 4)):
                return cls.from_homogeneous(R)
            raise TypeError("Pose.from_matrix(R, t): give t with a 3×3 R, or a 4×4 [[R, t], [0, 1]] alone")
        R = _numbers(R, (3, 3), "R")
        if not (np.all(np.isfinite(R)) and np.allclose(R @ R.T, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0):
            raise ValueError("R is not a rotation matrix (orthonormal, det +1)")
        return cls(quat.from_matrix(R), t)

    @classmethod
    def from_homogeneous(cls, T: Any) -> "Pose":
        """From a 4×4 matrix ``[[R, t], [0, 1]]`` or its top 3×4 ``[R t]``; a 4×4 whose last row
        is not ``[0, 0, 0, 1]`` (a transposed matrix, a projection) is refused."""
        T = np.asarray(T, float)
        if T.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"a homogeneous pose is 4×4 or 3×4, got shape {T.shape}")
        if T.shape == (4, 4) and not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError(f"a 4×4 pose's last row must be [0, 0, 0, 1], got {T[3].tolist()} (transposed?)")
        return cls.from_matrix(T[:3, :3], T[:3, 3])

    @classmethod
    def from_rvec(cls, rvec: Any, tvec: Any) -> "Pose":
        """From OpenCV's ``rvec, tvec`` (Rodrigues: ``rvec`` = axis · angle, radians)."""
        return cls(quat.from_rotvec(_numbers(rvec, 3, "rvec")), _numbers(tvec, 3, "tvec"))

    # -- views -------------------------------------------------------------------------------
    @cached_property
    def R(self) -> np.ndarray:
        """The 3×3 rotation matrix ``R(q)`` (eq. 5 of Ude 1999), read-only."""
        return _readonly(quat.to_matrix(self.q_wxyz))

    @property
    def rvec(self) -> np.ndarray:
        """OpenCV's rotation vector (axis · angle, radians), shape (3,)."""
        return quat.to_rotvec(self.q_wxyz)

    def as_matrix(self) -> np.ndarray:
        """The 4×4 homogeneous matrix ``[[R, t], [0, 1]]``."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    def to_json(self, digits: int | None = None) -> dict:
        """``{"t": [...], "q_wxyz": [...]}``, the contract's pose object."""
        r = (lambda v: float(v)) if digits is None else (lambda v: round(float(v), digits))
        return {"t": [r(v) for v in self.t], "q_wxyz": [r(v) for v in self.q_wxyz]}

    # -- group operations --------------------------------------------------------------------
    def apply(self, X: Any) -> np.ndarray:
        """Points (..., 3) from the object frame into the camera frame: ``R X + t``."""
        return np.asarray(X, float) @ self.R.T + self.t

    def compose(self, other: "Pose") -> "Pose":
        """``self ∘ other``: first ``other``, then ``self`` (``q = q_s ⊗ q_o``, ``t = R_s t_o + t_s``).

        >>> a = Pose.from_rvec([0.1, 0.2, 0.3], [1.0, 2.0, 3.0])
        >>> b = Pose.from_rvec([-0.3, 0.0, 0.5], [0.0, -1.0, 4.0])
        >>> bool(np.allclose(a.compose(b).apply([1.0, 2.0, 3.0]), a.apply(b.apply([1.0, 2.0, 3.0]))))
        True
        """
        if not isinstance(other, Pose):  # (a 4×4 array: AttributeError 'q_wxyz')
            raise TypeError(f"a Pose composes with a Pose, got {type(other).__name__} "
                            f"(Pose.from_homogeneous reads a 4×4 matrix)")
        return Pose(quat.multiply(self.q_wxyz, other.q_wxyz), self.R @ other.t + self.t)

    __matmul__ = compose

    def inverse(self) -> "Pose":
        """Camera → object: ``q̄`` and ``−Rᵀ t``."""
        return Pose(quat.conjugate(self.q_wxyz), -self.R.T @ self.t)

    def viewing_direction(self, point: Any) -> np.ndarray:
        """Unit vector, in the object frame, from ``point`` (object frame) towards the camera:
        ``d = −Rᵀ(R x + t) / ‖·‖`` (the camera centre is ``−Rᵀ t``). The direction a view sees
        the object from; unlike the rotation it ignores the camera's roll, to which SIFT is blind.

        >>> in_front = Pose.from_rvec([0.0, 0.0, 0.0], [0.0, 0.0, 5.0])  # 5 units ahead, unturned
        >>> bool(np.allclose(in_front.viewing_direction([0.0, 0.0, 0.0]), [0.0, 0.0, -1.0]))
        True
        """
        d = -self.R.T @ self.apply(np.asarray(point, float))
        return d / np.linalg.norm(d)

    def view_angle(self, other: "Pose", point: Any) -> float:
        """Angle (radians) between the directions ``self`` and ``other`` see ``point`` from."""
        c = float(self.viewing_direction(point) @ other.viewing_direction(point))
        return float(np.arccos(np.clip(c, -1.0, 1.0)))

    # -- comparison --------------------------------------------------------------------------
    def distance(self, other: "Pose") -> tuple[float, float]:
        """``(‖t − t_o‖, angle between the rotations in radians)``: the error measures of the
        benchmarks (translation in mesh units)."""
        return float(np.linalg.norm(self.t - other.t)), float(quat.angle_between(self.q_wxyz, other.q_wxyz))

    def allclose(self, other: "Pose", atol: float = 1e-9) -> bool:
        """Same transform within ``atol`` (translation and quaternion components; ``q ≡ −q``)."""
        return bool(np.allclose(self.t, other.t, atol=atol) and np.allclose(self.q_wxyz, other.q_wxyz, atol=atol))

    def __eq__(self, other: object) -> bool:
        """Exact value equality: the same ``q_wxyz`` and ``t``, number for number (both are
        canonical, so one transform has one representation; ``−0.0 == 0.0``). Not a tolerance:
        for "the same within rounding" use :meth:`allclose` or :meth:`distance`. (It was the
        dataclass's identity: two poses made alike compared unequal.)

        >>> Pose.from_rvec([0.0, 0.0, 0.5], [1.0, 2.0, 3.0]) == Pose.from_rvec([0.0, 0.0, 0.5], [1.0, 2.0, 3.0])
        True
        >>> Pose.identity() == Pose(-quat.IDENTITY, [0.0, 0.0, 0.0])    # q and −q: one rotation
        True
        >>> len({Pose.identity(), Pose.identity()})                     # hashable, by value
        1
        """
        if not isinstance(other, Pose):
            return NotImplemented
        return self is other or (np.array_equal(self.q_wxyz, other.q_wxyz) and np.array_equal(self.t, other.t))

    def __hash__(self) -> int:
        """Consistent with ``==``: equal floats hash alike (``hash(−0.0) == hash(0.0)``); a pose
        is immutable (frozen, read-only arrays), so it may be a dict key or a set member."""
        return hash((*self.q_wxyz.tolist(), *self.t.tolist()))

    def __repr__(self) -> str:
        """To 6 decimals, a negative zero shown as 0.0 (``+ 0.0``: a rotation about y printed
        ``q_wxyz=[0.988771, -0.0, 0.149438, -0.0]``).

        >>> Pose.from_rvec([0.0, 0.3, 0.0], [40.0, -0.0, 600.0])
        Pose(q_wxyz=[0.988771, 0.0, 0.149438, 0.0], t=[40.0, 0.0, 600.0])
        """
        return f"Pose(q_wxyz={(np.round(self.q_wxyz, 6) + 0.0).tolist()}, t={(np.round(self.t, 6) + 0.0).tolist()})"

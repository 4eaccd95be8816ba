"""Settings dataclasses checked field by field: every field of the kind its annotation says.

Why: a settings object is built by users (``PoseParams(ransac_px="6")``, a dict where a nested
settings object belongs) and its values surface only deep in a call — "'<' not supported between
'int' and 'str'" at the first frame, a numpy UFuncTypeError, ``refresh_every=2.5`` run as given.
:func:`check_field_kinds` refuses them at construction, naming the field. One function for every
settings class (``TrackerParams``, ``PoseParams``, ``LocateParams``, ``WindowSearchParams``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import fields

import numpy as np

__all__ = ["check_field_kinds", "is_number"]


def is_number(value) -> bool:
    """A real number, not a bool or a string (``np.isfinite`` raised a TypeError naming no field)."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def check_field_kinds(obj, settings: dict[str, type] | None = None) -> None:
    """Every field of the (frozen) dataclass ``obj`` of the kind its annotation says, or a
    ValueError naming it (a TypeError for a nested settings object of the wrong type). Checked
    kinds: ``int`` (a whole number ≥ 0; stored as Python's ``int``), ``float`` (a finite number),
    ``bool`` (True or False, not a truthy string),
    ``tuple[float, ...]`` (numbers), any of those ``| None`` (None allowed), and the class names
    in ``settings`` (an instance of it); other annotations are left alone.

    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... class P:
    ...     n: int = 3
    ...     x: float = 1.0
    ...     def __post_init__(self):
    ...         check_field_kinds(self)
    >>> P(n=4.0).n, P(x=2).x
    (4, 2)
    >>> P(x="2")
    Traceback (most recent call last):
    ...
    ValueError: x must be a finite number, not '2'
    """
    settings = settings or {}
    for f in fields(obj):
        kind, value = f.type, getattr(obj, f.name)
        if value is None and kind.endswith("| None"):
            continue
        kind = kind.removesuffix(" | None")
        if kind == "int":
            if not (is_number(value) and np.isfinite(value) and float(value).is_integer() and value >= 0):
                raise ValueError(f"{f.name} must be a whole number >= 0, not {value!r}"[:120])
            object.__setattr__(obj, f.name, int(value))  # (150.0, numpy's ints: Python's int)
        elif kind == "float":
            if not (is_number(value) and np.isfinite(value)):
                raise ValueError(f"{f.name} must be a finite number, not {value!r}"[:120])
        elif kind == "bool":
            if not isinstance(value, (bool, np.bool_)):  # (learn="yes" was taken as true, "no" too)
                raise ValueError(f"{f.name} must be True or False, not {value!r}"[:120])
            object.__setattr__(obj, f.name, bool(value))
        elif kind == "tuple[float, ...]":
            if isinstance(value, (str, bytes)) or not isinstance(value, Iterable) \
                    or not all(is_number(v) and np.isfinite(v) for v in value):
                raise ValueError(f"{f.name} must be a tuple of numbers, e.g. (20.0,), not {value!r}"[:120])
        elif kind in settings and not isinstance(value, settings[kind]):
            raise TypeError(f"{f.name}: a {kind}, got {type(value).__name__}")

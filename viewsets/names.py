"""Object names: they become folder names in the model store, so they must not escape it."""

from __future__ import annotations

import re

from .errors import StoreError

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


def check_object_name(name: object) -> str:
    """Return ``name`` if it is a safe object name (letters, digits, ``._-``, ≤ 64, no leading dot)."""
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise StoreError(
            f"invalid object name {name!r}: use 1-64 letters, digits, '.', '_' or '-', starting with a letter or digit"
        )
    return name

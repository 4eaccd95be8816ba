"""Object names: they become folder names in the model store, so they must not escape it."""

from __future__ import annotations

import re

from .errors import StoreError

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
# names a command gives a meaning of its own: ``quatrack locate --object all`` searches every
# object, so an object trained as ``all`` could never be located alone. Refused for new training
# only (:func:`~.spec.load_spec`); a store that already holds one still lists and loads it.
RESERVED = frozenset({"all"})


def check_object_name(name: object, new: bool = False) -> str:
    """Return ``name`` if it is a safe object name (letters, digits, ``._-``, ≤ 64, no leading dot);
    ``new`` (a name to train under): not a :data:`RESERVED` one either."""
    if not isinstance(name, str) or not NAME_RE.match(name):
        if isinstance(name, str) and name.endswith("/") and NAME_RE.match(name.rstrip("/")):
            raise StoreError(f"invalid object name {name!r}: drop the trailing '/' (the shell's completion of its "
                             f"folder): {name.rstrip('/')!r}")
        raise StoreError(
            f"invalid object name {name!r}: use 1-64 letters, digits, '.', '_' or '-', starting with a letter or digit"
        )
    if new and name in RESERVED:
        raise StoreError(f"object name {name!r} is reserved (`quatrack locate --object all` searches every object): "
                         f"choose another name")
    return name

"""The bundled example objects, installed as package data (``quatrack.examples``) so every
command and benchmark finds them from any working directory and from a non-editable install.

>>> (example_dir("cookie-box") / "object.json").is_file()
True
"""

from __future__ import annotations

from pathlib import Path

#: The object every default of the commands refers to (OpenCV's cookie box; see its README).
DEFAULT_EXAMPLE = "cookie-box"


def example_dir(name: str = DEFAULT_EXAMPLE) -> Path:
    """The folder of a bundled example (``object.json``, ``camera.json``, mesh, photo, video)."""
    path = Path(__file__).resolve().parent / name
    if not (path / "object.json").is_file():
        known = sorted(p.name for p in Path(__file__).resolve().parent.iterdir() if (p / "object.json").is_file())
        raise FileNotFoundError(f"no bundled example {name!r}; bundled: {', '.join(known) or 'none'}")
    return path

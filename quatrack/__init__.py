"""quatrack: find, pose and track a known textured object (see README.md)."""

__version__ = "0.2.0"  # the one place it is written: pyproject.toml reads it (models record the installed one)

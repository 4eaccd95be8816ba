"""quatrack: find, pose and track a known textured object (see README.md)."""

__version__ = "0.1.0"

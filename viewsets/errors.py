"""Error types of the object-model layer: all are ``ValueError`` so the CLI reports them in one line."""

from __future__ import annotations


class SpecError(ValueError):
    """Bad training input (spec, camera, pose, mesh, image): the message names the file/field/view."""


class StoreError(ValueError):
    """Bad model-store request: invalid object name, unknown object, refused overwrite, corrupt model."""

"""Users' own meshes and specs: the formats exporters write, their quirks, and the messages a
mistake gets (one line, naming the culprit, nothing stored)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from quatrack.cli import main
from quatrack.viewsets.errors import SpecError
from quatrack.viewsets.mesh import load_mesh
from quatrack.viewsets.spec import parse_pose

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cookie-box"

# a 2 × 3 × 1 box: 8 corners, its 6 sides as quads (outward)
CORNERS = np.array([[x, y, z] for x in (0, 2.0) for y in (0, 3.0) for z in (0, 1.0)])
QUADS = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]


def _triangles(quads):
    return np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def test_a_folder_named_as_the_mesh_is_called_a_folder(tmp_path):
    (tmp_path / "box.ply").mkdir()
    with pytest.raises(SpecError, match="a folder, not a mesh file"):
        load_mesh(tmp_path / "box.ply")


def test_a_file_of_another_kind_named_as_the_mesh_says_which_formats_are_read(tmp_path):
    cv2.imwrite(str(tmp_path / "texture.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(SpecError) as info:
        load_mesh(tmp_path / "texture.png")
    msg = str(info.value)
    assert "not a mesh file format" in msg and ".png" in msg and "PLY, OBJ" in msg
    assert "NotImplementedError" not in msg

"""make_mesh's faces: whole vertex indices (integral floats as loadtxt gives them are taken);
anything else is a SpecError naming it (viewsets/mesh.py)."""

import numpy as np
import pytest

from quatrack.viewsets.errors import SpecError
from quatrack.viewsets.mesh import make_mesh

TETRA = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
FACES = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]


@pytest.mark.parametrize("faces, got", [
    (np.array(FACES) + [0, 0.5, 0], "got 2.5"),  # (was cut to 2: another triangle, in silence)
    (np.where(np.eye(4, 3, dtype=bool), np.nan, np.array(FACES, float)), "got nan"),  # (was IndexError -2147483648)
    (np.array(FACES).astype(str), "got text"),  # (was numpy's UFuncTypeError)
    (np.array(FACES).astype(bool), "got True/False values"),
])
def test_faces_that_are_not_whole_indices_are_refused_naming_what_they_are(faces, got):
    with pytest.raises(SpecError, match=f"^mesh: faces must be whole vertex indices, {got}$"):
        make_mesh(TETRA, faces)


def test_rows_of_different_lengths_are_refused_as_no_triangles():
    # (was numpy's "setting an array element with a sequence ... inhomogeneous shape")
    with pytest.raises(SpecError, match=r"faces must be an \(m, 3\) array of vertex indices \(triangles\), got shape"):
        make_mesh(TETRA, [[0, 2, 1], [0, 1]])


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.uint8, np.float64, np.float32])
def test_whole_indices_of_any_number_type_make_the_same_mesh(dtype):
    mesh = make_mesh(TETRA, np.array(FACES, dtype))
    assert mesh.faces.dtype == np.int32 and mesh.faces.tolist() == FACES

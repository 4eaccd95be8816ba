"""pyproject.toml's dependency floors against what the code calls (nothing installed, nothing built).

A trial install at the declared floors failed: uvicorn 0.30-0.34 has no
``websockets_sansio_impl`` (service/shutdown.py), OpenCV 4.x's ``undistortPoints`` takes no
termination criteria (viewsets/render.py: even 4.13 refused 7 arguments) and Starlette 0.36's
``Request.form`` no ``max_part_size`` (service/routes.py). Each row below names the code that
needs a release and the first release that has it; a floor below it fails here.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]

# (source file, what it uses (a regular expression), distribution, first release that has it, where that is said)
USES = [
    ("service/shutdown.py", r"uvicorn\.protocols\.websockets\.websockets_sansio_impl", "uvicorn", "0.35",
     "uvicorn 0.35.0 added the sans-I/O websockets protocol"),
    ("service/routes.py", r"\.form\([^)]*max_part_size=", "starlette", "0.44",
     "Starlette 0.44.0: 'Add max_part_size parameter to Request.form()'"),
    ("service/routes.py", r"\.form\([^)]*max_part_size=", "fastapi", "0.115.7",
     "FastAPI 0.115.6 pins starlette<0.42; 0.115.7 allows <0.46"),
    ("viewsets/render.py", r"cv2\.undistortPoints\((?s:.{0,200}?)None, None, None,\s*\(cv2\.TERM_CRITERIA",
     "opencv-contrib-python-headless", "5.0", "4.13's undistortPoints takes at most 6 arguments"),
    ("recognition/trackio.py", r"cv2\.utils\.logging", "opencv-contrib-python-headless", "5.0",
     "the logging module the capture's warnings are quieted with"),
]

# (distribution, at or above this floor, needs, at least): what a floor's release itself requires
IMPLIED = [
    ("opencv-contrib-python-headless", "5.0", "numpy", "2.0"),  # its wheels: numpy>=2 (Python >= 3.9)
    ("numpy", "2.0", "scipy", "1.13"),  # the first SciPy built against numpy 2
    ("numpy", "2.0", "numba", "0.60"),  # the first numba for numpy 2
    ("python", "3.13", "numba", "0.61"),  # the first numba for Python 3.13 (requires-python allows it)
]


def floors() -> dict[str, Version]:
    """Each dependency's lower bound (``>=``) in pyproject.toml, by normalised name."""
    out = {}
    for text in PROJECT["dependencies"]:
        req = Requirement(text)
        lows = [Version(s.version) for s in req.specifier if s.operator in (">=", "==", "~=")]
        assert lows, f"{text}: no lower bound"
        out[req.name.lower().replace("_", "-")] = max(lows)
    return out


@pytest.mark.parametrize("source, pattern, dist, first, why", USES, ids=[f"{u[2]}-{u[0]}" for u in USES])
def test_a_floor_has_what_the_code_calls(source, pattern, dist, first, why):
    text = (ROOT / source).read_text(encoding="utf-8")
    if not re.search(pattern, text):
        pytest.skip(f"{source} no longer uses it: drop this row")
    have = floors()
    assert dist in have, f"{source} needs {dist} but pyproject.toml does not declare it"
    assert have[dist] >= Version(first), f"{dist}>={have[dist]} is below {first}, which {source} needs ({why})"


@pytest.mark.parametrize("dist, at, needs, least", IMPLIED, ids=[f"{i[0]}-{i[2]}" for i in IMPLIED])
def test_floors_agree_with_each_other(dist, at, needs, least):
    have = floors()
    top = max(Requirement(f"python{PROJECT['requires-python']}").specifier.filter(["3.11", "3.12", "3.13", "3.14"]),
              key=Version) if dist == "python" else have.get(dist)
    if top is None or Version(str(top)) < Version(at):
        pytest.skip(f"{dist} may be below {at}")
    assert have[needs] >= Version(least), f"{dist} {at} needs {needs}>={least}; pyproject.toml says >={have[needs]}"

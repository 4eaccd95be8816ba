"""Every ``Examples``/``>>>`` block in the installed package runs as a test (issue 10: the
docstrings' examples are part of the documentation, so they must stay true)."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import numpy as np
import pytest

import quatrack

# The product's layers; bench/ is a command, not a library, and is left out.
PACKAGES = ["quatrack", "quatrack.tracking", "quatrack.viewsets", "quatrack.recognition", "quatrack.recognition.tracker",
            "quatrack.service",
            "quatrack.examples"]


def _modules() -> list[str]:
    names = []
    for pkg in PACKAGES:
        mod = importlib.import_module(pkg)
        names.append(pkg)
        for info in pkgutil.iter_modules(mod.__path__, pkg + "."):
            if not info.name.endswith(".__main__"):  # importing it would run the CLI
                names.append(info.name)
    return sorted(set(names))


@pytest.mark.parametrize("name", _modules())
def test_docstring_examples_hold(name: str) -> None:
    module = importlib.import_module(name)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    with np.printoptions(legacy="1.25"):  # numpy ≥ 2 prints scalars as np.float64(...)
        for test in finder.find(module, name, extraglobs={"np": np}):
            runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{result.failed} docstring example(s) of {name} failed (see the output above)"


def test_the_examples_are_found() -> None:
    """The collection above must not silently find nothing."""
    assert "quatrack.tracking.pose" in _modules()
    assert quatrack.__name__ == "quatrack"

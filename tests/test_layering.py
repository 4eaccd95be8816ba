"""Imports point one way only (docs/architecture.md): tracking ← viewsets ← recognition ← service
← quatrack (CLI, client) and bench; the test fixtures (quatrack.testing) sit above recognition. A lower layer importing a higher one is a layering leak."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# folder → (package, rank); a module may import packages of its rank or lower
LAYERS = {"tracking": ("quatrack.tracking", 0), "viewsets": ("quatrack.viewsets", 1),
          "recognition": ("quatrack.recognition", 2), "service": ("quatrack.service", 3),
          "testing": ("quatrack.testing", 2.5),  # ground-truth fixtures: above recognition, below the service
          "quatrack": ("quatrack", 4), "bench": ("quatrack.bench", 4)}  # CLI and bench: both thin tops
EVERYONE = {"quatrack.examples"}  # the bundled example data, below every layer


def _rank(module: str) -> int | None:
    if any(module == e or module.startswith(e + ".") for e in EVERYONE):
        return None
    best = None
    for pkg, rank in LAYERS.values():
        if module == pkg or module.startswith(pkg + "."):
            if best is None or len(pkg) > len(best[0]):
                best = (pkg, rank)
    return None if best is None else best[1]


def _imports(path: Path, package: str) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the module's own package
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                names.append(f"{base}.{node.module}" if node.module else base)
            elif node.module:
                names.append(node.module)
    return names


def _modules():
    for folder, (pkg, rank) in LAYERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            sub = path.relative_to(ROOT / folder).with_suffix("").parts
            package = ".".join((pkg, *sub[:-1]))
            yield pytest.param(path, package, rank, id=str(path.relative_to(ROOT)))


@pytest.mark.parametrize("path, package, rank", list(_modules()))
def test_imports_point_down(path: Path, package: str, rank: int) -> None:
    upward = [m for m in _imports(path, package) if (r := _rank(m)) is not None and r > rank]
    assert not upward, f"{path.relative_to(ROOT)} imports a higher layer: {upward}"


def test_the_check_sees_a_leak(tmp_path: Path) -> None:
    """The checker itself must be able to fail."""
    leak = tmp_path / "leak.py"
    leak.write_text("from quatrack.service.app import create_app\nfrom ..recognition import locate\n")
    found = [m for m in _imports(leak, "quatrack.viewsets") if (_rank(m) or 0) > 1]
    assert found == ["quatrack.service.app", "quatrack.recognition"]


@pytest.mark.parametrize("path, package, rank", list(_modules()))
def test_every_quatrack_import_resolves(path: Path, package: str, rank: int) -> None:
    """Imports inside functions run only when that path runs (a benchmark, a rare error): a
    module moved or renamed must not leave one behind that fails there, long after the tests."""
    import importlib.util

    missing = []
    for name in _imports(path, package):
        if name.startswith("quatrack"):
            try:
                found = importlib.util.find_spec(name) is not None
            except ModuleNotFoundError:
                found = False
            if not found:
                missing.append(name)
    assert not missing, f"{path.relative_to(ROOT)} imports modules that do not exist: {missing}"

"""What a wheel, an sdist and the image hold, read from pyproject.toml, MANIFEST.in and the
Dockerfile (nothing is built or installed here).

A trial user installing quatrack other ways met: ``bench serve --replicas`` reading
``deploy/nginx.conf``, which no wheel held; setuptools warning "Package would be ignored" for the
viewer's static files and the zoo's data folders and that the TOML-table ``license`` stops being
supported in 2027; an sdist whose tests read files it did not hold (docs/, deploy/, the
Dockerfile, tests/conftest.py); the version written twice; and the image running from the
source folder, whose quatrack/ shadowed the installed package (``python -m quatrack`` failed).
"""

from __future__ import annotations

import ast
import fnmatch
import re
import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.version import Version

from quatrack.testing import balancer

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
SETUP = PYPROJECT["tool"]["setuptools"]


def package_folder(package: str) -> Path:
    """The checkout folder a package is built from (``package-dir``, the nearest mapped parent)."""
    mapping = SETUP["package-dir"]
    parts = package.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in mapping:
            return ROOT / mapping[".".join(parts[:n])] / Path(*parts[n:])
    raise AssertionError(f"{package}: no package-dir maps it")


def shipped(path: Path) -> bool:
    """Whether a checkout file goes into the wheel: a module of a listed package, or matched by
    its package's package-data patterns."""
    for package in SETUP["packages"]:
        folder = package_folder(package)
        if path.parent == folder and path.suffix == ".py":
            return True
        if folder in path.parents:
            rel = path.relative_to(folder).as_posix()
            if any(fnmatch.fnmatch(rel, g) for g in SETUP.get("package-data", {}).get(package, [])):
                return True
    return False


def test_the_balancer_template_is_in_the_wheel_where_the_balancer_looks():
    """balancer.NGINX_CONF is ROOT/deploy/nginx.conf; ROOT is the checkout, or site-packages/quatrack
    from a wheel: deploy/ must install as quatrack/deploy/ with nginx.conf in it."""
    rel = balancer.NGINX_CONF.relative_to(balancer.ROOT)
    assert rel == Path("deploy", "nginx.conf")
    assert package_folder("quatrack.deploy") == ROOT / "deploy"
    assert "quatrack.deploy" in SETUP["packages"] and shipped(ROOT / rel)


def test_every_data_folder_is_a_listed_package_and_its_files_ship():
    """setuptools warns "Package would be ignored" for a folder with an importable name and files
    in it under a package that is not listed; a listed folder of data ships all its files."""
    listed = set(SETUP["packages"])
    for package in sorted(listed):
        folder = package_folder(package)
        assert folder.is_dir(), package
        for sub in folder.rglob("*"):
            if not sub.is_dir() or "__pycache__" in sub.parts or not any(f.is_file() for f in sub.iterdir()):
                continue
            rel = sub.relative_to(folder).parts
            if not all(p.isidentifier() for p in rel):  # (examples/cookie-box: not importable, no warning)
                continue
            name = ".".join((package, *rel))
            assert name in listed or any(package_folder(p) == sub for p in listed), f"{name} is not in packages"
        if not (folder / "__init__.py").exists():  # (a folder of data: all of it is what it is there for)
            for f in folder.iterdir():
                assert f.is_dir() or shipped(f), f"{f.relative_to(ROOT)} is not in the wheel (package-data of {package})"


def test_the_licence_is_an_spdx_expression_with_its_files():
    project = PYPROJECT["project"]
    assert project["license"] == "Apache-2.0"  # (a string: the TOML table is deprecated)
    for name in project["license-files"]:
        assert (ROOT / name).is_file(), name
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert "Apache License" in text and "Version 2.0, January 2004" in text and "END OF TERMS AND CONDITIONS" in text
    (setuptools,) = [Requirement(r) for r in PYPROJECT["build-system"]["requires"] if Requirement(r).name == "setuptools"]
    assert not setuptools.specifier.contains("76.9"), "license-files and an SPDX license need setuptools>=77"


def test_the_version_is_written_once():
    """pyproject.toml reads it from quatrack/__init__.py (``quatrack --version``'s), which the
    built metadata, and so the models' ``library_versions``, then carry."""
    project = PYPROJECT["project"]
    assert "version" not in project and "version" in project["dynamic"]
    attr = SETUP["dynamic"]["version"]["attr"]
    module, name = attr.rsplit(".", 1)
    source = package_folder(module) / "__init__.py"
    tree = ast.parse(source.read_text(encoding="utf-8"))
    (value,) = [ast.literal_eval(n.value) for n in tree.body
                if isinstance(n, ast.Assign) and any(getattr(t, "id", None) == name for t in n.targets)]
    assert Version(value) >= Version("0.2.0")
    assert value not in (ROOT / "pyproject.toml").read_text(encoding="utf-8")


def _manifest_covers(top: str) -> bool:
    lines = [ln.split() for ln in (ROOT / "MANIFEST.in").read_text(encoding="utf-8").splitlines()
             if ln.strip() and not ln.startswith("#")]
    return any(words[0] in ("graft", "recursive-include") and words[1] == top or words[0] == "include" and top in words[1:]
               for words in lines)


def test_the_sdist_holds_what_the_tests_read():
    """Every top-level file or folder the tests open (``ROOT / "docs"`` ...), and the tests'
    conftest.py, is in the sdist: a package folder is; anything else through MANIFEST.in."""
    tops = {"tests"}
    pattern = re.compile(r"(?:ROOT|root|parents\[1\]|parent\.parent)\s*/\s*\"([^\"/]+)\"")
    for test in (ROOT / "tests").glob("*.py"):
        tops |= {m for m in pattern.findall(test.read_text(encoding="utf-8")) if (ROOT / m).exists()}
    package_tops = {package_folder(p).relative_to(ROOT).parts[0] for p in SETUP["packages"]}
    auto = ("README.md", "pyproject.toml", "MANIFEST.in")  # (setuptools adds these)
    missing = sorted(t for t in tops if t not in package_tops and t not in auto and not _manifest_covers(t))
    assert not missing, f"MANIFEST.in leaves out {missing}"
    assert _manifest_covers(".ci") and _manifest_covers("LICENSE") and _manifest_covers("NOTICE")


def _instructions() -> list[tuple[str, str]]:
    text = re.sub(r"\\\n", " ", (ROOT / "Dockerfile").read_text(encoding="utf-8"))
    return [(ln.split(None, 1)[0].upper(), ln.split(None, 1)[1]) for ln in text.splitlines()
            if ln.strip() and not ln.lstrip().startswith("#")]


def test_the_image_does_not_run_in_its_source_folder():
    """A non-editable install run from the copied source: its quatrack/ folder came first on
    sys.path (``python -m quatrack``), not the installed package."""
    steps = _instructions()
    (source,) = [args.split()[-1] for op, args in steps if op == "COPY" and args.split()[0] == "."]
    installs = [args for op, args in steps if op == "RUN" and "pip install" in args]
    assert installs and not any(re.search(r"\s(-e|--editable)\s", a) for a in installs)
    workdirs = [args.strip() for op, args in steps if op == "WORKDIR"]
    for w in workdirs:
        assert Path(w) != Path(source) and Path(source) not in Path(w).parents, f"WORKDIR {w} is the source {source}"
    # deploy/'s train commands name the example relative to the working folder: it is copied there
    final = Path(workdirs[-1])
    for manifest in (ROOT / "deploy").glob("*.yaml"):
        for spec in re.findall(r"\"train\", \"([^\"]+\.json)\"", manifest.read_text(encoding="utf-8")):
            folder = Path(spec).parent
            copied = re.escape(f"{Path(source) / folder}") + r"/?\s+" + re.escape(f"{final / folder.parent}")
            assert any(re.search(copied, a) for op, a in steps if op == "RUN"), f"{manifest.name}: {spec} not in {final}"

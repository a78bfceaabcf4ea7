"""The distribution: what `pip install thgs` gets.

The wheel and the sdist are built here with hatchling (as pip would, minus the isolation) and read
back: the license, ``py.typed``, the project URLs and extras in the metadata, a long description
(PyPI's page) whose links all lead somewhere, and every third-party module that ``src/thgs``
imports declared where it is needed (imported when a module loads: a core dependency; imported
inside a function: core or an extra). `scripts/check_package.sh` (run by CI) then installs the
wheel into a fresh virtual environment and runs `thgs demo` there.
"""

from __future__ import annotations

import ast
import email
import email.message
import importlib.metadata
import re
import subprocess
import sys
import tarfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from conftest import REPO
from thgs.cli import entrypoint
from thgs.errors import ThgsError

REPOSITORY = "https://github.com/thgs-dev/thgs"
EXTRAS = {"models", "viewer", "gpu", "demo", "bench", "cluster", "dev"}


def _build(kind: str, out: Path) -> Path:
    """Build the ``wheel`` or ``sdist`` into ``out`` through hatchling's PEP 517 hook."""
    for module in ("hatchling", "hatch_fancy_pypi_readme"):
        pytest.importorskip(module, reason="building needs the dev extra (scripts/setup.sh)")
    hook = f"import hatchling.build as b; print(b.build_{kind}({str(out)!r}))"
    result = subprocess.run(
        [sys.executable, "-c", hook], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr
    return out / result.stdout.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Iterator[zipfile.ZipFile]:
    path = _build("wheel", tmp_path_factory.mktemp("wheel"))
    with zipfile.ZipFile(path) as archive:
        yield archive


@pytest.fixture(scope="module")
def metadata(wheel) -> email.message.Message:
    (name,) = [n for n in wheel.namelist() if n.endswith(".dist-info/METADATA")]
    return email.message_from_bytes(wheel.read(name))


def _requirements(metadata: email.message.Message) -> list[Requirement]:
    return [Requirement(line) for line in metadata.get_all("Requires-Dist")]


def test_wheel_holds_the_package_its_types_marker_and_the_license(wheel, metadata):
    names = set(wheel.namelist())
    assert "thgs/__init__.py" in names and "thgs/cli/__init__.py" in names
    assert "thgs/py.typed" in names
    (license_name,) = [n for n in names if n.endswith(".dist-info/licenses/LICENSE")]
    text = wheel.read(license_name).decode()
    assert text == (REPO / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    assert metadata["License-Expression"] == "Apache-2.0"
    assert not any(n.startswith(("tests/", "docs/")) for n in names)
    (entry_points,) = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
    assert "thgs = thgs._main:main" in wheel.read(entry_points).decode()


def test_metadata_urls_extras_and_the_partition_dependency(metadata):
    urls = dict(line.split(", ", 1) for line in metadata.get_all("Project-URL"))
    assert urls["Repository"] == REPOSITORY and urls["Issues"] == f"{REPOSITORY}/issues"
    assert set(metadata.get_all("Provides-Extra")) == EXTRAS
    core = {canonicalize_name(r.name): r for r in _requirements(metadata) if r.marker is None} | {
        canonicalize_name(r.name): r
        for r in _requirements(metadata)
        if r.marker is not None and "extra" not in str(r.marker)
    }
    # the partition is part of every build: its solver is a core dependency
    assert "pycut-pursuit" in core
    # pycut-pursuit's modules work only with the NumPy major they were built against (NumPy 1
    # up to CPython 3.12, NumPy 2 from 3.13): the NumPy requirement follows that line
    numpy = [r for r in _requirements(metadata) if r.name == "numpy"]
    for python, allowed, refused in (("3.11", "1.26.4", "2.0.0"), ("3.13", "2.1.0", "1.26.4")):
        environment = {"python_version": python, "extra": ""}
        (active,) = [r for r in numpy if r.marker is None or r.marker.evaluate(environment)]
        assert active.specifier.contains(allowed) and not active.specifier.contains(refused)
    # pyarrow 26 needs NumPy 2 at runtime (its metadata does not say so): the cluster extra keeps
    # it below 26 where NumPy 1 is required
    pyarrow = [r for r in _requirements(metadata) if r.name == "pyarrow"]
    for python, allowed, refused in (("3.11", "25.0.1", "26.0.0"), ("3.13", None, None)):
        environment = {"python_version": python, "extra": "cluster"}
        active = [r for r in pyarrow if r.marker.evaluate(environment)]
        if allowed is None:
            assert active == []
        else:
            (requirement,) = active
            assert requirement.specifier.contains(allowed)
            assert not requirement.specifier.contains(refused)
    # torch is never pinned by the package (the user picks the build)
    assert core["torch"].specifier.contains("2.13.0") and core["torch"].specifier.contains("9.0")


def test_long_description_links_point_at_repository_files(metadata):
    description = metadata.get_payload()
    assert metadata["Description-Content-Type"] == "text/markdown"
    assert description.startswith("# thgs")
    targets = re.findall(r"\]\(([^)\s]+)\)", description)
    assert targets, "the README has links"
    prefix = f"{REPOSITORY}/blob/main/"
    for target in targets:
        assert target.startswith(("https://", "http://", "#")), f"relative link {target!r}"
        if target.startswith(prefix):
            path = target.removeprefix(prefix).split("#")[0]
            assert (REPO / path).exists(), f"the README links to {path}, which does not exist"


def test_sdist_holds_sources_tests_docs_and_license(tmp_path):
    path = _build("sdist", tmp_path)
    with tarfile.open(path) as archive:
        names = {name.split("/", 1)[1] for name in archive.getnames() if "/" in name}
    for required in (
        "pyproject.toml",
        "README.md",
        "LICENSE",
        "src/thgs/py.typed",
        "src/thgs/__init__.py",
        "tests/conftest.py",
        "scripts/setup.sh",
        "scripts/constraints.txt",
    ):
        assert required in names, required
    assert any(name.startswith("docs/") for name in names)
    assert not any(name.startswith((".ci/", ".hypothesis/", ".venv/")) for name in names)


def _third_party_imports() -> list[tuple[str, int, str, bool]]:
    """``(file, line, top-level module, at load time)`` for every import in ``src/thgs`` of a
    module outside the standard library and thgs. "At load time" means neither inside a function
    nor under ``if TYPE_CHECKING:``."""
    found = []
    for path in sorted((REPO / "src" / "thgs").rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        deferred: set[int] = set()
        for node in ast.walk(tree):
            type_checking = isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) or type_checking:
                deferred.update(id(child) for child in ast.walk(node) if child is not node)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                modules = [node.module]
            else:
                continue
            for module in modules:
                top = module.split(".")[0]
                if top == "thgs" or top in sys.stdlib_module_names or top == "__future__":
                    continue
                relative = str(path.relative_to(REPO))
                found.append((relative, node.lineno, top, id(node) not in deferred))
    return found


@pytest.mark.slow
def test_every_imported_module_is_declared(metadata):
    """A module-level import needs a core dependency; one inside a function may be an extra.
    (The dev environment has every extra, so every module resolves to its distribution.)"""
    core, anywhere = set(), set()
    for requirement in _requirements(metadata):
        name = canonicalize_name(requirement.name)
        anywhere.add(name)
        if requirement.marker is None or "extra" not in str(requirement.marker):
            core.add(name)
    distributions = importlib.metadata.packages_distributions()
    imports = _third_party_imports()
    assert {"torch", "numpy", "viser", "transformers"} <= {module for _, _, module, _ in imports}
    problems = []
    for file, line, module, at_load in imports:
        names = {canonicalize_name(d) for d in distributions.get(module, [])}
        if not names:
            problems.append(f"{file}:{line}: {module} is not installed by any distribution")
        elif at_load and not names & core:
            problems.append(f"{file}:{line}: {module} ({', '.join(names)}) is no core dependency")
        elif not names & anywhere:
            problems.append(f"{file}:{line}: {module} ({', '.join(names)}) is in no extra")
    assert not problems, "\n".join(problems)


def test_the_import_scan_sees_module_level_and_function_imports(tmp_path, monkeypatch):
    """The scan tells an import that runs when a module loads from one inside a function."""
    package = tmp_path / "src" / "thgs"
    package.mkdir(parents=True)
    (package / "mod.py").write_text(
        "import json\nimport numpy as np\nfrom thgs import x\nfrom typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    import gsplat\n\n"
        "def f():\n    import viser\n    from transformers import AutoConfig\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert sorted(_third_party_imports()) == [
        ("src/thgs/mod.py", 2, "numpy", True),
        ("src/thgs/mod.py", 6, "gsplat", False),
        ("src/thgs/mod.py", 9, "viser", False),
        ("src/thgs/mod.py", 10, "transformers", False),
    ]


def _start_viewer():
    from thgs.viewer.app import start_viewer

    start_viewer("missing.thgs", port=0)


def _minilm():
    from thgs.text import MiniLMEncoder

    MiniLMEncoder()


def _clip_text():
    from thgs.text import CLIPTextEncoder

    CLIPTextEncoder()


def _sam():
    from thgs.guidance.preprocess.sam import PointSegmenter

    PointSegmenter()


def _clip_image():
    from thgs.guidance.preprocess.clip_features import CLIPImageEncoder

    CLIPImageEncoder()


def _connect_ray():
    from thgs.cluster import connect_ray

    connect_ray("127.0.0.1:1")


def _preprocess_with_ray():
    from thgs.guidance.preprocess import preprocess_with_ray

    preprocess_with_ray([], sam="sam", clip="clip")


def _matplotlib():
    from thgs.bench import require_matplotlib

    require_matplotlib()


def _gsplat():
    from thgs.render.backends import get_backend

    get_backend("gsplat")


@pytest.mark.parametrize(
    ("module", "extra", "use"),
    [
        ("viser", "viewer", _start_viewer),
        ("sentence_transformers", "demo", _minilm),
        ("transformers", "models", _clip_text),
        ("transformers", "models", _sam),
        ("transformers", "models", _clip_image),
        ("matplotlib", "bench", _matplotlib),
        ("gsplat", "gpu", _gsplat),
        ("ray", "cluster", _connect_ray),
        ("ray", "cluster", _preprocess_with_ray),
    ],
    ids=[
        "viewer",
        "minilm",
        "clip-text",
        "sam",
        "clip-image",
        "bench-plot",
        "gsplat",
        "ray-connect",
        "ray-preprocess",
    ],
)
def test_a_part_without_its_extra_names_the_extra(module, extra, use, monkeypatch):
    """With the extra's module missing (None in sys.modules makes its import fail), the part
    stops with a thgs error that says which extra to install."""
    for name in [m for m in sys.modules if m == module or m.startswith(f"{module}.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(ThgsError, match=re.escape(f"pip install 'thgs[{extra}]'")):
        use()


def test_thgs_view_without_the_viewer_extra_is_one_error_line(monkeypatch, capsys):
    for name in [m for m in sys.modules if m == "viser" or m.startswith("viser.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "viser", None)
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(["view", "missing.thgs"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2
    assert err.startswith("error: ") and "pip install 'thgs[viewer]'" in err
    assert "Traceback" not in err

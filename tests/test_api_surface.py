"""The public API: every public module's ``__all__`` is pinned in ``public_api.json`` (a name
that disappears or appears fails here until the file is updated on purpose), every listed name
exists, the imports shown in the README and docs work, and no private name crosses modules.

Regenerate the pinned file after a deliberate change with
``.venv/bin/python tests/test_api_surface.py``.
"""

from __future__ import annotations

import ast
import importlib
import json
import pkgutil
import re
import sys
from pathlib import Path

import pytest

import thgs

REPO = Path(__file__).resolve().parents[1]
PINNED = Path(__file__).with_name("public_api.json")
SOURCE = REPO / "src" / "thgs"


def public_modules() -> list[str]:
    """``thgs`` and every module or package under it without an underscore-prefixed part
    (the CLI is its own surface: the commands, tested in test_cli.py)."""
    names = ["thgs"]
    for info in pkgutil.walk_packages(thgs.__path__, "thgs."):
        parts = info.name.split(".")[1:]
        if not any(part.startswith("_") for part in parts) and parts[0] != "cli":
            names.append(info.name)
    return sorted(names)


def current_surface() -> dict[str, list[str]]:
    return {name: sorted(importlib.import_module(name).__all__) for name in public_modules()}


def test_every_public_module_declares_all():
    missing = [
        name for name in public_modules() if not hasattr(importlib.import_module(name), "__all__")
    ]
    assert missing == []


def test_surface_is_the_pinned_one():
    pinned = json.loads(PINNED.read_text(encoding="utf-8"))
    current = current_surface()
    removed = {m: sorted(set(names) - set(current.get(m, []))) for m, names in pinned.items()}
    added = {m: sorted(set(names) - set(pinned.get(m, []))) for m, names in current.items()}
    assert {m: n for m, n in removed.items() if n} == {}, "public names removed"
    assert {m: n for m, n in added.items() if n} == {}, "public names added: update the pin"
    assert sorted(pinned) == sorted(current)


@pytest.mark.parametrize("module", public_modules())
def test_every_exported_name_exists(module):
    imported = importlib.import_module(module)
    assert [name for name in imported.__all__ if not hasattr(imported, name)] == []


def documented_imports() -> list[tuple[str, str, list[str]]]:
    """(file, module, names) of every ``from thgs… import …`` in README.md and docs/*.md."""
    found = []
    pattern = re.compile(r"^\s*from (thgs[\w.]*) import \(?([\w ,]+)\)?\s*$", re.MULTILINE)
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for module, names in pattern.findall(path.read_text(encoding="utf-8")):
            listed = [name.strip() for name in names.split(",") if name.strip()]
            found.append((path.name, module, listed))
    return found


def test_documented_imports_work():
    found = documented_imports()
    assert len(found) >= 10  # the docs do show imports; the pattern must keep finding them
    broken = []
    for file, module, names in found:
        try:
            imported = importlib.import_module(module)
        except ImportError as error:
            broken.append(f"{file}: {module} ({error})")
            continue
        broken += [f"{file}: {module}.{name}" for name in names if not hasattr(imported, name)]
    assert broken == []


def _module_name(path: Path, root: Path) -> str:
    return ".".join(path.relative_to(root.parent).with_suffix("").parts).removesuffix(".__init__")


def _package_of(module: str, is_package: bool) -> str:
    return module if is_package else module.rpartition(".")[0]


def private_crossings(root: Path = SOURCE) -> list[str]:
    """Imports that break the rule of docs/design.md: a private name (``_x``) is used only in
    its own module; a subpackage's private module (``thgs.scene._json``) only inside that
    subpackage; top-level private modules (``thgs._atomic``) anywhere in thgs."""
    problems = []
    for path in sorted(root.rglob("*.py")):
        module = _module_name(path, root)
        package = _package_of(module, path.name == "__init__.py")
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not (isinstance(node, ast.ImportFrom) and node.module and node.level == 0):
                continue
            if not node.module.startswith("thgs"):
                continue
            where = f"{path.relative_to(root.parent)}:{node.lineno}"
            parts = node.module.split(".")
            for i, part in enumerate(parts[1:], start=1):
                owner = ".".join(parts[:i])
                if part.startswith("_") and owner != "thgs" and not package.startswith(owner):
                    problems.append(f"{where}: private module {node.module} outside {owner}")
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    problems.append(f"{where}: private name {alias.name} from {node.module}")
    return problems


def private_attribute_uses(root: Path = SOURCE) -> list[str]:
    """``x._name`` where x is not self/cls: a private attribute of another object or module."""
    problems = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (
                isinstance(node, ast.Attribute)
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
                and isinstance(node.value, ast.Attribute)
                and isinstance(node.value.value, ast.Name)
                and node.value.value.id == "self"
            ):
                problems.append(f"{path.relative_to(root.parent)}:{node.lineno}: .{node.attr}")
    return problems


@pytest.mark.slow
def test_no_private_name_crosses_modules():
    assert private_crossings() == []
    assert private_attribute_uses() == []


def test_the_rule_catches_what_it_should(tmp_path):
    package = tmp_path / "thgs"
    (package / "scene").mkdir(parents=True)
    (package / "eval").mkdir()
    for folder in (package, package / "scene", package / "eval"):
        (folder / "__init__.py").write_text("")
    (package / "scene" / "loader.py").write_text("from thgs.scene._json import load\n")
    (package / "eval" / "good.py").write_text("from thgs._atomic import atomic_output\n")
    (package / "eval" / "bad.py").write_text(
        "from thgs.scene._json import load\nfrom thgs.graph.knn import _query\n"
    )
    (package / "eval" / "reach.py").write_text("def f(self):\n    return self.field._level\n")
    problems = private_crossings(package)
    assert len(problems) == 2
    assert problems[0].startswith("thgs/eval/bad.py:1: private module thgs.scene._json")
    assert problems[1].startswith("thgs/eval/bad.py:2: private name _query")
    assert private_attribute_uses(package) == ["thgs/eval/reach.py:2: ._level"]


def import_graph(root: Path = SOURCE) -> dict[str, set[str]]:
    """Module → the modules of the package it imports, anywhere in its body (at the top, in a
    function, under ``TYPE_CHECKING``): ``from a.b import c`` imports ``a.b``, and ``a.b.c``
    too where that is a module; relative imports resolved."""
    paths = {_module_name(path, root): path for path in sorted(root.rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for module, path in paths.items():
        package = _package_of(module, path.name == "__init__.py")
        imported: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                imported.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    parts = parts[: len(parts) - node.level + 1]
                    base = ".".join([*parts, base] if base else parts)
                imported.add(base)
                imported.update(f"{base}.{alias.name}" for alias in node.names)
        graph[module] = {name for name in imported if name in paths and name != module}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for other in sorted(graph[module]):
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            group = []
            while not group or group[-1] != module:
                group.append(stack.pop())
            if len(group) > 1:
                cycles.append(sorted(group))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return cycles


def test_no_import_cycle():
    assert import_cycles(import_graph()) == []


def test_the_cycle_check_finds_a_lazy_cycle(tmp_path):
    package = tmp_path / "thgs"
    (package / "suite").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "suite" / "__init__.py").write_text("from .run import go\n")
    (package / "suite" / "run.py").write_text("def go():\n    from thgs.suite import report\n")
    (package / "suite" / "report.py").write_text("from thgs.suite.run import go\n")
    (package / "alone.py").write_text("import thgs.suite.report\n")
    graph = import_graph(package)
    assert graph["thgs.suite.run"] == {"thgs.suite", "thgs.suite.report"}
    assert graph["thgs.suite"] == {"thgs.suite.run"}
    assert import_cycles(graph) == [["thgs.suite", "thgs.suite.report", "thgs.suite.run"]]


if __name__ == "__main__":
    PINNED.write_text(json.dumps(current_surface(), indent=1) + "\n", encoding="utf-8")
    print(f"wrote {PINNED}", file=sys.stderr)

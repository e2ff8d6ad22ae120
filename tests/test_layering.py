"""gyronet's folders import only the layers below them, and no two modules import each other in a circle."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "gyronet"
BASE = {"errors", "atomic", "_moved"}
# each folder and the folders it may import (besides itself and BASE); gyronet/__init__.py says the same
MAY_IMPORT = {
    "recordings": set(),
    "allan": {"recordings"},
    "sim": {"recordings"},
    "figures": {"recordings"},
    "model": {"recordings", "allan"},
    "bundle": {"recordings", "allan", "model"},
    "training": {"recordings", "allan", "figures", "model", "bundle"},
    "deploy": {"recordings", "allan", "figures", "model", "bundle"},
    "analysis": {"recordings", "allan", "sim", "figures", "model", "bundle", "training", "deploy"},
}


def module_name(path: Path) -> str:
    """``gyronet/bundle/io.py`` -> ``gyronet.bundle.io``; a folder's ``__init__`` is the folder."""
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def runtime_nodes(tree: ast.AST):
    """Every node that runs, at the top or inside a function; not ``if TYPE_CHECKING:`` blocks (type hints
    only) nor a module's ``__getattr__`` (an old name kept importable from where it used to live)."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", "")) == "TYPE_CHECKING":
            yield from (n for child in node.orelse for n in ast.walk(child))
        elif isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
            continue
        else:
            yield from ast.walk(node)


def imports_of(path: Path, modules: set[str]) -> set[str]:
    """Every gyronet module this file imports when it runs, at its top or inside a function."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in runtime_nodes(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                stem = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(stem + ([node.module] if node.module else []))
            found.update(f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names)
    return {m for m in found if m in modules and m != name}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    files = sorted(PACKAGE.rglob("*.py"))
    modules = {module_name(p) for p in files}
    return {module_name(p): imports_of(p, modules) for p in files}


def folder(module: str) -> str:
    """The top folder (layer) a module belongs to: ``gyronet.bundle.io`` -> ``bundle``."""
    return module.split(".")[1] if "." in module else ""


def test_the_top_of_gyronet_holds_only_the_layers_and_the_shared_base():
    tops = {p.stem for p in PACKAGE.glob("*.py")} | {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    assert tops - {"__init__"} == BASE | set(MAY_IMPORT)


def test_every_folder_imports_only_the_layers_below_it(graph):
    upward = [f"{m} imports {d}" for m, deps in graph.items() for d in deps
              if folder(m) in MAY_IMPORT and folder(d) not in MAY_IMPORT[folder(m)] | BASE | {folder(m), ""}]
    assert not upward, "\n".join(upward)


def test_the_base_modules_import_nothing_above_them(graph):
    for m in BASE:
        assert {folder(d) for d in graph[f"gyronet.{m}"]} <= BASE, m


def test_no_modules_import_each_other_in_a_circle(graph):
    done: set[str] = set()

    def visit(m: str, stack: list[str]) -> None:
        if m in stack:
            raise AssertionError("import circle: " + " -> ".join(stack[stack.index(m):] + [m]))
        if m in done:
            return
        for d in sorted(graph[m]):
            # a module importing its own folder's __init__ (a package's re-exports) is no circle of code
            if not m.startswith(d + "."):
                visit(d, stack + [m])
        done.add(m)

    for m in sorted(graph):
        visit(m, [])


def test_every_folder_opens_with_a_docstring_saying_what_it_holds():
    for init in PACKAGE.rglob("__init__.py"):
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and len(doc) > 40, f"{init.relative_to(PACKAGE.parent)} has no docstring"


def test_top_folders_say_what_they_may_import():
    for name in MAY_IMPORT:
        doc = ast.get_docstring(ast.parse((PACKAGE / name / "__init__.py").read_text())) or ""
        assert "may import" in doc.lower(), name


def test_modules_stay_at_most_300_lines():
    long = [f"{p.relative_to(PACKAGE.parent)}: {n}" for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 300]
    assert not long, "\n".join(long)


def test_old_flat_import_paths_still_work_and_are_the_same_modules():
    import importlib

    import hydra.utils

    import gyronet.training.train as train

    assert importlib.import_module("gyronet.train") is train  # the names below are the old, flat ones
    old = {name: importlib.import_module("gyronet." + name) for name in ("compensator", "stream.lpbus", "px4")}
    from gyronet.bundle.compensator import Compensator
    from gyronet.deploy.stream.lpbus import LpBusParser
    from gyronet.model.px4 import Px4Cubic
    from gyronet.model.rbf import RBFNet

    assert old["compensator"].Compensator is Compensator and old["stream.lpbus"].LpBusParser is LpBusParser
    assert old["px4"].Px4Cubic is Px4Cubic
    # older bundles' and configs' Hydra targets
    assert hydra.utils.get_class("gyronet.model.RBFNet") is RBFNet
    assert hydra.utils.get_method("gyronet.runs.training_data") is importlib.import_module("gyronet.training.runs").training_data

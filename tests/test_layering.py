"""Dependencies point one way: ``protocol`` <- ``controller``, ``plant_sim`` <- ``sim``;
``protocol`` <- ``controller`` <- ``bridge``; ``recorder`` above them, ``gui`` above the
recorder, ``soak`` above all.

``controller`` and ``plant_sim`` never import each other, and ``protocol`` imports neither;
and no module imports itself through others (no cycle in the graph of the project's modules).
Read from every module's own import statements (``ast``), lazy imports included.
"""

from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx
import pytest
from support import ROOT

PACKAGES = ("protocol", "controller", "plant_sim", "sim", "bridge", "recorder", "gui", "soak")
ALLOWED = {
    "protocol": {"protocol"},
    "controller": {"controller", "protocol"},
    "plant_sim": {"plant_sim", "protocol"},
    "sim": {"sim", "controller", "plant_sim", "protocol"},
    "bridge": {"bridge", "controller", "protocol"},
    "recorder": {"recorder", "bridge", "sim", "controller", "plant_sim", "protocol"},
    "gui": {"gui", "recorder", "bridge", "sim", "controller", "plant_sim", "protocol"},
    "soak": set(PACKAGES),
}


def project_imports(path: Path) -> set[str]:
    """The top-level project packages a module imports, wherever the import statement is."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        found |= {name.split(".")[0] for name in names} & set(PACKAGES)
    return found


@pytest.mark.parametrize("package", PACKAGES)
def test_a_package_imports_only_what_lies_below_it(package: str) -> None:
    modules = sorted((ROOT / package).rglob("*.py"))
    assert modules, f"no modules found in {package}"
    wrong = {
        str(module.relative_to(ROOT)): sorted(imported - ALLOWED[package])
        for module in modules
        if (imported := project_imports(module)) - ALLOWED[package]
    }
    assert not wrong, f"{package} must import only {sorted(ALLOWED[package])}: {wrong}"


def test_the_check_sees_a_forbidden_import(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from plant_sim.model import PlantModel\n    import sim.cli\n")
    assert project_imports(module) == {"plant_sim", "sim"}


def module_names(root: Path) -> dict[str, Path]:
    """Every module of the project's packages under ``root``, by dotted name (a package is
    its ``__init__.py``)."""
    found: dict[str, Path] = {}
    for package in PACKAGES:
        for path in (root / package).rglob("*.py"):
            parts = path.relative_to(root).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def imported_modules(path: Path, modules: set[str]) -> set[str]:
    """The project modules of ``modules`` one module imports, wherever the import statement
    is: ``import a.b`` is ``a.b``; ``from a import b`` is ``a.b`` when that is a module,
    else ``a``."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for alias in node.names:
                submodule = f"{node.module}.{alias.name}"
                found.add(submodule if submodule in modules else node.module)
    return found & modules


def import_cycles(root: Path) -> list[list[str]]:
    """The cycles of the import graph of the modules under ``root``, each as the modules on
    it (empty: the graph has none)."""
    modules = module_names(root)
    graph = nx.DiGraph()
    graph.add_nodes_from(modules)
    for name, path in modules.items():
        graph.add_edges_from((name, imported) for imported in imported_modules(path, set(modules)))
    return sorted(sorted(cycle) for cycle in nx.simple_cycles(graph))


def test_no_module_imports_itself_through_others() -> None:
    assert len(module_names(ROOT)) > len(PACKAGES)
    assert import_cycles(ROOT) == []


def test_the_check_finds_a_planted_cycle(tmp_path: Path) -> None:
    package = tmp_path / "controller"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "node.py").write_text("def make():\n    from controller import service\n")
    (package / "service.py").write_text("from controller.node import make\n")
    (package / "cli.py").write_text("import controller.service\n")
    assert import_cycles(tmp_path) == [["controller.node", "controller.service"]]

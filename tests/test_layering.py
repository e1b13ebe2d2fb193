"""Dependencies point one way: ``protocol`` <- ``controller``, ``plant_sim`` <- ``sim``;
``protocol`` <- ``controller`` <- ``bridge``.

``controller`` and ``plant_sim`` never import each other, and ``protocol`` imports neither:
read from every module's own import statements (``ast``), lazy imports included.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from support import ROOT

PACKAGES = ("protocol", "controller", "plant_sim", "sim", "bridge", "recorder")
ALLOWED = {
    "protocol": {"protocol"},
    "controller": {"controller", "protocol"},
    "plant_sim": {"plant_sim", "protocol"},
    "sim": {"sim", "controller", "plant_sim", "protocol"},
    "bridge": {"bridge", "controller", "protocol"},
    "recorder": {"recorder", "bridge", "sim", "controller", "plant_sim", "protocol"},
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

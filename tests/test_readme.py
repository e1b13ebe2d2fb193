"""README.md stays the map a newcomer reads: its layout table names every directory of the
tree (and no directory that is gone), its command table every command the package installs,
its links (and those of ``docs/``) lead to files that exist, and it stays short and free of
what changes with every commit."""

from __future__ import annotations

import os
import re
import tomllib
from pathlib import Path

import pytest
from support import ROOT

README = ROOT / "README.md"
MAX_LINES = 200
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
"""A commit hash as the docs would quote one: 7 to 40 hex digits, letters and digits mixed."""


def ignored(name: str) -> bool:
    """Directories that are no part of the tree a reader needs: hidden ones (``.git``,
    ``.venv``, ``.ci``, tool caches), build products and run outputs."""
    return (
        name.startswith(".")
        or name in {"__pycache__", "out", "build"}
        or name.endswith(".egg-info")
    )


def tree_directories(root: Path) -> set[str]:
    """Every directory under ``root`` that holds a file at any depth, relative to ``root``."""
    found: set[str] = set()
    for folder, subfolders, files in os.walk(root):
        subfolders[:] = [name for name in subfolders if not ignored(name)]
        relative = Path(folder).relative_to(root)
        if files and relative != Path("."):
            found.update(path.as_posix() for path in (relative, *relative.parents[:-1]))
    return found


def section(text: str, heading: str) -> str:
    """The body of the ``## heading`` section of a Markdown text."""
    parts = re.split(rf"^## {re.escape(heading)}\s*$", text, maxsplit=1, flags=re.MULTILINE)
    assert len(parts) == 2, f"no section '## {heading}'"
    return re.split(r"^## ", parts[1], maxsplit=1, flags=re.MULTILINE)[0]


def first_cells(table_section: str) -> list[str]:
    """The first cell of every body row of the Markdown tables in a section."""
    rows = [line for line in table_section.splitlines() if line.startswith("|")]
    cells = [row.split("|")[1].strip() for row in rows]
    return [cell for cell in cells if cell and not set(cell) <= set("-: ")][1:]


def layout_paths(readme: str) -> set[str]:
    """The directories the layout table names: each `path/` in a row's first cell."""
    paths: set[str] = set()
    for cell in first_cells(section(readme, "Layout")):
        paths.update(name.rstrip("/") for name in re.findall(r"`([^`]+/)`", cell))
    return paths


def unnamed_and_stale(root: Path, readme: str) -> tuple[set[str], set[str]]:
    """Directories of the tree the layout table misses, and paths it names that are not
    directories of the tree."""
    tree, named = tree_directories(root), layout_paths(readme)
    return tree - named, named - tree


def test_the_layout_table_names_every_directory_of_the_tree() -> None:
    unnamed, stale = unnamed_and_stale(ROOT, README.read_text())
    assert not unnamed, f"add these to README.md's layout table: {sorted(unnamed)}"
    assert not stale, f"README.md's layout table names what the tree no longer has: {stale}"


def test_the_layout_check_finds_a_new_directory_and_a_stale_row(tmp_path: Path) -> None:
    for file in (
        "pkg/a.py", "pkg/sub/b.py", "pkg/__pycache__/a.cpython-311.pyc", "data/deep/x.json",
        ".venv/lib/site.py", "out/run/run.mcap", "pkg.egg-info/PKG-INFO",
    ):  # fmt: skip
        (tmp_path / file).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / file).write_text("")
    (tmp_path / "empty").mkdir()
    readme = "## Layout\n\n| path | what |\n|---|---|\n| `pkg/` | code |\n| `data/`, `gone/` | |\n"
    unnamed, stale = unnamed_and_stale(tmp_path, readme)
    assert unnamed == {"pkg/sub", "data/deep"}
    assert stale == {"gone"}
    complete = readme + "| `pkg/sub/` | more code |\n| `data/deep/` | data |\n"
    assert unnamed_and_stale(tmp_path, complete.replace(", `gone/`", "")) == (set(), set())


def test_the_command_table_names_every_installed_command() -> None:
    scripts = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"])
    cells = first_cells(section(README.read_text(), "Commands"))
    named = {cell.strip("`").split()[0] for cell in cells if not cell.startswith("`python ")}
    assert named == scripts, f"table only: {named - scripts}; not in the table: {scripts - named}"
    assert "`python benchmarks/bench_*.py`" in cells


@pytest.mark.parametrize(
    "document",
    [README, *sorted((ROOT / "docs").glob("*.md"))],
    ids=lambda path: path.relative_to(ROOT).as_posix(),
)
def test_every_relative_link_leads_to_a_file(document: Path) -> None:
    targets = [target for target in LINK.findall(document.read_text()) if "://" not in target]
    missing = [target for target in targets if not (document.parent / target).exists()]
    assert not missing, f"{document.name} links to what does not exist: {missing}"


def test_the_readme_links_the_docs_it_sends_readers_to() -> None:
    linked = {target for target in LINK.findall(README.read_text()) if target.startswith("docs/")}
    documents = {f"docs/{path.name}" for path in (ROOT / "docs").glob("*.md")}
    assert documents <= linked, f"not linked from README.md: {documents - linked}"


def test_the_readme_is_short_and_holds_nothing_that_changes_with_every_commit() -> None:
    text = README.read_text()
    assert len(text.splitlines()) < MAX_LINES
    assert not COMMIT.findall(text), COMMIT.findall(text)

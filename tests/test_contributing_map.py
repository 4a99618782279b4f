"""CONTRIBUTING.md's map of the package matches the tree: every module named, none missing."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "byoc_cli"
ROW = re.compile(r"^\|\s*`([^`]+\.py)`\s*\|")
PATH = re.compile(r"`([A-Za-z0-9_/]+\.py)`")


def _map_section() -> list[str]:
    lines = (ROOT / "CONTRIBUTING.md").read_text(encoding="utf-8").splitlines()
    start = lines.index("## Map of the package")
    end = next((k for k in range(start + 1, len(lines)) if lines[k].startswith("## ")), len(lines))
    return lines[start + 1 : end]


def _modules() -> set[str]:
    return {p.relative_to(SRC).as_posix() for p in SRC.rglob("*.py") if p.name != "__init__.py"}


def _rows() -> list[str]:
    return [m.group(1) for line in _map_section() if (m := ROW.match(line))]


def test_every_module_has_a_row_in_the_map():
    missing = sorted(_modules() - set(_rows()))
    assert not missing, f"modules missing from CONTRIBUTING.md's map: {missing}"


def test_every_row_of_the_map_is_a_module_once():
    rows = _rows()
    assert rows, "CONTRIBUTING.md's map has no module rows"
    stale = sorted(set(rows) - _modules())
    assert not stale, f"CONTRIBUTING.md's map names modules that do not exist: {stale}"
    twice = sorted({r for r in rows if rows.count(r) > 1})
    assert not twice, f"CONTRIBUTING.md's map lists modules twice: {twice}"


def test_every_path_the_map_mentions_exists():
    # prose paths are relative to src/byoc_cli, or to the repository for tests/ and benchmarks/
    named = {m.group(1) for line in _map_section() for m in PATH.finditer(line)}
    absent = sorted(
        p
        for p in named
        if not ((ROOT / p) if p.startswith(("tests/", "benchmarks/")) else (SRC / p)).is_file()
    )
    assert not absent, f"CONTRIBUTING.md's map names files that do not exist: {absent}"

"""The layers of CONTRIBUTING.md, checked on the import statements of every module."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "byoc_cli"

# package -> packages of ours it must never import (directly or lazily)
FORBIDDEN = {
    "geometry": {"models", "matching", "fitting", "pipeline", "training", "evaluation", "cli"},
    "models": {"matching", "fitting", "pipeline", "training", "evaluation", "cli"},
    "matching": {"models", "fitting", "pipeline", "training", "evaluation", "cli"},
    "fitting": {"models", "matching", "pipeline", "training", "evaluation", "cli"},
    "io": {
        "geometry",
        "models",
        "matching",
        "fitting",
        "pipeline",
        "training",
        "evaluation",
        "cli",
    },
    "pipeline": {"training", "evaluation", "cli"},
    "training": {"evaluation", "cli"},
    "evaluation": {"training", "cli"},
}
NO_UI = {"click", "rich"}
CORE = ("geometry", "models", "matching", "fitting", "io", "pipeline", "training", "evaluation")


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


@pytest.mark.parametrize("package", CORE)
def test_core_packages_respect_the_layers(package):
    offences = []
    for path in sorted((SRC / package).rglob("*.py")):
        for name in _imports(path):
            parts = name.split(".")
            if parts[0] in NO_UI or (parts[0] == "open3d"):
                offences.append(f"{path.name}: {name}")
            if parts[0] == "byoc_cli" and len(parts) > 1 and parts[1] in FORBIDDEN[package]:
                offences.append(f"{path.name}: {name}")
    assert not offences, f"{package} imports across its layer: {offences}"

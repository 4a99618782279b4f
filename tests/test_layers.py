"""The layers of CONTRIBUTING.md, checked on the import statements of every module: between
packages, inside the packages split into one module per idea, and no import cycle."""

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
                offences.append(f"{_module_name(path)}: {name}")
            if parts[0] == "byoc_cli" and len(parts) > 1 and parts[1] in FORBIDDEN[package]:
                offences.append(f"{_module_name(path)}: {name}")
    assert not offences, f"{package} imports across its layer: {offences}"


# ------------------------------------------------------------------ inside the split packages

# package -> {module: rank}: a module imports only modules of its package with a LOWER rank
# (same rank: not each other), so e.g. a layout module never reaches the registry or
# discovery, and the parts of a split never import the module that assembles them.
INTERNAL_RANKS = {
    "byoc_cli.io.rgbd": {
        "frames": 0,
        "files": 0,
        "pairs": 0,
        "preprocess": 0,
        "backproject": 0,
        "sequence": 1,
        "layout": 1,
        "tum": 2,
        "threedmatch": 2,
        "scannet": 2,
        "redwood": 2,
        "registry": 3,
        "discovery": 4,
        "__init__": 5,
    },
    "byoc_cli.models.sparse": {
        "maps": 0,
        "ops": 1,
        "tensor": 1,
        "layers": 2,
        "pointwise": 2,
        "__init__": 3,
    },
    # one training loop: its parts below it (the task protocol a variant meets, then the run
    # state that checkpoints a task), the loop and the variants that supply their data and
    # step (paper, self_posed) on one rank (they never import each other), and the trainer
    # that picks a variant on top
    "byoc_cli.training": {
        "checkpoint": 0,
        "config": 0,
        "data": 0,
        "distributed": 0,
        "guard": 0,
        "losses": 0,
        "metric_loss": 0,
        "plot": 0,
        "pseudo_poses": 0,
        "self_posed_data": 0,
        "loaders": 1,
        "model": 1,
        "validate": 1,
        "run_folder": 2,
        "self_posed_eval": 3,
        "task": 3,
        "run_state": 4,
        "loop": 5,
        "paper": 5,
        "self_posed": 5,
        "trainer": 6,
    },
    # the pieces of eval-fmr below the module that assembles them
    "byoc_cli.evaluation": {"benchmark": 0, "fmr_protocol": 0, "fmr_summary": 1, "fmr": 2},
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


MODULES = {_module_name(p): p for p in SRC.rglob("*.py")}


def _absolute(path: Path, node: ast.ImportFrom) -> str | None:
    """The module a ``from ... import`` names, relative ones (``from . import x``) resolved."""
    if node.level == 0:
        return node.module
    package = _module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def _targets(path: Path, top_level_only: bool = False) -> set[str]:
    """Modules of ours that ``path`` imports (``from pkg import sub`` counts as ``pkg.sub``;
    relative imports resolved)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    found = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name in MODULES)
        elif isinstance(node, ast.ImportFrom):
            module = _absolute(path, node)
            if module not in MODULES:
                continue
            subs = {f"{module}.{a.name}" for a in node.names} & MODULES.keys()
            found.update(subs or {module})
            if len(subs) < len(node.names):
                found.add(module)
    return found


@pytest.mark.parametrize("package", sorted(INTERNAL_RANKS))
def test_split_packages_import_downwards(package):
    ranks = INTERNAL_RANKS[package]
    offences = []
    for module, rank in ranks.items():
        name = package if module == "__init__" else f"{package}.{module}"
        assert name in MODULES, f"{name} is ranked but does not exist"
        for target in _targets(MODULES[name]):
            if target == package or not target.startswith(package + "."):
                continue
            other = target[len(package) + 1 :].split(".")[0]
            if other in ranks and ranks[other] >= rank:
                offences.append(f"{name} -> {target}")
    assert not offences, f"imports against the order inside {package}: {offences}"


def test_split_packages_rank_every_module():
    for package in ("byoc_cli.io.rgbd", "byoc_cli.models.sparse", "byoc_cli.training"):
        ranked = {f"{package}.{m}" for m in INTERNAL_RANKS[package] if m != "__init__"}
        present = {m for m in MODULES if m.startswith(package + ".")}
        assert present == ranked, f"{package}: rank the new module(s) {present - ranked}"


def test_no_import_cycle_at_module_level():
    graph = {name: _targets(path, top_level_only=True) - {name} for name, path in MODULES.items()}
    state: dict[str, int] = {}  # 1 visiting, 2 done
    stack: list[str] = []

    def visit(name: str) -> None:
        state[name] = 1
        stack.append(name)
        for target in sorted(graph[name]):
            if state.get(target) == 1:
                cycle = [*stack[stack.index(target) :], target]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if target not in state:
                visit(target)
        stack.pop()
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name)


# ------------------------------------------------------------------ command modules


def _command_modules() -> set[str]:
    tree = ast.parse((SRC / "cli" / "main.py").read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "_COMMANDS" for t in node.targets
        ):
            # CommandEntry("module", "attr", "short help")
            found = {v.args[0].value for v in node.value.values}
    assert found, "cli/main.py has no _COMMANDS"
    return found


def test_no_command_module_imports_another():
    commands = _command_modules()
    found = {
        (name, target)
        for name in sorted(commands)
        for target in _targets(MODULES[name])
        if target in commands and target != name
    }
    assert not found, (
        f"a command module imports another (share through a cli module that is not a "
        f"command, e.g. cli/pairwise.py): {sorted(found)}"
    )


def _parameters(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Parameters a caller passes (``self`` and ``cls`` not counted; ``*args`` and
    ``**kwargs`` count one each)."""
    a = node.args
    names = [p.arg for p in (*a.posonlyargs, *a.args)]
    if names and names[0] in ("self", "cls"):
        names = names[1:]
    return len(names) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)


def test_no_function_takes_more_than_8_parameters():
    found = set()
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and _parameters(node) > 8:
                found.add(f"{name}.{node.name}")
    assert not found, (
        f"functions with more than 8 parameters (group them in a dataclass): {sorted(found)}"
    )


def test_nothing_below_the_api_imports_it():
    # the API is a facade over the pipeline's engine: the commands and the pipeline never
    # reach back up into it (only the package's lazy re-export names it)
    offences = sorted(
        name
        for name, path in MODULES.items()
        if name not in ("byoc_cli", "byoc_cli.api") and "byoc_cli.api" in _targets(path)
    )
    assert not offences, f"modules that import byoc_cli.api: {offences}"

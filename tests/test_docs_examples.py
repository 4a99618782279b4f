"""Every shell and Python example of README.md and docs/**/*.md runs, as a reader would run it.

The examples are found in the Markdown, not listed here: every fenced block whose language is
``bash``, ``sh``, ``shell``, ``console`` (the lines after ``$ ``) or ``python``. The examples of
one file run in the order they appear, in one folder that stands for the repository's root (its
files linked in, ``../shared/data`` beside it, every output inside a temporary folder), so an
example may use what an earlier one wrote. An HTML comment on the line before the fence marks
an example:

* ``<!-- slow -->``: runs only with ``pytest --slow`` (more than a few seconds);
* ``<!-- skip: reason -->``: never runs in a test (installs packages, trains for hours,
  placeholder folders); the reason is shown.

Selecting one example (``-k``) also runs the earlier ones of its file that it may need.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import SHARED_DATA

ROOT = Path(__file__).resolve().parents[1]
LANGUAGES = {"bash": "shell", "sh": "shell", "shell": "shell", "console": "console"}
LANGUAGES["python"] = "python"
#: one example may take this long (the slow ones included) before it fails
TIMEOUT_S = 1800
#: what the workspace does not link from the repository: outputs of earlier runs (an example
#: writing ``runs/smoke`` must write into the workspace, not into a developer's ``runs/``)
_NOT_LINKED = {"runs", "build", "dist", "__pycache__"}
_FENCE = re.compile(r"^(```+|~~~+)\s*([\w+-]*)")
_MARK = re.compile(r"^<!--\s*(slow|skip)\s*(?::\s*(.*?))?\s*-->$")


@dataclass
class Example:
    """One fenced example: where it is, its kind and code, and its mark."""

    path: Path
    line: int
    kind: str  # "shell", "console" (its commands) or "python"
    code: str
    mark: str | None = None  # None, "slow" or "skip"
    reason: str = ""

    @property
    def name(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def markdown_files() -> list[Path]:
    """README.md and every Markdown file under docs/."""
    docs = sorted((ROOT / "docs").rglob("*.md")) if (ROOT / "docs").is_dir() else []
    return [ROOT / "README.md", *docs]


def _console_commands(lines: list[str]) -> list[str]:
    """The commands of a console transcript: the lines after ``$ `` (outputs dropped)."""
    return [line[2:] for line in lines if line.startswith("$ ")]


def parse_examples(path: Path) -> list[Example]:
    """The runnable fenced blocks of one Markdown file, in order.

    Raises:
        ValueError: a fence is never closed, or a mark is not ``slow`` or ``skip: reason``.
    """
    lines = path.read_text(encoding="utf-8").splitlines()
    examples, k = [], 0
    while k < len(lines):
        fence = _FENCE.match(lines[k].strip())
        if not fence:
            k += 1
            continue
        start, closing = k, fence.group(1)
        end = next((j for j in range(k + 1, len(lines)) if lines[j].strip() == closing), None)
        if end is None:
            raise ValueError(f"{path}:{start + 1}: the fence is never closed")
        body, k = lines[start + 1 : end], end + 1
        kind = LANGUAGES.get(fence.group(2).lower())
        if kind is None:
            continue
        if fence.group(2).lower() == "console":
            body = _console_commands(body)
        example = Example(path, start + 1, kind, "\n".join(body) + "\n")
        before = next((lines[j].strip() for j in range(start - 1, -1, -1) if lines[j].strip()), "")
        mark = _MARK.match(before)
        if before.startswith("<!--") and mark is None and re.search(r"\b(slow|skip)\b", before):
            raise ValueError(f"{path}:{start + 1}: write <!-- slow --> or <!-- skip: reason -->")
        if mark:
            example.mark, example.reason = mark.group(1), mark.group(2) or ""
            if example.mark == "skip" and not example.reason:
                raise ValueError(f"{path}:{start + 1}: a skipped example needs a reason")
        examples.append(example)
    return examples


EXAMPLES = [example for path in markdown_files() for example in parse_examples(path)]


class Workspace:
    """The folder the examples of one Markdown file run in, and which of them ran."""

    def __init__(self, folder: Path, examples: list[Example]) -> None:
        self.cwd = folder / "repo"
        self.cwd.mkdir(parents=True)
        for entry in ROOT.iterdir():
            if not entry.name.startswith(".") and entry.name not in _NOT_LINKED:
                (self.cwd / entry.name).symlink_to(entry)
        (folder / "shared").mkdir()
        (folder / "shared" / "data").symlink_to(SHARED_DATA)
        self.examples = examples
        self.outcomes: dict[int, str | None] = {}  # index -> None (passed) or the failure

    def run_through(self, index: int, slow: bool) -> str | None:
        """Run the examples of the file up to ``index`` that did not run yet (skipping the
        marked ones); the failure of example ``index`` or of one before it, else None."""
        for k in range(index + 1):
            example = self.examples[k]
            if example.mark == "skip" or (example.mark == "slow" and not slow):
                continue
            if k not in self.outcomes:
                self.outcomes[k] = _run(example, self.cwd)
            if self.outcomes[k] is not None:
                before = "" if k == index else f"the earlier example {example.name} failed: "
                return before + self.outcomes[k]
        return None


def _run(example: Example, cwd: Path) -> str | None:
    """Run one example in ``cwd``; None when it exits 0, else what went wrong."""
    if example.kind == "python":
        script = cwd / f"example_{example.line}.py"
        script.write_text(example.code, encoding="utf-8")
        command = [sys.executable, script.name]
    else:
        command = ["bash", "-euo", "pipefail", "-c", example.code]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    try:
        done = subprocess.run(
            command, cwd=cwd, env=env, capture_output=True, text=True, timeout=TIMEOUT_S
        )
    except subprocess.TimeoutExpired:
        return f"{example.name} did not finish in {TIMEOUT_S} s"
    if done.returncode == 0:
        return None
    tail = "\n".join((done.stdout + done.stderr).splitlines()[-30:])
    return f"{example.name} exited {done.returncode}:\n{example.code}\n{tail}"


@pytest.fixture(scope="session")
def workspaces() -> dict[Path, Workspace]:
    """One workspace per Markdown file, made when its first example runs."""
    return {}


def _workspace(workspaces: dict[Path, Workspace], example: Example, tmp_path_factory):
    if example.path not in workspaces:
        examples = [e for e in EXAMPLES if e.path == example.path]
        folder = tmp_path_factory.mktemp(example.path.stem)
        workspaces[example.path] = Workspace(folder, examples)
    return workspaces[example.path]


@pytest.mark.realdata
@pytest.mark.parametrize("example", EXAMPLES, ids=[e.name for e in EXAMPLES])
def test_example_runs(example, workspaces, tmp_path_factory, request, shared_data):
    if example.mark == "skip":
        pytest.skip(f"{example.name}: {example.reason}")
    slow = request.config.getoption("--slow")
    if example.mark == "slow" and not slow:
        pytest.skip(f"{example.name}: slow (pytest --slow runs it)")
    workspace = _workspace(workspaces, example, tmp_path_factory)
    failure = workspace.run_through(workspace.examples.index(example), slow)
    if failure is not None:
        pytest.fail(failure, pytrace=False)


def test_the_examples_are_found_and_marks_are_parsed(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "text\n\n```bash\nbyoc --help\n```\n\n<!-- slow -->\n```python\nprint(1)\n```\n"
        "<!-- skip: installs packages -->\n\n```sh\npip install x\n```\n"
        "```console\n$ byoc --version\nbyoc, version 0.1.0\n```\n"
        "```\nbyoc register A B   (a synopsis, not run)\n```\n````bash\n```\n````\n",
        encoding="utf-8",
    )
    found = [(e.line, e.kind, e.code, e.mark, e.reason) for e in parse_examples(page)]
    assert found == [
        (3, "shell", "byoc --help\n", None, ""),
        (8, "python", "print(1)\n", "slow", ""),
        (13, "shell", "pip install x\n", "skip", "installs packages"),
        (16, "console", "byoc --version\n", None, ""),
        (23, "shell", "```\n", None, ""),
    ]
    page.write_text("<!-- skip -->\n```bash\nls\n```\n", encoding="utf-8")
    with pytest.raises(ValueError, match="needs a reason"):
        parse_examples(page)
    page.write_text("```bash\nls\n", encoding="utf-8")
    with pytest.raises(ValueError, match="never closed"):
        parse_examples(page)


def test_the_readme_has_examples_and_few_are_skipped():
    readme = [e for e in EXAMPLES if e.path.name == "README.md"]
    assert any(e.kind == "python" for e in readme) and any(e.kind == "shell" for e in readme)
    assert sum(e.mark == "skip" for e in EXAMPLES) <= len(EXAMPLES) // 2

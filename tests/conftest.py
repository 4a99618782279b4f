"""Shared fixtures: the real-data folder beside the project, seeded generators."""

from __future__ import annotations

import os
from pathlib import Path

from byoc_cli.threads import set_wait_policy

# before torch loads OpenMP (just below): the tests wait passively, as `byoc` does, whether
# they are run by the README's command or by CI; test subprocesses inherit it
set_wait_policy()

import pytest  # noqa: E402
import torch  # noqa: E402

SHARED_DATA = Path(
    os.environ.get(
        "BYOC_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"
    )
)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--slow",
        action="store_true",
        default=False,
        help="Run the fuzz tests with many more cases (BYOC_FUZZ_SCALE, default 10 times).",
    )


def pytest_configure(config: pytest.Config) -> None:
    # read by tests/_fuzzing.py when the fuzz modules are collected (after this hook)
    if config.getoption("--slow"):
        os.environ.setdefault("BYOC_FUZZ_SCALE", "10")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skips when absent, fails in CI (CI must not skip)."""
    if not SHARED_DATA.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"real data missing in CI: {SHARED_DATA}")
        pytest.skip(f"real data not found at {SHARED_DATA} (set BYOC_SHARED_DATA)")
    return SHARED_DATA


@pytest.fixture
def generator() -> torch.Generator:
    """A CPU generator seeded with 0."""
    return torch.Generator().manual_seed(0)


@pytest.fixture(autouse=True)
def _seeded_global_rng() -> None:
    """Every test starts from the same global torch RNG state.

    The library never draws from it (its seeds go through ``torch.Generator``), but a test
    that builds its input with a bare ``torch.rand`` would otherwise see a new draw on every
    run and could fail one run in many (CI once drew a point into a test's full cell).
    """
    torch.manual_seed(0)

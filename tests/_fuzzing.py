"""Helpers of the fuzz tests: hypothesis settings scaled by ``pytest --slow``, byte-level
mutations of a valid file, and the checks every fuzzed run must pass."""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st


def fuzz_settings(examples: int):
    """``examples`` cases (times ``BYOC_FUZZ_SCALE``, which ``--slow`` sets to 10)."""
    scale = int(os.environ.get("BYOC_FUZZ_SCALE", "1"))
    return settings(
        max_examples=examples * scale,
        deadline=None,
        derandomize=scale == 1,  # CI runs the same cases every time
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


_NUMBER = re.compile(rb"-?\d+(\.\d+)?(e-?\d+)?")
_ODD_NUMBERS = [b"0", b"-1", b"1e400", b"nan", b"-inf", b"99999999999", b"1000000000000", b"3.5"]


@st.composite
def mutated(draw, base: bytes, header_bytes: int = 400) -> bytes:
    """``base`` with a few mutations: a number in the header replaced (huge, negative,
    nan, ...), bytes flipped, a cut, random bytes inserted, or the whole file random."""
    if draw(st.integers(0, 19)) == 0:
        return draw(st.binary(max_size=600))
    data = bytearray(base)
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["number", "number", "flip", "cut", "insert"]))
        if kind == "number":
            found = list(_NUMBER.finditer(bytes(data[:header_bytes])))
            if found:
                match = found[draw(st.integers(0, len(found) - 1))]
                value = draw(
                    st.sampled_from(_ODD_NUMBERS)
                    | st.integers(-(10**13), 10**13).map(lambda v: str(v).encode())
                )
                data[match.start() : match.end()] = value
        elif kind == "flip" and data:
            at = draw(st.integers(0, len(data) - 1))
            data[at] = draw(st.integers(0, 255))
        elif kind == "cut":
            data = data[: draw(st.integers(0, len(data)))]
        else:
            at = draw(st.integers(0, len(data)))
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
    return bytes(data)


def snapshot(folder: Path) -> dict[str, str]:
    """SHA-256 of every file below ``folder``, by relative path."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def check_run(result, before: dict[str, str], after: dict[str, str], outputs=()) -> bool:
    """Assert the contract of a fuzzed run; returns True when it succeeded.

    Exit 0 or 1; every stderr line is one of ours (``byoc: ...``, no traceback, no raw
    warning); on failure exactly one error line; no pre-existing file changed; only
    ``outputs`` (names) may be new, and only after a success.
    """
    assert result.exit_code in (0, 1), (result.exit_code, result.output, result.exception)
    assert "Traceback" not in result.output
    lines = result.stderr.splitlines()
    assert all(line.startswith("byoc: ") for line in lines), result.stderr
    errors = [line for line in lines if line.startswith("byoc: error: ")]
    assert len(errors) == (result.exit_code == 1), result.stderr
    assert all(after.get(name) == digest for name, digest in before.items()), "input changed"
    added = set(after) - set(before)
    assert added <= (set(outputs) if result.exit_code == 0 else set()), added
    return result.exit_code == 0

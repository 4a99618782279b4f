"""The names of the methods ``eval-fmr`` and ``eval-pairs`` compare (``--method``), without
torch: the commands' ``--help`` lists them (:mod:`byoc_cli.evaluation.methods` builds them)."""

from __future__ import annotations

from collections.abc import Sequence

#: Every method name ``--method`` accepts, in table order.
METHOD_NAMES = (
    "byoc",
    "byoc-random",
    "fpfh-ransac",
    "fpfh-procrustes",
    "icp-point",
    "icp-plane",
    "identity",
)


def parse_method_names(values: Sequence[str]) -> list[str]:
    """Split ``values`` on commas and whitespace, check the names, drop repeats (keep order).

    Raises:
        ValueError: an unknown name (the message lists the known ones) or no name at all.
    """
    names: list[str] = []
    for value in values:
        for part in value.replace(",", " ").split():
            if part not in METHOD_NAMES:
                raise ValueError(f"unknown method {part!r} (known: {', '.join(METHOD_NAMES)})")
            if part not in names:
                names.append(part)
    if not names:
        raise ValueError(f"no method given (known: {', '.join(METHOD_NAMES)})")
    return names

"""The JSON Lines summary of ``register-batch``: one record per pair, appended as pairs finish.

A record says what became of a pair (:data:`OK`, :data:`LOW_CONFIDENCE`, :data:`FAILED`,
:data:`SKIPPED`). A rerun reads the results an earlier run recorded (:func:`recorded_results`),
so that a skipped pair below the gate still counts towards the exit code
(:func:`recorded_below`); the pairs below the gate are named on stderr at the end
(:func:`below_gate_lines`).
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import Any

log = logging.getLogger("byoc")

#: a pair's status in the summary
OK, LOW_CONFIDENCE, FAILED, SKIPPED = "ok", "low_confidence", "failed", "skipped"
#: pairs below the gate named on stderr at the end of a run (the others are counted)
NAMED_BELOW_GATE = 10


def output_key(output: Path) -> str:
    """How a T file is matched with the records of earlier runs (its absolute path)."""
    return str(output.absolute())


def recorded_results(summary: Path) -> dict[str, dict]:
    """The last registered result (status ``ok`` or ``low_confidence``) an earlier run
    recorded in ``summary`` for each T file: ``{output key: {"status", "confidence",
    "min_confidence", "beyond_trust_region"}}``; empty when there is no summary or it cannot
    be read (a line cut by a kill is passed over)."""
    import json

    from byoc_cli.errors import InputError
    from byoc_cli.io.inputs import open_input

    if not summary.exists():
        return {}
    found: dict[str, dict] = {}
    try:
        with open_input(summary, "report") as file:
            for raw in file:
                try:
                    record = json.loads(raw)
                except ValueError:
                    continue
                if not isinstance(record, dict) or record.get("status") not in (OK, LOW_CONFIDENCE):
                    continue
                output = record.get("output")
                if isinstance(output, str):
                    keep = ("status", "confidence", "min_confidence")
                    earlier = {k: record.get(k) for k in keep}
                    earlier["beyond_trust_region"] = init_reason(record) is not None
                    found[output_key(Path(output))] = earlier
    except InputError as exc:
        log.warning("the statuses of pairs done earlier are not known: %s", exc)
    return found


def recorded_below(recorded: dict, gate: float) -> bool:
    """Whether a recorded result is below this run's gate (its confidence against ``gate``;
    without a confidence, its recorded status); one that left its initial pose's trust region
    never passes."""
    if recorded.get("beyond_trust_region"):
        return True
    confidence = recorded.get("confidence")
    if isinstance(confidence, int | float) and not isinstance(confidence, bool):
        return confidence < gate
    return recorded.get("status") == LOW_CONFIDENCE


def init_reason(record: dict) -> str | None:
    """Why a pair did not pass other than its confidence: it is ambiguous (a turned try, or
    the check with another seed, fits elsewhere, or the source turned about the up axis fits
    as well), inconsistent with what the scans saw, or it was registered from its initial
    pose and left the trust region; None: none of these."""
    from byoc_cli.cli.pairwise import ambiguity, check_ambiguity, seen_through, turned_rival

    turns = record.get("turns") or {}
    if turns.get("ambiguous"):
        return ambiguity(turns)
    check = record.get("check") or {}
    if check.get("ambiguous"):
        return check_ambiguity(check, record.get("unit"))
    visibility = record.get("visibility") or {}
    if not visibility.get("consistent", True):
        return seen_through(visibility)
    turned = turned_rival(record.get("cues"))
    if turned is not None:
        return turned
    init = record.get("init") or {}
    if not init:
        return None

    def moved(c: dict) -> str:
        return f"{c['rotation_deg']:.1f} deg / {c['translation']:.4g}"

    bound = f"--max-correction {moved(init['trust_region'])}"
    if init.get("check") == "disagrees":
        return (
            f"the global result lies {moved(init['correction'])} from its init, beyond {bound}, "
            "and the local registration from the init did not pass"
        )
    if record.get("path") == "local" and not init.get("inside_trust_region", True):
        return f"the result moved {moved(init['correction'])} from its init, beyond {bound}"
    return None


def below_gate_lines(pairs: list, gate: float, summary: Path) -> list[str]:
    """The ``(entry, confidence, skipped, reason)`` ``pairs`` that did not pass, one line each
    up to :data:`NAMED_BELOW_GATE`, then a count (``reason``: :func:`init_reason`, or None for
    a confidence below the gate)."""
    lines = []
    for entry, confidence, was_skipped, reason in pairs[:NAMED_BELOW_GATE]:
        shown = "unknown" if confidence is None else f"{confidence:.3f}"
        when = " (recorded by an earlier run; T file kept)" if was_skipped else ""
        why = reason or f"confidence {shown} is below --min-confidence {gate:g}"
        lines.append(f"byoc: line {entry.line}: {entry.source} -> {entry.target}: {why}{when}")
    if len(pairs) > NAMED_BELOW_GATE:
        lines.append(
            f"byoc: and {len(pairs) - NAMED_BELOW_GATE} more pairs below --min-confidence "
            f"(the summary {summary} has every one)"
        )
    return lines


def pair_record(
    entry, output: Path, status: str, error: str | None = None, recorded: dict | None = None
) -> dict:
    """The fields every summary line has; ``recorded``: a skipped pair's result as an earlier
    run recorded it (``status``, ``confidence``, ``min_confidence``)."""
    return {
        "index": entry.index,
        "line": entry.line,
        "source": str(entry.source),
        "target": str(entry.target),
        "output": str(output),
        "status": status,
        "error": error,
        "recorded": recorded,
    }


class Summary:
    """The JSON Lines summary, appended one flushed line at a time; a summary this run created
    and left empty (it failed before a pair was done) is removed."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> Summary:
        self.created = not self.path.exists()
        self.file = open(self.path, "a", encoding="utf-8")
        return self

    def write(self, record: dict) -> None:
        from byoc_cli.io.jsonout import strict_dumps

        self.file.write(strict_dumps(record) + "\n")
        self.file.flush()

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        empty = self.file.tell() == 0
        self.file.close()
        if exc_type is not None and self.created and empty:
            with contextlib.suppress(OSError):
                self.path.unlink()

"""`confidence.py floor` and `floor-table`: every pair's refined registrations with and without
the refinement's restarts, and what each floor of ``register.RESTART_FLOOR`` would skip.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

from _confidence_set import part_of_set


def floor_collect(out: Path, part: tuple[int, int]) -> None:
    """Every pair's refined registrations with and without the restarts, one line per pair."""
    import dataclasses

    import byoc_cli.pipeline.register as register
    from byoc_cli.api import Registrar

    calls: list[dict] = []
    estimate = register.estimate_transform

    def both(src, tgt, config, voxel_size, clouds=None, refine_voxel=None, parallel=None):
        every = dataclasses.replace(config, restart_floor=0.0)  # the restarts always run
        after = estimate(src, tgt, every, voxel_size, clouds, refine_voxel, parallel)
        if config.refine == "multiscale" and config.restarts:
            none = dataclasses.replace(config, restarts=False)
            before = estimate(src, tgt, none, voxel_size, clouds, refine_voxel, parallel)
            calls.append(
                {
                    "model": config.confidence_model,
                    "before": before.confidence,
                    "after": after.confidence,
                    "restart_seconds": after.timings.get("restarts", 0.0),
                }
            )
        return after

    register.estimate_transform = both  # the registrar calls it through the module
    registrar = Registrar("byoc", device="cpu", fallback="fpfh")
    with out.open("w") as file:
        for name, group, load_src, load_tgt, _, _ in part_of_set(part):
            calls.clear()
            record = {"name": name, "group": group}
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    record["confidence"] = registrar.register(load_src(), load_tgt()).confidence
            except Exception as exc:  # a refusal: no registration to measure
                record["refused"] = str(exc)
            record["calls"] = list(calls)
            file.write(json.dumps(record) + "\n")
            file.flush()
            print(name, [(c["model"], round(c["before"], 3), round(c["after"], 3)) for c in calls])


def floor_table(paths: list[Path]) -> None:
    """For each floor: registrations below it before the restarts, the most confident of them
    after, how many passed the default gate after, and the restarts' seconds they took."""
    from byoc_cli.pipeline.confidence import DEFAULT_MIN_CONFIDENCE

    calls = [
        c for p in paths for line in p.read_text().splitlines() for c in json.loads(line)["calls"]
    ]
    raised = [c for c in calls if c["after"] > c["before"] + 1e-9]
    print(
        f"{len(calls)} refined registrations; the restarts raised the confidence of {len(raised)}"
        + (f", by at most {max(c['after'] - c['before'] for c in raised):.3f}" if raised else "")
    )
    print("floor  below  of  passed-after  most-after  restart-s-below  restart-s-all")
    total = sum(c["restart_seconds"] for c in calls)
    for floor in (0.05, 0.1, 0.2, 0.3, 0.45):
        below = [c for c in calls if c["before"] < floor]
        passed = sum(c["after"] >= DEFAULT_MIN_CONFIDENCE for c in below)
        most = max((c["after"] for c in below), default=0.0)
        seconds = sum(c["restart_seconds"] for c in below)
        print(
            f"{floor:5.2f} {len(below):6d} {len(calls):4d} {passed:13d} {most:11.3f}"
            f" {seconds:16.1f} {total:14.1f}"
        )

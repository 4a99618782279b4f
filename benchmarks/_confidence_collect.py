"""`confidence.py collect`: register every pair of the development set with the CLI's defaults
and append one JSON line per pair (its results, cues, ground truth refined on the data).
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import numpy as np

from _confidence_records import load_records
from _confidence_set import part_of_set

#: FPFH runs on the pairs whose learned confidence is below this (the fallback runs below the
#: gate, under 0.5 with any model fitted so far)
FALLBACK_MARGIN = 0.7


def _result(registrar, src: np.ndarray, tgt: np.ndarray, **settings) -> dict:
    """One registration's record: its transform, cues, confidence and seconds (or refusal)."""
    start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = registrar.register(src, tgt, **settings)
    except Exception as exc:  # a refusal: never exit 0, nothing to calibrate
        return {"refused": str(exc), "seconds": time.perf_counter() - start}
    return {
        "T": result.T_tgt_src.tolist(),
        "cues": result.cues,
        "confidence": result.confidence,
        "voxel": result.voxel_size,
        "seconds": time.perf_counter() - start,
    }


def _refined_truth(registrar, src, tgt, T_gt: np.ndarray) -> np.ndarray:
    """The ground truth refined by the multiscale ICP on the full clouds: the alignment the
    data support near the truth (as FCGF refines KITTI's GPS poses with ICP)."""
    import torch

    from byoc_cli.pipeline.refine import refine_multiscale

    choice = registrar.choose_voxel(src, tgt)
    refined = refine_multiscale(
        torch.from_numpy(src), torch.from_numpy(tgt), torch.from_numpy(T_gt), choice.refine_voxel
    )
    return refined.T_tgt_src.numpy()


def _truths(paths: list[Path]) -> dict[str, dict]:
    """The ground truth of every pair of earlier collections, by name."""
    keys = ("T_gt", "T_gt_refined", "T_gt_refined_error")
    return {r["name"]: {k: r[k] for k in keys if k in r} for r in load_records(paths)}


def collect(
    out: Path,
    part: tuple[int, int],
    groups: list[str],
    refine: str | None = None,
    truth_from: list[Path] | None = None,
) -> None:
    """Register the pairs into ``out``; ``refine="none"``: both features unrefined, FPFH on
    every pair (the calibration of results that are not refined); ``truth_from``: earlier
    collections whose ground truth (refined on the data) is reused."""
    from byoc_cli.api import Registrar

    done = set()
    if out.exists():
        done = {json.loads(line)["name"] for line in out.read_text().splitlines() if line}
    truths = _truths(truth_from) if truth_from else {}
    settings = {} if refine is None else {"refine": refine}
    byoc = Registrar("byoc", device="cpu", fallback=None)
    fpfh = Registrar("fpfh", device="cpu")
    with out.open("a") as file:
        for name, group, load_src, load_tgt, T_gt, scale in part_of_set(part):
            if name in done or (groups and group not in groups):
                continue
            record = {"name": name, "group": group, "scale": scale}
            src, tgt = load_src(), load_tgt()
            record["byoc"] = _result(byoc, src, tgt, **settings)
            # FPFH with the learned path's refinement: what the fallback runs, which it
            # does only below the gate (with a margin for the refitted model)
            if refine is not None:
                record["fpfh"] = _result(fpfh, src, tgt, **settings)
            elif record["byoc"].get("confidence", 0.0) < FALLBACK_MARGIN:
                record["fpfh"] = _result(fpfh, src, tgt, refine="multiscale")
            else:
                record["fpfh"] = {"skipped": f"learned confidence >= {FALLBACK_MARGIN}"}
            if name in truths:
                record.update(truths[name])
            elif T_gt is not None:
                T_gt = np.array(T_gt, dtype=np.float64)
                T_gt[:3, 3] *= scale
                record["T_gt"] = T_gt.tolist()
                try:
                    record["T_gt_refined"] = _refined_truth(byoc, src, tgt, T_gt).tolist()
                except Exception as exc:
                    record["T_gt_refined_error"] = str(exc)
            file.write(json.dumps(record) + "\n")
            file.flush()
            print(
                f"{name:40s} "
                + " ".join(
                    f"{k}={record[k].get('confidence', float('nan')):.3f}" for k in ("byoc", "fpfh")
                ),
                flush=True,
            )

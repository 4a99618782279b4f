"""Per-method summaries of the per-pair records of :func:`~.fmr.evaluate_fmr`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from byoc_cli.evaluation.fmr_protocol import FmrConfig
from byoc_cli.evaluation.methods import Method
from byoc_cli.evaluation.metrics import error_summary, recall_by_group


def _recall_dict(summary) -> dict[str, Any]:
    return {
        "mean_over_scenes": summary.mean,
        "std_over_scenes": summary.std,
        "pooled": summary.pooled,
        "num_pairs": summary.num_pairs,
        "per_scene": {
            scene: {"value": value, "num_pairs": n}
            for scene, (value, n) in summary.per_group.items()
        },
    }


def summarize_fmr(
    records: Sequence[dict[str, Any]], methods: Sequence[Method], config: FmrConfig
) -> dict[str, dict[str, Any]]:
    """Per-method summaries of per-pair records.

    Returns:
        ``{method: {...}}`` with ``fmr``, ``corr_fmr``, ``inlier_ratio``, ``corr_inlier_ratio``
        (each: ``mean_over_scenes``, ``std_over_scenes``, ``pooled``, ``num_pairs``,
        ``per_scene``; None for methods without features), ``registration_recall``
        (official pairs ``j - i > 1`` with ``gt.info``; None when no pair has it),
        ``registration_recall_all_pairs``, ``success_rate``, ``rotation_error_deg`` and
        ``translation_error_cm`` (mean, median over all pairs), ``num_failed``,
        ``seconds_per_pair``.
    """
    scenes = [r["scene"] for r in records]
    out: dict[str, dict[str, Any]] = {}
    for method in methods:
        rows = [r["methods"][method.name] for r in records]
        summary: dict[str, Any] = {"num_pairs": len(records)}
        if method.features is not None and records:
            feats = [r["features"][method.features.key] for r in records]
            summary["fmr"] = _recall_dict(recall_by_group([f["recalled"] for f in feats], scenes))
            summary["corr_fmr"] = _recall_dict(
                recall_by_group([f["corr_recalled"] for f in feats], scenes)
            )
            summary["inlier_ratio"] = _recall_dict(
                recall_by_group(
                    [f["recalled"] for f in feats], scenes, [f["inlier_ratio"] for f in feats]
                )
            )
            summary["corr_inlier_ratio"] = _recall_dict(
                recall_by_group(
                    [f["corr_recalled"] for f in feats],
                    scenes,
                    [f["corr_inlier_ratio"] for f in feats],
                )
            )
        else:
            summary.update(fmr=None, corr_fmr=None, inlier_ratio=None, corr_inlier_ratio=None)
        for key, keep in (
            ("registration_recall", lambda r: r["official"] and r["has_info"]),
            ("registration_recall_all_pairs", lambda r: r["has_info"]),
        ):
            chosen = [r for r in records if keep(r)]
            if chosen:
                flags = [r["methods"][method.name]["registered"] for r in chosen]
                result = _recall_dict(recall_by_group(flags, [r["scene"] for r in chosen]))
                result["num_degenerate_info"] = sum(
                    1
                    for r in chosen
                    if r["methods"][method.name]["rmse_m"] is None
                    or math.isnan(r["methods"][method.name]["rmse_m"])
                )
                summary[key] = result
            else:
                summary[key] = None
        summary["success_rate"] = (
            _recall_dict(recall_by_group([row["success"] for row in rows], scenes))
            if rows
            else None
        )
        rot = error_summary([row["rotation_error_deg"] for row in rows], ())
        trans = error_summary([100.0 * row["translation_error_m"] for row in rows], ())
        summary["rotation_error_deg"] = {"mean": rot.mean, "median": rot.median}
        summary["translation_error_cm"] = {"mean": trans.mean, "median": trans.median}
        summary["num_failed"] = sum(1 for row in rows if row["failed"])
        summary["seconds_per_pair"] = (
            float(np.mean([row["seconds"] for row in rows])) if rows else float("nan")
        )
        out[method.name] = summary
    return out

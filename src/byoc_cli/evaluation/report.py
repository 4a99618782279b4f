"""Evaluation reports: the JSON object and the rows of the side-by-side table.

The JSON holds every figure (summaries and per-pair records), the protocol of each figure,
the pair count, the settings, the seed and the versions. NaN and infinities become ``null``.
The table is plain strings (one column per method); the CLI draws it.
"""

from __future__ import annotations

import math
import platform
from collections.abc import Sequence
from importlib import metadata
from typing import Any

__all__ = [
    "FMR_PROTOCOLS",
    "PAIRS_PROTOCOLS",
    "clean_json",
    "fmr_report",
    "fmr_table",
    "pairs_report",
    "pairs_table",
    "versions",
]

FMR_PROTOCOLS = {
    "fmr": "feature-match recall: 5000 seeded random kept points per fragment; each point of "
    "the smaller sample matched to its nearest neighbour in feature space among the other "
    "sample (one direction, no mutual check, as FCGF); inlier when |T_gt p - q| < tau1; "
    "pair recalled when the inlier ratio >= tau2",
    "fmr-fcgf": "FCGF protocol: recall per scene, then mean and population std over scenes",
    "fmr-pooled": "BYOC protocol: recall over all pairs pooled",
    "corr": "the same recall on the ratio-test correspondences (top k per direction, 2k in "
    "all) of the same samples",
    "inlier-ratio": "mean inlier ratio of the nearest-neighbour matches (resp. correspondences)",
    "rr-3dmatch": "official 3DMatch registration recall: E = inv(T_gt) T_est, p = (t_E, "
    "imaginary part of the unit quaternion of R_E, w >= 0), RMSE = sqrt(p^T info p / "
    "info[0,0]) from gt.info, recalled when RMSE <= 0.2 m; only pairs with j - i > 1 (the "
    "toolbox skips consecutive fragments); a degenerate info (info[0,0] = 0) counts as not "
    "recalled; per scene, mean over scenes and pooled",
    "rr-all-pairs": "the same recall over every gt.log pair that has gt.info",
    "success-rate": "rotation error < 15 deg and translation error < 30 cm (DGR), all pairs",
    "pose-errors": "rotation error arccos((tr(R_est R_gt^T) - 1) / 2) in degrees, translation "
    "error |t_est - t_gt| in cm; mean and median over all pairs (failed registrations count "
    "with the identity)",
}

PAIRS_PROTOCOLS = {
    "pairs": "test pairs of each posed sequence: every spacing-th frame, consecutive ones "
    "paired; source = later frame, target = earlier, T_gt = inv(T_world_tgt) T_world_src; "
    "clouds = full-resolution depth back-projections",
    "rotation": "arccos((tr(R_est R_gt^T) - 1) / 2) in degrees; accuracy = percent of pairs "
    "with error strictly below the threshold",
    "translation": "|t_est - t_gt| in cm",
    "chamfer": "symmetric chamfer distance with squared distances (mean_a min_b |a-b|^2 + "
    "mean_b min_a |b-a|^2, as PyTorch3D) between target + T_est source and target + T_gt "
    "source, both clouds voxelised at 2.5 cm, in 1e-3 m^2; the paper gives no unit for its "
    "thresholds 1/5/10, this unit is this tool's reading",
}


def versions() -> dict[str, str | None]:
    """Versions of byoc-cli, Python, torch, numpy and open3d (None when absent)."""
    from byoc_cli import __version__

    def dist(*names: str) -> str | None:
        for name in names:
            try:
                return metadata.version(name)
            except metadata.PackageNotFoundError:
                continue
        return None

    return {
        "byoc_cli": __version__,
        "python": platform.python_version(),
        "torch": dist("torch"),
        "numpy": dist("numpy"),
        "open3d": dist("open3d", "open3d-cpu"),
    }


def clean_json(value: Any) -> Any:
    """Recursively replace NaN/Inf floats by None and tuples by lists (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): clean_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [clean_json(v) for v in value]
    return value


def fmr_report(
    result,
    pair_set,
    methods: Sequence,
    config,
    settings: dict[str, Any],
    bands: Sequence = (),
    num_outside_bands: int = 0,
) -> dict[str, Any]:
    """The ``eval-fmr`` JSON report (see the module docstring).

    ``bands``: :class:`~byoc_cli.evaluation.bands.OverlapBand` s; each gets the summaries of
    its pairs under ``bands`` (``label``, ``min_overlap``, ``max_overlap``, ``num_pairs``,
    ``results``), and the table shows them side by side.
    """
    from dataclasses import asdict

    from byoc_cli.evaluation.bands import split_by_band
    from byoc_cli.evaluation.fmr_summary import summarize_fmr

    by_band = []
    if bands:
        members, _ = split_by_band([r["overlap"] for r in result.records], bands)
        for band, indices in zip(bands, members, strict=True):
            records = [result.records[k] for k in indices]
            by_band.append(
                {
                    "label": band.label,
                    "min_overlap": band.low,
                    "max_overlap": band.high,
                    "num_pairs": len(records),
                    "results": summarize_fmr(records, methods, config),
                }
            )
    return clean_json(
        {
            "command": "eval-fmr",
            "protocols": FMR_PROTOCOLS,
            "settings": {**asdict(config), **settings},
            "seed": config.seed,
            "versions": versions(),
            "methods": [m.describe() for m in methods],
            "scenes": [
                {
                    "name": s.name,
                    "gt_log": str(s.gt_log),
                    "gt_info": str(s.gt_info) if s.gt_info else None,
                    "num_pairs": sum(1 for p in pair_set.pairs if p.scene == s.name),
                }
                for s in pair_set.scenes
            ],
            "num_pairs": len(pair_set.pairs),
            "num_pairs_listed": pair_set.num_listed,
            "num_pairs_official": sum(1 for r in result.records if r["official"]),
            "num_pairs_with_info": sum(1 for r in result.records if r["has_info"]),
            "num_pairs_skipped_missing": len(pair_set.skipped_pairs),
            "missing_fragments": pair_set.missing_fragments,
            "skipped_pairs": [list(p) for p in pair_set.skipped_pairs],
            "results": result.summaries,
            "bands": by_band or None,
            "num_pairs_outside_bands": num_outside_bands if bands else None,
            "cache": {"hits": result.cache_hits, "misses": result.cache_misses},
            "seconds": result.seconds,
            "pairs": result.records,
        }
    )


def pairs_report(
    result, methods: Sequence, config, settings: dict[str, Any], sources: list[dict[str, Any]]
) -> dict[str, Any]:
    """The ``eval-pairs`` JSON report."""
    from dataclasses import asdict

    return clean_json(
        {
            "command": "eval-pairs",
            "protocols": PAIRS_PROTOCOLS,
            "settings": {**asdict(config), **settings},
            "seed": config.seed,
            "versions": versions(),
            "methods": [m.describe() for m in methods],
            "sources": sources,
            "num_pairs": len(result.records),
            "gt_motion": result.motion,
            "results": result.summaries,
            "cache": {"hits": result.cache_hits, "misses": result.cache_misses},
            "seconds": result.seconds,
            "pairs": result.records,
        }
    )


# ================================================================== tables


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100.0 * value:.1f}"


def _num(value: float | None, spec: str = ".2f") -> str:
    return "-" if value is None else format(value, spec)


def fmr_table(report: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """``(column names, rows)`` of the eval-fmr table: one column per method, or per
    overlap band and method (``byoc 10-30%``) when the report has ``bands``, band by band.

    Recalls and ratios in percent; "-" where a figure does not apply (no features, no
    gt.info).
    """
    results = report["results"]
    if report.get("bands"):
        results = {
            f"{name} {band['label']}": summary
            for band in report["bands"]
            for name, summary in band["results"].items()
        }
    names = list(results)
    rows: list[list[str]] = [["pairs", *[str(results[n]["num_pairs"]) for n in names]]]

    def add(label: str, getter) -> None:
        rows.append([label, *[getter(results[n]) for n in names]])

    def mean_std(key: str):
        def get(s):
            block = s.get(key)
            if not block:
                return "-"
            return f"{_pct(block['mean_over_scenes'])} ± {_pct(block['std_over_scenes'])}"

        return get

    def field(key: str, sub: str):
        return lambda s: _pct(s[key][sub]) if s.get(key) else "-"

    add("FMR % (fcgf: scene mean ± std)", mean_std("fmr"))
    add("FMR % (pooled)", field("fmr", "pooled"))
    scenes = [s["name"] for s in report["scenes"] if s["num_pairs"]]
    if len(scenes) > 1:
        for scene in scenes:
            add(
                f"  FMR % {scene}",
                lambda s, scene=scene: (
                    _pct(s["fmr"]["per_scene"][scene]["value"])
                    if s.get("fmr") and scene in s["fmr"]["per_scene"]
                    else "-"
                ),
            )
    add("FMR corr % (fcgf)", mean_std("corr_fmr"))
    add("FMR corr % (pooled)", field("corr_fmr", "pooled"))
    add("inlier ratio % (NN)", field("inlier_ratio", "pooled"))
    add("inlier ratio % (corr)", field("corr_inlier_ratio", "pooled"))
    add(
        "RR % (official, j-i>1: scene mean)",
        field("registration_recall", "mean_over_scenes"),
    )
    add("RR % (official, j-i>1: pooled)", field("registration_recall", "pooled"))
    add("RR % (all pairs, pooled)", field("registration_recall_all_pairs", "pooled"))
    add("success % (RE<15°, TE<30cm)", field("success_rate", "pooled"))
    add("rotation error mean / median °", lambda s: _mean_median(s["rotation_error_deg"], ".1f"))
    add(
        "translation error mean / median cm",
        lambda s: _mean_median(s["translation_error_cm"], ".1f"),
    )
    add("failed", lambda s: str(s["num_failed"]))
    add("registration s / pair", lambda s: _num(s["seconds_per_pair"], ".3f"))
    return ["metric", *names], rows


def _mean_median(block: dict[str, Any], spec: str) -> str:
    return f"{_num(block['mean'], spec)} / {_num(block['median'], spec)}"


def pairs_table(report: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """``(column names, rows)`` of the eval-pairs table: one column per method."""
    results = report["results"]
    names = list(results)
    rows: list[list[str]] = [["pairs", *[str(results[n]["num_pairs"]) for n in names]]]
    for key, label, unit in (
        ("rotation_deg", "rotation", "°"),
        ("translation_cm", "translation", "cm"),
        ("chamfer", "chamfer", "e-3 m²"),
    ):
        thresholds = list(results[names[0]][key]["accuracy_percent"]) if names else []
        for thr in thresholds:
            rows.append(
                [
                    f"{label} acc % < {thr} {unit}",
                    *[_num(results[n][key]["accuracy_percent"][thr], ".1f") for n in names],
                ]
            )
        rows.append([f"{label} mean {unit}", *[_num(results[n][key]["mean"]) for n in names]])
        rows.append([f"{label} median {unit}", *[_num(results[n][key]["median"]) for n in names]])
    rows.append(["failed", *[str(results[n]["num_failed"]) for n in names]])
    rows.append(
        ["registration s / pair", *[_num(results[n]["seconds_per_pair"], ".3f") for n in names]]
    )
    return ["metric", *names], rows

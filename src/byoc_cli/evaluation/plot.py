"""PNG plots of accuracy against threshold, all methods side by side (matplotlib, Agg).

Curves are computed from the per-pair records of a report: for each threshold ``x`` the
percent of pairs whose error is strictly below ``x`` (for recall: whose inlier ratio is at
least ``x``). Files are written atomically.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["accuracy_curve", "fmr_figure", "pairs_figure", "plot_fmr", "plot_pairs"]


def accuracy_curve(values: Sequence[float | None], thresholds: np.ndarray) -> np.ndarray:
    """Percent of values strictly below each threshold (None/NaN never are).

    Args:
        values: per-pair errors.
        thresholds: ``(T,)``.

    Returns:
        ``(T,)`` percentages (zeros when there is no value).
    """
    v = np.array([np.nan if x is None else x for x in values], dtype=np.float64)
    if v.size == 0:
        return np.zeros(len(thresholds))
    with np.errstate(invalid="ignore"):
        return 100.0 * (v[None, :] < np.asarray(thresholds)[:, None]).mean(axis=1)


def _figure(panels: int):
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.6 * panels, 4.0), dpi=100)
    axes = fig.subplots(1, panels, squeeze=False)[0]
    return fig, axes


def _save(fig, path: str | Path) -> Path:
    from byoc_cli.io.atomic import atomic_write_bytes

    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    atomic_write_bytes(path, buffer.getvalue())
    return Path(path)


def _datasets(report: dict[str, Any]) -> str:
    """The data sets of a report, for titles: sequence names, pair folders or the benchmark."""
    names: list[str] = []
    for source in report.get("sources", []):
        name = source.get("name") or Path(str(source.get("root", ""))).name
        if name and name not in names:
            names.append(name)
    if not names and report.get("settings", {}).get("root"):
        names.append(Path(report["settings"]["root"]).name)
        scenes = report["settings"].get("scenes_selected")
        if scenes:
            names[0] += f" ({', '.join(scenes)})"
    shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    return shown or "?"


def _axis(limit: float, values: Sequence[float | None], points: int = 201) -> np.ndarray:
    """Thresholds from 0 to ``limit``, extended to reach the largest of ``values``."""
    finite = [v for v in values if v is not None and np.isfinite(v)]
    top = max([limit, *finite])
    if top > limit:
        top = float(np.ceil(top * 1.05))
    return np.linspace(0, top, points)


def _panel(ax, curves: dict[str, np.ndarray], x: np.ndarray, xlabel: str, ylabel: str) -> None:
    for name, y in curves.items():
        ax.plot(x, y, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    if curves:
        ax.legend(fontsize="small")


def plot_pairs(report: dict[str, Any], path: str | Path, title: str = "") -> Path:
    """Write :func:`pairs_figure` as a PNG to ``path`` (atomically); returns ``path``."""
    return _save(pairs_figure(report, title), path)


def pairs_figure(report: dict[str, Any], title: str = ""):
    """Rotation, translation and chamfer accuracy against threshold, one curve per method.

    Args:
        report: an ``eval-pairs`` report (:func:`byoc_cli.evaluation.report.pairs_report`).
        title: figure title [default: the data sets and the number of pairs].

    Returns:
        A matplotlib ``Figure``.
    """
    names = list(report["results"])
    records = report["pairs"]
    fig, axes = _figure(3)
    # the rotation and translation axes reach the identity's error (the ground-truth motion)
    rotation = _axis(45, [r.get("gt_rotation_deg") for r in records], 181)
    translation = _axis(50, [r.get("gt_translation_cm") for r in records])
    for ax, key, x, label in (
        (axes[0], "rotation_error_deg", rotation, "rotation error threshold (°)"),
        (axes[1], "translation_error_cm", translation, "translation threshold (cm)"),
        (axes[2], "chamfer", np.linspace(0, 20, 201), "chamfer threshold (1e-3 m²)"),
    ):
        curves = {n: accuracy_curve([r["methods"][n][key] for r in records], x) for n in names}
        _panel(ax, curves, x, label, "pairs below threshold (%)")
    fig.suptitle(title or f"eval-pairs on {_datasets(report)}: {report['num_pairs']} pairs")
    return fig


def plot_fmr(report: dict[str, Any], path: str | Path, title: str = "") -> Path:
    """Write :func:`fmr_figure` as a PNG to ``path`` (atomically); returns ``path``."""
    return _save(fmr_figure(report, title), path)


def fmr_figure(report: dict[str, Any], title: str = ""):
    """FMR against tau2, registration recall against the RMSE threshold, rotation accuracy.

    The first panel has one curve per feature spec, labelled with the names of the methods
    that share it (``fpfh-ransac``, as in the other panels and the table); the RMSE panel
    is drawn from the official pairs with ``gt.info`` (empty without any).

    Returns:
        A matplotlib ``Figure`` titled with the benchmark [default] or ``title``.
    """
    records = report["pairs"]
    methods = report["methods"]
    fig, axes = _figure(3)
    tau2 = np.linspace(0, 0.3, 151)
    sharing: dict[str, list[str]] = {}
    for m in methods:
        key = (m.get("features") or {}).get("key")
        if key is not None:
            sharing.setdefault(key, []).append(m["name"])
    curves = {}
    for key, users in sharing.items():
        ratios = [r["features"][key]["inlier_ratio"] for r in records]
        # recalled when ratio >= tau2  <=>  -ratio <= -tau2; use 1 - "below" of the ratios
        curves[", ".join(users)] = 100.0 - accuracy_curve(ratios, tau2)
    _panel(axes[0], curves, tau2, "inlier-ratio threshold tau2", "FMR, pooled (%)")
    axes[0].axvline(report["settings"]["tau2"], color="grey", linestyle=":")
    official = [r for r in records if r["official"] and r["has_info"]]
    rmse = np.linspace(0, 0.5, 201)
    _panel(
        axes[1],
        {
            m["name"]: accuracy_curve([r["methods"][m["name"]]["rmse_m"] for r in official], rmse)
            for m in methods
        }
        if official
        else {},
        rmse,
        "RMSE threshold (m), pairs j-i>1",
        "registration recall (%)",
    )
    rot = np.linspace(0, 45, 181)
    _panel(
        axes[2],
        {
            m["name"]: accuracy_curve(
                [r["methods"][m["name"]]["rotation_error_deg"] for r in records], rot
            )
            for m in methods
        },
        rot,
        "rotation error threshold (°)",
        "pairs below threshold (%)",
    )
    fig.suptitle(title or f"eval-fmr on {_datasets(report)}: {report['num_pairs']} pairs")
    return fig

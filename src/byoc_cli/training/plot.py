"""A PNG of a run's losses and validation accuracy (matplotlib, Agg backend)."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

METRICS_FILE = "metrics.jsonl"
PLOT_FILE = "training.png"


def read_metrics(path: str | Path) -> list[dict[str, Any]]:
    """Parse a metrics JSON-lines file; unparseable lines (a torn last line) are skipped."""
    from byoc_cli.io.inputs import read_input

    records = []
    if not Path(path).exists():
        return []
    text = read_input(path, "report").decode("utf-8", errors="replace")
    for line in text.splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            record = json.loads(line)
        except (json.JSONDecodeError, RecursionError):
            continue
        if isinstance(record, dict):
            records.append(record)
    return records


def plot_metrics(records: list[dict[str, Any]], path: str | Path, title: str = "") -> Path:
    """Draw loss terms (left) and validation rotation/translation accuracy (right).

    Args:
        records: metric records (``kind`` ``"train"`` with ``loss*`` keys, ``"val"`` with
            ``rot_acc_*``/``trans_acc_*``/``inlier_pct_mean`` keys).
        path: PNG to write (atomically).
        title: figure title.

    Returns:
        ``path``.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    from byoc_cli.io.atomic import atomic_write_bytes

    train = [r for r in records if r.get("kind") == "train"]
    val = [r for r in records if r.get("kind") == "val"]
    fig = Figure(figsize=(11, 4), dpi=100)
    ax_loss, ax_val = fig.subplots(1, 2)
    for key in ("loss", "loss_vis", "loss_geo", "loss_v2g"):
        pts = [(r["step"], r[key]) for r in train if r.get(key) is not None]
        if pts and any(v != 0 for _, v in pts):
            ax_loss.plot(*zip(*pts, strict=True), label=key)
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("loss")
    ax_loss.set_title("training losses")
    if ax_loss.lines:
        ax_loss.legend()
    for key in ("rot_acc_5", "rot_acc_10", "trans_acc_5", "trans_acc_10", "inlier_pct_mean"):
        pts = [(r["step"], r[key]) for r in val if r.get(key) is not None]
        if pts:
            ax_val.plot(*zip(*pts, strict=True), marker="o", label=key)
    ax_val.set_xlabel("step")
    ax_val.set_ylabel("accuracy (%)")
    ax_val.set_title("validation (geometric encoder)")
    if ax_val.lines:
        ax_val.legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    atomic_write_bytes(path, buffer.getvalue())
    return Path(path)

"""Writing the pairs of benchmarks/scan_sim.py: binary PLY (float64 where float32 would lose more
than a millionth of the cloud's size), ``T_gt.txt``, ``info.json``; size names; a top view.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from _scan_sim_geometry import Pair


def ply_dtype(points: np.ndarray) -> str:
    """``"f4"`` when float32 keeps ``points (N, 3)`` within a millionth of the cloud's size
    (the spread between its 1st and 99th percentiles), else ``"f8"``."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return "f4"
    with np.errstate(over="ignore"):
        as32 = points.astype(np.float32).astype(np.float64)
    if not np.all(np.isfinite(as32)):
        return "f8"
    spread = np.percentile(points, 99, axis=0) - np.percentile(points, 1, axis=0)
    size = float(np.linalg.norm(spread))
    error = float(np.max(np.abs(as32 - points)))
    return "f4" if error <= 1e-6 * size or error == 0.0 else "f8"


def write_ply(path: Path, points: np.ndarray, dtype: str | None = None) -> str:
    """Write ``points (N, 3)`` as a binary PLY of x, y, z of ``dtype`` (``"f4"`` float,
    ``"f8"`` double; None: :func:`ply_dtype`); returns the dtype written."""
    from plyfile import PlyData, PlyElement

    dtype = dtype or ply_dtype(points)
    vertex = np.empty(len(points), dtype=[("x", dtype), ("y", dtype), ("z", dtype)])
    with np.errstate(over="ignore"):
        for k, axis in enumerate("xyz"):
            vertex[axis] = points[:, k]
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    return dtype


def write_pair(folder: Path, pair: Pair, info: dict, dtype: str | None = None) -> dict:
    """``folder/{source.ply,target.ply,T_gt.txt,info.json}``; ``info`` (how it was made) gets
    the point counts and PLY types; returns it."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    src, tgt, T = pair
    info = {**info, "points_src": len(src), "points_tgt": len(tgt)}
    info["ply_dtype"] = [
        write_ply(folder / "source.ply", src, dtype),
        write_ply(folder / "target.ply", tgt, dtype),
    ]
    np.savetxt(folder / "T_gt.txt", T, fmt="%.17g")
    (folder / "info.json").write_text(json.dumps(info, indent=1) + "\n")
    return info


def size_name(points: int) -> str:
    """``42000 -> "42k"``, ``1100000 -> "1.1M"``, ``500 -> "500"``."""
    for unit, div in (("M", 1e6), ("k", 1e3)):
        if points >= div:
            return f"{points / div:.3g}{unit}"
    return str(points)


def top_view(points: np.ndarray, path: Path, title: str = "", extent: float = 60.0) -> None:
    """A PNG of ``points (N, 3)`` seen from above (x right, y up), coloured by height, within
    ``extent`` m of the origin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    near = np.all(np.abs(points[:, :2]) < extent, axis=1)
    p = points[near][np.argsort(points[near, 2])]
    span = np.ptp(p[:, :2], axis=0) + 1e-9
    fig, ax = plt.subplots(figsize=(16, max(4.0, 16 * span[1] / span[0])))
    dots = ax.scatter(p[:, 0], p[:, 1], c=p[:, 2], s=0.5, cmap="turbo", linewidths=0)
    fig.colorbar(dots, ax=ax, label="height (sensor frame)", shrink=0.6)
    ax.set_aspect("equal")
    ax.set_title(f"{title} ({len(points)} points)")
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)

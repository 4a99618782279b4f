"""Quality files of one registration, for a person to judge a doubtful pair in seconds.

Given the source, the target and ``T_tgt_src``, :func:`write_qc` writes two files:

* ``<name>_qc.png``: the target and the moved source overlaid in three orthographic views
  (top: x-y seen from +z; front: x-z seen from -y; side: y-z seen from +x), target in blue
  (:data:`TARGET_RGB`) and source in orange (:data:`SOURCE_RGB`), the two clouds' points
  drawn in one shuffled order so that where they overlap both colours show; below, the same
  views of the moved source coloured by its residual (the distance of each moved source
  point to its nearest target point, clipped at ``clip``; viridis, with a colour bar) over
  the target in light grey;
* ``<name>_residual.ply``: the moved source in the input's coordinates, coloured by residual
  with the same colour map, and the residual itself as a ``residual`` property (a scalar field
  in CloudCompare).

Large clouds are sampled (seeded): at most :data:`MAX_DRAW_POINTS` points of each cloud are
drawn and at most :data:`MAX_PLY_POINTS` source points go into the PLY. Coordinates far from
the origin (georeferenced) are drawn relative to a whole-unit origin the axis labels state.
Both files are written atomically. matplotlib (Agg) draws; nothing here prints.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from byoc_cli.errors import ShapeError

__all__ = [
    "MAX_DRAW_POINTS",
    "MAX_PLY_POINTS",
    "RESIDUAL_CLIP_VOXELS",
    "SOURCE_RGB",
    "TARGET_RGB",
    "QcResult",
    "QcSettings",
    "qc_paths",
    "residuals",
    "write_qc",
]

#: the target's colour in the overlay (Okabe-Ito blue)
TARGET_RGB = (0, 114, 178)
#: the moved source's colour in the overlay (Okabe-Ito orange)
SOURCE_RGB = (230, 159, 0)
#: the target under the residual views
CONTEXT_RGB = (205, 205, 205)
#: the colour map of residuals (0 to the clip)
RESIDUAL_CMAP = "viridis"
#: the residuals are clipped at this many voxels of the registration (the commands' choice)
RESIDUAL_CLIP_VOXELS = 3.0
#: most points of each cloud drawn
MAX_DRAW_POINTS = 200_000
#: most source points written to the residual PLY
MAX_PLY_POINTS = 2_000_000
#: (panel title, horizontal axis, vertical axis) of the three views
VIEWS = (("top (x-y)", 0, 1), ("front (x-z)", 0, 2), ("side (y-z)", 1, 2))
#: marker area in points^2 (about 1.4 pixels a side at the figure's 100 dpi)
_MARKER_AREA = 1.0
#: coordinates at least this far from the origin are drawn relative to a whole-unit origin
_FAR = 1e4
#: share of the points (each end, per axis) left outside a view, so that strays do not
#: shrink the clouds to a dot
_VIEW_QUANTILE = 0.002


@dataclass(frozen=True)
class QcSettings:
    """How the quality files of one pair are made.

    Attributes:
        clip: residuals at or above this are drawn in the top colour, in the points' units
            (the commands use :data:`RESIDUAL_CLIP_VOXELS` voxels).
        unit: the points' unit, for labels (``"m"`` or ``"input units"``).
        title: the figure's first line (the pair, its confidence).
        max_draw_points: most points of each cloud drawn.
        max_ply_points: most source points in the residual PLY.
        seed: seed of the samples.
    """

    clip: float
    unit: str = "input units"
    title: str = ""
    max_draw_points: int = MAX_DRAW_POINTS
    max_ply_points: int = MAX_PLY_POINTS
    seed: int = 0


class QcResult(NamedTuple):
    """What :func:`write_qc` wrote and measured.

    Attributes:
        png: the figure.
        ply: the moved source coloured by residual.
        clip: the residual clip, in the points' units.
        median_residual: median residual of the moved source points (of the PLY's sample).
        within_clip: share of those points whose residual is below ``clip``.
        num_points_src, num_points_tgt: points of each cloud given.
    """

    png: Path
    ply: Path
    clip: float
    median_residual: float
    within_clip: float
    num_points_src: int
    num_points_tgt: int


def qc_paths(folder: str | Path, name: str) -> tuple[Path, Path]:
    """``(folder/<name>_qc.png, folder/<name>_residual.ply)``."""
    folder = Path(folder)
    return folder / f"{name}_qc.png", folder / f"{name}_residual.ply"


def _points(points: np.ndarray, label: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ShapeError(f"{label} must be (N, 3) with N >= 1, got {points.shape}")
    if not np.isfinite(points).all():
        raise ShapeError(f"{label} must be finite")
    return points


def _origin(points: np.ndarray) -> np.ndarray:
    """A whole-unit origin near the median point when the points lie far out, else zeros."""
    median = np.median(points, axis=0)
    if np.abs(median).max() < _FAR:
        return np.zeros(3)
    return np.round(median)


def residuals(points_src: np.ndarray, points_tgt: np.ndarray) -> np.ndarray:
    """Distance of each source point to its nearest target point (k-d tree, float64).

    Args:
        points_src: ``(N, 3)`` points, already in the target's frame.
        points_tgt: ``(M, 3)`` points, M >= 1.

    Returns:
        ``(N,)`` float64; ``out[i]`` is the distance of ``points_src[i]`` to the nearest row
        of ``points_tgt``.

    Raises:
        ShapeError: not ``(N, 3)`` and ``(M, 3)`` finite with M >= 1.
    """
    from pykdtree.kdtree import KDTree

    points_tgt = _points(points_tgt, "points_tgt")
    points_src = np.asarray(points_src, dtype=np.float64)
    if points_src.ndim != 2 or points_src.shape[1] != 3:
        raise ShapeError(f"points_src must be (N, 3), got {points_src.shape}")
    if points_src.shape[0] == 0:
        return np.zeros(0)
    origin = _origin(points_tgt)  # subtracted in float64: the tree works near the origin
    tree = KDTree(np.ascontiguousarray(points_tgt - origin))
    distances, _ = tree.query(np.ascontiguousarray(points_src - origin), k=1)
    return np.asarray(distances, dtype=np.float64)


def _sample(n: int, most: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of at most ``most`` of ``n`` points (all of them when ``n <= most``)."""
    if n <= most:
        return np.arange(n)
    return np.sort(rng.choice(n, size=most, replace=False))


def _residual_colors(values: np.ndarray, clip: float) -> np.ndarray:
    """``(N, 3)`` uint8 colours of residuals in the colour map, 0 to ``clip``."""
    import matplotlib

    cmap = matplotlib.colormaps[RESIDUAL_CMAP]
    rgba = cmap(np.clip(values / clip, 0.0, 1.0))
    return np.round(np.asarray(rgba)[:, :3] * 255).astype(np.uint8)


def _limits(clouds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis ``(low, high)`` of the views: both clouds' points but the outer quantiles,
    padded by 5 %, the same span on every axis (views at one scale)."""
    both = np.concatenate(clouds)
    low = np.quantile(both, _VIEW_QUANTILE, axis=0)
    high = np.quantile(both, 1 - _VIEW_QUANTILE, axis=0)
    span = max(float(np.max(high - low)), 1e-9) * 1.05
    middle = (low + high) / 2
    return middle - span / 2, middle + span / 2


def _axis_label(axis: int, origin: np.ndarray, unit: str) -> str:
    name = "xyz"[axis]
    if origin[axis] == 0:
        return f"{name} ({unit})"
    return f"{name} - {origin[axis]:.0f} ({unit})"


def _draw(
    ax, points: np.ndarray, colors: np.ndarray, view: tuple, limits: tuple, labels: tuple
) -> None:
    """One orthographic view of ``points`` (already relative to the drawing origin)."""
    title, u, v = view
    low, high = limits
    ax.scatter(
        points[:, u],
        points[:, v],
        s=_MARKER_AREA,
        c=colors / 255.0,
        marker="s",
        linewidths=0,
        antialiased=False,
        rasterized=True,
    )
    ax.set_xlim(low[u], high[u])
    ax.set_ylim(low[v], high[v])
    ax.set_aspect("equal", adjustable="box")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(labels[u], fontsize=8)
    ax.set_ylabel(labels[v], fontsize=8)
    ax.tick_params(labelsize=7)


def _figure_png(
    src: np.ndarray,
    tgt: np.ndarray,
    res: np.ndarray,
    settings: QcSettings,
    origin: np.ndarray,
    subtitle: str,
) -> bytes:
    """The PNG's bytes: overlay row, residual row, colour bar; ``src`` and ``tgt`` are
    relative to the drawing origin ``origin``, ``res`` the residual of each ``src`` row."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    rng = np.random.default_rng(settings.seed)
    limits = _limits([src, tgt])
    labels = tuple(_axis_label(k, origin, settings.unit) for k in range(3))
    # overlay: both clouds in one shuffled order, so neither hides the other where they meet
    overlay = np.concatenate([tgt, src])
    overlay_colors = np.concatenate(
        [np.tile(TARGET_RGB, (len(tgt), 1)), np.tile(SOURCE_RGB, (len(src), 1))]
    ).astype(np.float64)
    order = rng.permutation(len(overlay))
    # residual views: the target in grey under the source, worst residuals drawn last
    worst_last = np.argsort(res, kind="stable")
    context = np.concatenate([tgt, src[worst_last]])
    context_colors = np.concatenate(
        [np.tile(CONTEXT_RGB, (len(tgt), 1)), _residual_colors(res[worst_last], settings.clip)]
    ).astype(np.float64)

    fig = Figure(figsize=(15, 10.5), dpi=100)
    axes = fig.subplots(2, 3)
    for k, view in enumerate(VIEWS):
        _draw(axes[0, k], overlay[order], overlay_colors[order], view, limits, labels)
        _draw(axes[1, k], context, context_colors, view, limits, labels)
    axes[0, 0].legend(
        handles=[
            _patch(TARGET_RGB, f"target ({len(tgt):,} points drawn)"),
            _patch(SOURCE_RGB, f"source moved by T ({len(src):,} points drawn)"),
        ],
        loc="upper left",
        fontsize=8,
    )
    mappable = ScalarMappable(norm=Normalize(0.0, settings.clip), cmap=RESIDUAL_CMAP)
    bar = fig.colorbar(mappable, ax=list(axes[1, :]), extend="max", fraction=0.03, pad=0.02)
    bar.set_label(f"moved source to nearest target point ({settings.unit})", fontsize=8)
    fig.suptitle(f"{settings.title}\n{subtitle}".strip(), fontsize=11)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return buffer.getvalue()


def _patch(rgb: tuple[int, int, int], label: str):
    from matplotlib.patches import Patch

    return Patch(color=np.asarray(rgb) / 255.0, label=label)


def _format_length(value: float, unit: str) -> str:
    return f"{value:.3g} {unit}"


def write_qc(
    folder: str | Path,
    name: str,
    points_src: np.ndarray,
    points_tgt: np.ndarray,
    T_tgt_src: np.ndarray,
    settings: QcSettings,
) -> QcResult:
    """Write ``folder/<name>_qc.png`` and ``folder/<name>_residual.ply`` of one registration
    (see the module docstring); the folder must exist.

    Args:
        folder: where the two files go.
        name: their common prefix (``<source-stem>__<target-stem>`` in the commands).
        points_src: ``(N, 3)`` the source as registered (input coordinates, float64).
        points_tgt: ``(M, 3)`` the target, in the coordinates ``T_tgt_src`` maps into.
        T_tgt_src: ``(4, 4)``, maps source points into the target frame (column vectors).
        settings: the residual clip, labels, sample sizes and seed.

    Returns:
        :class:`QcResult`: the files and the residual figures.

    Raises:
        ShapeError: clouds not finite ``(N, 3)`` with N >= 1, ``T_tgt_src`` not a finite
            4x4, a clip that is not positive and finite.
        InputError: a file cannot be written.
    """
    from byoc_cli.io.atomic import atomic_write_bytes
    from byoc_cli.io.ply import write_ply

    points_src = _points(points_src, "points_src")
    points_tgt = _points(points_tgt, "points_tgt")
    T = np.asarray(T_tgt_src, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ShapeError(f"T_tgt_src must be a finite (4, 4), got {T.shape}")
    if not (math.isfinite(settings.clip) and settings.clip > 0):
        raise ShapeError(f"clip must be positive and finite, got {settings.clip}")
    rng = np.random.default_rng(settings.seed)
    kept = _sample(len(points_src), settings.max_ply_points, rng)
    moved = points_src[kept] @ T[:3, :3].T + T[:3, 3]
    res = residuals(moved, points_tgt)
    median = float(np.median(res))
    within = float(np.mean(res < settings.clip))

    origin = _origin(points_tgt)
    drawn_src = _sample(len(moved), settings.max_draw_points, rng)
    drawn_tgt = _sample(len(points_tgt), settings.max_draw_points, rng)
    subtitle = (
        f"residual of the moved source: median {_format_length(median, settings.unit)}, "
        f"{100 * within:.1f} % of its points within {_format_length(settings.clip, settings.unit)}"
        f" of the target"
    )
    png_bytes = _figure_png(
        moved[drawn_src] - origin,
        points_tgt[drawn_tgt] - origin,
        res[drawn_src],
        settings,
        origin,
        subtitle,
    )
    png, ply = qc_paths(folder, name)
    atomic_write_bytes(png, png_bytes)
    write_ply(
        ply,
        moved,
        colors=_residual_colors(res, settings.clip),
        scalars={"residual": res.astype(np.float32)},
    )
    return QcResult(png, ply, settings.clip, median, within, len(points_src), len(points_tgt))

"""The geo and hostile variants of a pair of benchmarks/scan_sim.py: offsets of 1e3 .. 1e7 m, a
stray point far away, duplicated points, huge scales, float32 coordinates at a 1e9 m offset;
each keeps the pair's ground truth right.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from _scan_sim_geometry import Pair, apply, translation

GEO_OFFSETS = {
    "1e3": (1.0e3, 1.0e3, 0.0),
    "1e5": (1.0e5, 1.0e5, 0.0),
    "utm": (4.5e5, 5.2e6, 120.0),
    "1e6": (1.0e6, 1.0e6, 0.0),
    "1e7": (1.0e7, 1.0e7, 0.0),
}


def georeferenced(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, offset) -> Pair:
    """Both clouds ``(N, 3)``, ``(M, 3)`` shifted by ``offset (3,)`` and ``T (4, 4)``
    conjugated so that it still maps the shifted source onto the shifted target:
    ``T' = Tr(o) T Tr(-o)``."""
    o = np.asarray(offset, dtype=np.float64)
    T_new = translation(o) @ T @ translation(-o)
    return src + o, tgt + o, T_new


def scaled(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, factor: float) -> Pair:
    """Both clouds multiplied by ``factor``; ``T``'s translation too."""
    T_new = T.copy()
    T_new[:3, 3] *= factor
    return src * factor, tgt * factor, T_new


def with_stray_point(
    src: np.ndarray, tgt: np.ndarray, T: np.ndarray, distance: float, seed: int = 0
) -> Pair:
    """One point appended to each cloud, ``distance`` from its origin in a seeded direction
    (a different one per cloud); ``T`` stays right for the others. ``(N + 1, 3)``,
    ``(M + 1, 3)``."""
    rng = np.random.default_rng([seed, 5])
    ways = rng.standard_normal((2, 3))
    ways *= distance / np.linalg.norm(ways, axis=1, keepdims=True)
    return np.vstack([src, ways[:1]]), np.vstack([tgt, ways[1:]]), T


def with_duplicates(
    src: np.ndarray,
    tgt: np.ndarray,
    T: np.ndarray,
    distinct: int = 10,
    repeats: int = 2000,
    only: bool = False,
    seed: int = 0,
) -> Pair:
    """``distinct`` seeded points of each cloud, each repeated ``repeats`` times, appended to
    that cloud (``only``: the clouds are those repeats alone, the target's being the source's
    points mapped by ``T``, so that ``T`` is exact)."""
    rng = np.random.default_rng([seed, 6])
    pick_src = src[rng.choice(len(src), distinct, replace=False)]
    if only:
        return np.repeat(pick_src, repeats, axis=0), np.repeat(apply(T, pick_src), repeats, 0), T
    pick_tgt = tgt[rng.choice(len(tgt), distinct, replace=False)]
    return (
        np.vstack([src, np.repeat(pick_src, repeats, axis=0)]),
        np.vstack([tgt, np.repeat(pick_tgt, repeats, axis=0)]),
        T,
    )


class Variant(NamedTuple):
    """A named change of a pair: ``make(src, tgt, T) -> (src, tgt, T)``; ``dtype`` forces the
    PLY's coordinate type (None: the smallest exact one); ``voxel_factor`` scales the
    hand-set voxel."""

    make: object
    dtype: str | None = None
    voxel_factor: float = 1.0


def geo_variants() -> dict[str, Variant]:
    """``geo-<name>``: the pair moved to the offsets of ``GEO_OFFSETS``."""
    return {
        f"geo-{name}": Variant(lambda s, t, T, o=offset: georeferenced(s, t, T, o))
        for name, offset in GEO_OFFSETS.items()
    }


def hostile_variants() -> dict[str, Variant]:
    """The hostile inputs: stray points, duplicates, huge scales, float32 at 1e9 m."""
    return {
        "stray-1e6": Variant(lambda s, t, T: with_stray_point(s, t, T, 1e6)),
        "stray-1e30": Variant(lambda s, t, T: with_stray_point(s, t, T, 1e30)),
        "dup-added": Variant(lambda s, t, T: with_duplicates(s, t, T)),
        "dup-only": Variant(lambda s, t, T: with_duplicates(s, t, T, only=True)),
        "scale-1e30": Variant(lambda s, t, T: scaled(s, t, T, 1e30), voxel_factor=1e30),
        "scale-1e300": Variant(lambda s, t, T: scaled(s, t, T, 1e300), voxel_factor=1e300),
        "f32-1e9": Variant(lambda s, t, T: georeferenced(s, t, T, (1e9, 1e9, 0.0)), "f4"),
    }

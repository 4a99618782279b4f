"""The rough share of this tree and the noise-blind candidates measured for issue 33, per group.

Issue 33: noisy laser scans of smooth objects read rough
(docs/experiments/2026-11-27-noise-cue.md; the candidates were not adopted).

For each pair of the groups (the shared data's reference pairs of ``objects.py cues`` and the
pair folders given), at the pair's auto voxel, each cloud's share of rough neighbourhoods by:

* ``before``: the rough share as shipped: the surface variation of the 64 nearest kept points
  (the first point per voxel, within 8 voxels) above 0.01;
* ``var256``: the surface variation ``l3 / (l1 + l2 + l3)`` of the 256 nearest kept points
  (within 16 voxels: about twice the radius) above ``--threshold``;
* ``two-scale``: the growth of the smallest principal variance from the 64 to the 256 nearest
  kept points over the larger one's total, ``(l3(256) - l3(64)) / (l1 + l2 + l3)(256)``, above
  ``--threshold``: range noise adds the same variance at both sizes and cancels, an edge's
  grows with the square of the size and stays;
* ``two-scale-w``: the same on the voxels' centroids weighted by their point counts (a stray
  point alone in its voxel weighs 1, a surface voxel its several points);
* ``shipped``: :func:`byoc_cli.geometry.sampling.rough_share` of this tree.

Prints one line per pair and the range per group; ``--seconds FILE`` times the shipped cue;
``--depth-frames`` counts, over pairs of every posed sequence of ../shared/data at several
frame gaps, the pairs each cue would send to FPFH first (both clouds at most ``--smooth``:
0.125 for ``before``, the shipped rule; ``--smooth`` for the others).

Usage: python benchmarks/rough_cues.py [GROUP=DIR ...] [--no-reference] [--threshold 0.03]
       python benchmarks/rough_cues.py --seconds cloud.ply
       python benchmarks/rough_cues.py --depth-frames [--threshold 0.04] [--smooth 0.07]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

CUES = ("before", "var256", "two-scale", "two-scale-w", "shipped")
SAMPLES = 1024


def _grid(points: np.ndarray, voxel: float):
    """First point per voxel (indices), the voxels' centroids and counts."""
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    count = np.bincount(inverse).astype(np.float64)
    centre = np.stack([np.bincount(inverse, points[:, d]) for d in range(3)], 1) / count[:, None]
    return first, centre, count


def _variances(base, asked, weight, k, radius):
    """``(S, 3)`` ascending principal variances of the ``k`` nearest points of ``base`` within
    ``radius`` of each ``asked`` point, weighted by ``weight`` (None: 1); NaN below 6 points."""
    from pykdtree.kdtree import KDTree

    k = min(k, len(base))
    dist, idx = KDTree(base).query(asked, k=k, distance_upper_bound=radius)
    found = np.isfinite(dist.reshape(len(asked), k))
    idx = np.where(found, idx.reshape(len(asked), k), 0)
    w = found * (1.0 if weight is None else weight[idx])
    total = np.maximum(w.sum(axis=1), 1e-300)
    mean = np.einsum("sk,ski->si", w, base[idx]) / total[:, None]
    centred = base[idx] - mean[:, None]
    cov = np.einsum("sk,ski,skj->sij", w, centred, centred) / total[:, None, None]
    lam = np.clip(np.linalg.eigvalsh(cov), 0.0, None)
    lam[found.sum(axis=1) < 6] = np.nan
    return lam


def shares(points: np.ndarray, voxel: float, threshold: float) -> dict[str, float]:
    """Each cue of :data:`CUES` for ``points (N, 3)`` at ``voxel``."""
    from byoc_cli.geometry.sampling import rough_share

    out = {"shipped": rough_share(torch.from_numpy(points), voxel)}
    first, centre, count = _grid(points, voxel)
    kept = points[first]
    pick = torch.randperm(len(kept), generator=torch.Generator().manual_seed(0))[:SAMPLES]
    pick = pick.numpy()
    for name, base, weight in (("", kept, None), ("-w", centre, count)):
        small = _variances(base, base[pick], weight, 64, 8 * voxel)
        if not name:
            var64 = small[:, 0] / small.sum(axis=1)
            out["before"] = float(np.mean(var64[np.isfinite(var64)] > 0.01))
        large = _variances(base, base[pick], weight, 256, 16 * voxel)
        with np.errstate(invalid="ignore", divide="ignore"):
            grow = (large[:, 0] - small[:, 0]) / large.sum(axis=1)
            var = large[:, 0] / large.sum(axis=1)
        if not name:
            out["var256"] = float(np.mean(var[np.isfinite(var)] > threshold))
        out[f"two-scale{name}"] = float(np.mean(grow[np.isfinite(grow)] > threshold))
    return out


def _given(groups: list[str]):
    from byoc_cli.api import load_cloud

    for group in groups:
        label, _, folder = group.partition("=")
        for pair in sorted(Path(folder).glob("*/source.ply")):
            clouds = [load_cloud(pair.parent / f, scale=1.0) for f in ("source.ply", "target.ply")]
            yield label, pair.parent.name, *clouds


#: the sequences and frame gaps of ``--depth-frames``
DEPTH_FRAMES = (
    ("tum_fr1_desk_full", 20),
    ("tum_fr1_rpy", 40),
    ("tum_fr3_cabinet", 3),
    ("tum_fr1_xyz", 2),
    ("tum_fr1_desk", 2),
    ("realsense_tabletop", 8),
)


def depth_frames(threshold: float, smooth: float) -> None:
    """Per sequence of :data:`DEPTH_FRAMES`: the pairs, the least rough cloud per cue, and the
    pairs each cue would send to FPFH first."""
    from _init_pairs import RGBD
    from byoc_cli.evaluation.pairs import rgbd_pairs
    from byoc_cli.pipeline.scale import choose_voxel, measure

    print(f"pairs FPFH-first (both clouds at most {smooth}; before: 0.125), least rough cloud")
    for sequence, gap in DEPTH_FRAMES:
        pairs, _ = rgbd_pairs([RGBD / sequence], spacing=gap)
        first = dict.fromkeys(CUES, 0)
        least = dict.fromkeys(CUES, 1.0)
        for p in pairs:
            clouds = [np.ascontiguousarray(p.source.load()), np.ascontiguousarray(p.target.load())]
            scales = [measure(torch.from_numpy(c), n) for c, n in zip(clouds, "st", strict=True)]
            voxel = choose_voxel(tuple(scales), 0.025).voxel_size
            got = [shares(c, voxel, threshold) for c in clouds]
            for cue in CUES:
                bound = 0.125 if cue in ("before", "shipped") else smooth
                first[cue] += max(g[cue] for g in got) <= bound
                least[cue] = min(least[cue], *(g[cue] for g in got))
        cells = "  ".join(f"{c} {first[c]:2d} ({least[c]:.3f})" for c in CUES)
        print(f"  {sequence:20s} {len(pairs):3d} pairs  {cells}", flush=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", nargs="*", default=[], help="GROUP=DIR: pair folders of DIR")
    parser.add_argument("--no-reference", action="store_true", help="only the folders given")
    parser.add_argument("--threshold", type=float, default=0.03, help="per neighbourhood")
    parser.add_argument("--seconds", type=Path, help="time rough_share on this cloud (metres)")
    parser.add_argument("--depth-frames", action="store_true", help="the shared sequences")
    parser.add_argument("--smooth", type=float, default=0.07, help="--depth-frames' bound")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    if args.depth_frames:
        depth_frames(args.threshold, args.smooth)
        return
    from byoc_cli.api import load_cloud
    from byoc_cli.pipeline.scale import choose_voxel, measure
    from objects import _reference_pairs

    if args.seconds:
        from byoc_cli.geometry.sampling import rough_share

        points = load_cloud(args.seconds, scale=1.0)
        scale = measure(torch.from_numpy(points), "c")
        voxel = choose_voxel((scale, scale), 0.025).voxel_size
        for _ in range(3):
            wall, cpu = time.perf_counter(), time.process_time()
            rough_share(torch.from_numpy(points), voxel)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            print(f"{len(points)} points, rough_share: {wall:.3f} s ({cpu:.3f} s CPU)")
        return
    groups: dict[str, list[dict]] = {}
    sources = (
        _given(args.pairs) if args.no_reference else (*_reference_pairs(), *_given(args.pairs))
    )
    for group, name, src, tgt in sources:
        scales = [measure(torch.from_numpy(c), n) for c, n in ((src, "s"), (tgt, "t"))]
        voxel = choose_voxel(tuple(scales), 0.025).voxel_size
        got = [
            shares(np.ascontiguousarray(c, np.float64), voxel, args.threshold) for c in (src, tgt)
        ]
        groups.setdefault(group, []).extend(got)
        cells = "  ".join(f"{c} {got[0][c]:.3f} {got[1][c]:.3f}" for c in CUES)
        print(f"{group:12s} {name:32s} {cells}", flush=True)
    print(f"rough share per group (per neighbourhood above {args.threshold}; before: 0.01)")
    print(f"  {'group':12s} clouds  " + "  ".join(f"{c:>12s}" for c in CUES))
    for group, rows in groups.items():
        cells = "  ".join(
            f"{min(r[c] for r in rows):.2f}..{max(r[c] for r in rows):.2f}" for c in CUES
        )
        print(f"  {group:12s} {len(rows):5d}   {cells}")


if __name__ == "__main__":
    main()

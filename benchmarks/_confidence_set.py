"""The development set of the confidence gate (benchmarks/confidence.py), made at run time from
../shared/data: posed RGB-D pairs, the 3DMatch sample's fragment pairs, scaled / thinned / noisy
copies, and pairs with no right answer; each pair as ``(name, group, load_source, load_target,
T_gt, scale)``.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from any_scan import make  # the same copies as any_scan.py

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
RGBD = DATA / "rgbd"
SAMPLE = DATA / "3dmatch" / "sample"
BENCH = DATA / "3dmatch" / "benchmarks"
#: (sequence, frame distances)
RGBD_SETS = (
    ("tum_fr1_desk_full", (10, 20, 30, 40, 50, 60)),
    ("tum_fr3_cabinet", (1, 2, 4, 8)),
    ("realsense_tabletop", (5, 15, 25, 35)),
    ("tum_fr1_rpy", (20, 60)),
    ("tum_fr1_desk", (2, 4, 8)),
)


def rgbd_pairs() -> Iterator[tuple[str, str, object, object, np.ndarray | None, float]]:
    """``(name, group, load_source, load_target, T_gt, scale)`` of the posed sequences."""
    from byoc_cli.evaluation.pairs import rgbd_pairs as make

    for sequence, spacings in RGBD_SETS:
        for spacing in spacings:
            pairs, _ = make([RGBD / sequence], spacing=spacing)
            for p in pairs:
                yield f"{p.name}@{spacing}", sequence, p.source.load, p.target.load, p.T_gt, 1.0


def _fragment(k: int) -> np.ndarray:
    from byoc_cli.api import load_cloud

    return load_cloud(SAMPLE / "3DMatch" / "7-scenes-redkitchen" / f"cloud_bin_{k}.ply")


def fragment_pairs() -> Iterator[tuple]:
    """Every pair of the sample's five fragments: ground truth, or none (< 10 % overlap)."""
    from byoc_cli.io.threedmatch import read_gt_log

    truth = {}
    for bench in ("3DMatch", "3DLoMatch"):
        for rec in read_gt_log(BENCH / bench / "7-scenes-redkitchen" / "gt.log"):
            truth[(rec.i, rec.j)] = rec.T_tgt_src
    frags = (0, 4, 7, 21, 34)
    for a in range(len(frags)):
        for b in range(a + 1, len(frags)):
            i, j = frags[a], frags[b]
            T = truth.get((i, j))
            yield (
                f"kitchen:{i}-{j}",
                "kitchen",
                lambda j=j: _fragment(j),
                lambda i=i: _fragment(i),
                T,
                1.0,
            )


def variant_pairs() -> Iterator[tuple]:
    """Scaled, thinned and noisy copies of the demo pair and the 3DMatch sample pairs."""
    from byoc_cli.api import load_cloud

    demo = DATA / "pairs" / "3dmatch_demo"
    bases = [
        (
            "demo",
            lambda: load_cloud(demo / "source.ply"),
            lambda: load_cloud(demo / "target.ply"),
            np.loadtxt(demo / "T_gt.txt"),
        )
    ]
    for name, _, src, tgt, T, _ in fragment_pairs():
        if T is not None and name in ("kitchen:0-4", "kitchen:4-7", "kitchen:7-21"):
            bases.append((name, src, tgt, T))
    recipes = [(f"x{s:g}", {"scale": s}) for s in (0.01, 0.1, 10.0, 100.0)]
    recipes += [("thin8both", {"thin": 8, "both": True})]
    for k in (2, 4):
        recipes += [(f"thin{k}both", {"thin": k, "both": True})]
        recipes += [(f"thin{k}src", {"thin": k, "both": False})]
    recipes += [("noise0.25", {"noise": 0.25}), ("noise0.5", {"noise": 0.5})]
    for n, (name, src, tgt, T) in enumerate(bases):
        for label, recipe in recipes:

            def load(which, src=src, tgt=tgt, recipe=recipe, seed=n):
                return make(src(), tgt(), recipe, seed)[which]

            s = recipe.get("scale", 1.0)
            yield (
                f"{name}~{label}",
                "variants",
                lambda load=load: load(0),
                lambda load=load: load(1),
                T,
                s,
            )


def negative_pairs() -> Iterator[tuple]:
    """Pairs with no right answer: noise, planes, two different rooms."""
    from byoc_cli.evaluation.pairs import rgbd_pairs as make

    rng = np.random.default_rng(7)

    def noise(n=20000, size=3.0):
        return rng.uniform(0, size, (n, 3))

    def plane(n=20000, size=3.0):
        xy = rng.uniform(0, size, (n, 2))
        return np.column_stack([xy, 0.002 * rng.standard_normal(n)])

    frag = lambda: _fragment(0)  # noqa: E731
    for k in range(3):
        yield f"noise-onto-cloud:{k}", "negative", noise, frag, None, 1.0
        yield f"noise-onto-noise:{k}", "negative", noise, noise, None, 1.0
        yield f"plane-onto-plane:{k}", "negative", plane, plane, None, 1.0
        yield f"cloud-onto-noise:{k}", "negative", frag, noise, None, 1.0
    desk, _ = make([RGBD / "tum_fr1_desk_full"], spacing=30)
    cabinet, _ = make([RGBD / "tum_fr3_cabinet"], spacing=6)
    tabletop, _ = make([RGBD / "realsense_tabletop"], spacing=10)
    for n, (a, b) in enumerate(zip(desk, cabinet, strict=False)):
        yield f"desk-onto-cabinet:{n}", "negative", a.source.load, b.target.load, None, 1.0
    for n, (a, b) in enumerate(zip(tabletop, cabinet, strict=False)):
        yield f"tabletop-onto-cabinet:{n}", "negative", a.source.load, b.target.load, None, 1.0


def part_of_set(part: tuple[int, int]) -> Iterator[tuple]:
    """The pairs of the set (:func:`rgbd_pairs` and the rest, in order) of part ``(I, N)``:
    every N-th from the I-th."""
    sources = (rgbd_pairs(), fragment_pairs(), variant_pairs(), negative_pairs())
    for count, pair in enumerate(p for source in sources for p in source):
        if count % part[1] == part[0] - 1:
            yield pair

"""`init.py sweep`: how far off a guess may be, the measurement behind the default trust region
(`--max-correction`, :data:`byoc_cli.pipeline.local.MAX_CORRECTION_DEG` and
``MAX_CORRECTION_VOXELS``).

On the benchmark's pairs whose truth the data determine and whose clouds overlap (the
refinement of the ground truth meets at least MIN_FITNESS of the source), one guess per pair
and setting: rotations of SWEEP_DEG about the source's centroid with --near-m of translation,
and translations of SWEEP_M with --near-deg of rotation. Prints, per setting, the local
registrations right (within 5 deg and 10 cm of the refined truth), and the largest correction
(rotation, translation of the centroid) among the right ones.
"""

from __future__ import annotations

import warnings

import numpy as np

from _init_pairs import errors, perturbed, refined_truth, rgbd_pairs

SWEEP_DEG = (5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 40.0)
SWEEP_M = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8)
#: a pair enters the sweep when the refinement of its truth meets this share of the source
MIN_FITNESS = 0.15


def sweep(args) -> None:
    import torch

    from byoc_cli.api import Registrar
    from byoc_cli.pipeline.refine import refine_multiscale

    registrar = Registrar(device="cpu")
    rng = np.random.default_rng(args.seed)
    settings = [(d, args.near_m) for d in SWEEP_DEG] + [(args.near_deg, m) for m in SWEEP_M]
    rows = {s: [] for s in settings}
    used = 0
    for pair in rgbd_pairs(limit=args.pairs):
        src, tgt = pair.load_source(), pair.load_target()
        voxel = registrar.choose_voxel(src, tgt).refine_voxel
        truth, determined = refined_truth(src, tgt, pair.T_gt, voxel)
        fit = refine_multiscale(
            torch.from_numpy(src), torch.from_numpy(tgt), torch.from_numpy(truth), voxel
        ).fitness
        if not determined or fit < MIN_FITNESS:
            continue
        used += 1
        for deg, length in settings:
            guess = perturbed(pair.T_gt, src.mean(axis=0), deg, length, rng)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                result = registrar.register(src, tgt, init=guess)
            rot, trans = errors(result.T_tgt_src, truth)
            moved = result.init["correction"]
            rows[(deg, length)].append((rot < 5 and trans < 0.10, moved, result.passed))
    print(f"{used} pairs (determined truth, refined fitness >= {MIN_FITNESS:g})")
    print("| guess off by | right | passed | wrong and passed | largest right correction |")
    print("|---|---|---|---|---|")
    for (deg, length), cells in rows.items():
        right = [c for c in cells if c[0]]
        top = max((c[1]["rotation_deg"] for c in right), default=0.0)
        far = max((c[1]["translation"] for c in right), default=0.0)
        passed = sum(c[2] for c in cells)
        wrong = sum(c[2] and not c[0] for c in cells)
        print(
            f"| {deg:g} deg, {100 * length:g} cm | {len(right)}/{len(cells)} | {passed} | "
            f"{wrong} | {top:.1f} deg, {100 * far:.0f} cm |"
        )

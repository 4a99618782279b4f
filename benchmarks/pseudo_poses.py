"""Accuracy of the self-posed training pairs against ground truth, per baseline.

Usage::

    python benchmarks/pseudo_poses.py --rgbd-dir ../shared/data/rgbd/tum_fr1_desk_full \
        [--rgbd-dir ...] [--gaps 5 10 20] [--start-stride 2] [--weights W.safetensors]
        [--from-run runs/sp1 [--round 2]] [--json out.json]

For each posed sequence the pairs are estimated exactly as ``byoc train --variant
self-posed`` does (no pose read; with ``--weights``, as its later rounds do: that encoder is
the global registration), or read from a run folder's cache with ``--from-run`` (round 1:
``pseudo_pairs/``, ``--round R``: ``pseudo_pairs/round-R/``; matched by sequence folder),
then compared with the ground truth: per gap
(frames apart), the pairs tried and kept, the kept share, the median rotation and
translation error of the kept pairs, and the share within 2 deg / 5 cm. The ground-truth
motion of the kept pairs (median) says how wide the baselines are.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def _from_run(run: Path, round_number: int, sequence) -> dict | None:
    from byoc_cli.training.self_posed import pairs_folder

    for path in sorted(pairs_folder(run, round_number).glob("*.json")):
        record = json.loads(path.read_text())
        if Path(record["sequence"]).resolve() == Path(sequence.root).resolve():
            return record
    return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rgbd-dir", type=Path, action="append", required=True)
    parser.add_argument("--gaps", type=int, nargs="+", default=None)
    parser.add_argument("--start-stride", type=int, default=None)
    parser.add_argument("--from-run", type=Path, default=None)
    parser.add_argument("--round", type=int, default=1)
    parser.add_argument("--weights", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from byoc_cli.io.rgbd import discover_sequences
    from byoc_cli.training.pseudo_poses import (
        LearnedStart,
        PseudoPoseConfig,
        SequencePairs,
        estimate_pairs,
        pair_accuracy,
        pairs_from_json,
        rotation_angle_deg,
    )

    overrides = {}
    if args.gaps:
        overrides["gaps"] = tuple(args.gaps)
    if args.start_stride:
        overrides["start_stride"] = args.start_stride
    loaded, voxel = None, None
    if args.weights:
        from byoc_cli.pipeline.weights import load_weights

        loaded = load_weights(args.weights)
        voxel = float(loaded.metadata.get("voxel_size", PseudoPoseConfig().voxel_size))
    report = {}
    header = (
        f"{'sequence':22s} {'gap':>4s} {'tried':>6s} {'kept':>5s} {'share':>6s} "
        f"{'motion deg/cm':>14s} {'rot err':>8s} {'trans err':>9s} {'<2deg':>6s} {'<5cm':>6s}"
    )
    print(header)
    for root in args.rgbd_dir:
        # all frames (as training lists them); frames without a pose are skipped in the table
        for sequence in discover_sequences(root):
            record = _from_run(args.from_run, args.round, sequence) if args.from_run else None
            t0 = time.perf_counter()
            if record is not None:
                config = PseudoPoseConfig(
                    **{k: v for k, v in record["config"].items() if k != "gaps"},
                    gaps=tuple(record["config"]["gaps"]),
                )
                result = SequencePairs(
                    record["frames"],
                    [],
                    record["segments"],
                    pairs_from_json(record),
                    {int(k): v for k, v in record["candidates"].items()},
                    {int(k): v for k, v in record["kept"].items()},
                    record["stats"],
                )
            else:
                config = PseudoPoseConfig(**overrides)
                # the estimate sees a copy without poses, as training does
                blind = discover_sequences(sequence.root, read_poses=False)[0]
                # a fresh start per sequence: its feature cache is keyed by frame position
                start = LearnedStart(loaded.encoder, voxel, config.seed) if loaded else None
                result = estimate_pairs(blind, config, global_start=start)
            seconds = time.perf_counter() - t0
            gt = [sequence.pose(i) for i in range(len(sequence.frames))]
            table = pair_accuracy(result, gt, config)
            position = {f: n for n, f in enumerate(result.frames)}
            motion: dict[int, list[tuple[float, float]]] = {g: [] for g in config.gaps}
            for pair in result.pairs:
                if gt[pair.i] is None or gt[pair.j] is None:
                    continue
                T = np.linalg.inv(gt[pair.i]) @ gt[pair.j]
                gap = position[pair.j] - position[pair.i]
                motion[gap].append((rotation_angle_deg(T[:3, :3]), np.linalg.norm(T[:3, 3])))
            for gap, row in table.items():
                m = np.asarray(motion[gap]).reshape(-1, 2)
                row["motion_median_deg"] = float(np.median(m[:, 0])) if len(m) else float("nan")
                row["motion_median_cm"] = (
                    float(np.median(m[:, 1]) * 100) if len(m) else float("nan")
                )
                print(
                    f"{sequence.name:22s} {gap:4d} {row['candidates']:6d} {row['kept']:5d} "
                    f"{100 * row['kept_share']:5.1f}% "
                    f"{row['motion_median_deg']:6.1f}/{row['motion_median_cm']:6.1f} "
                    f"{row['median_rotation_deg']:7.2f}d {row['median_translation_cm']:7.2f}cm "
                    f"{100 * row['rotation_acc_2deg']:5.1f}% "
                    f"{100 * row['translation_acc_5cm']:5.1f}%",
                    flush=True,
                )
            report[sequence.name] = {
                "seconds": seconds,
                "stats": result.stats,
                "gaps": {str(g): r for g, r in table.items()},
            }
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Training throughput: steps/s and pairs/s per variant and encoder, side by side.

Usage::

    python benchmarks/train.py [--rgbd-dir ../shared/data/rgbd/tum_fr1_rpy] [--steps 3]
        [--device auto] [--arch compact --arch minkunet34c]
        [--variant byoc-geo --variant byoc --variant self-posed] [--self-posed-batch 8]

The paper's variants: batches are read once up front (data loading is measured separately,
per sample), so the figure is the model's forward + backward + Adam step. ``self-posed``:
the frames of the same pairs (the same sequence, ``view_spacing`` 20) are cached once as
training does, and the timed step includes everything training does per step from the
cache (augmentation, voxelisation, correspondences, forward, backward, Adam). Its
correspondences use the sequence's ground-truth poses here (throughput only: training uses
self-posed pairs). The ratio column is pairs/s over the first row's (byoc-geo, compact).
On CUDA the peak GPU memory is printed too.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "rgbd" / "tum_fr1_rpy"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rgbd-dir", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--steps", type=int, default=3, help="timed steps per configuration")
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    parser.add_argument("--arch", action="append", default=None)
    parser.add_argument("--variant", action="append", default=None)
    parser.add_argument("--amp", action=argparse.BooleanOptionalAction, default=None)
    parser.add_argument("--self-posed-batch", type=int, default=8)
    parser.add_argument(
        "--self-posed-options",
        action="append",
        default=None,
        help="extra self-posed rows: comma-separated key=value TrainConfig overrides, "
        "e.g. 'amp=true,crop_radius=0.6' (repeat for several rows)",
    )
    args = parser.parse_args()

    from byoc_cli.io.rgbd import discover_sequences
    from byoc_cli.training.config import TrainConfig
    from byoc_cli.training.data import PairDataset
    from byoc_cli.training.distributed import resolve_device
    from byoc_cli.training.loop import build_optimizer
    from byoc_cli.training.paper import build_model, mixed_precision

    device = resolve_device(args.device)
    archs = args.arch or ["compact", "minkunet34c"]
    variants = args.variant or ["byoc-geo", "byoc"]
    seqs = discover_sequences(args.rgbd_dir, require_color=True)
    dataset = PairDataset(seqs, 20, "train", use_color=True)
    n = args.batch_size * (args.steps + args.warmup)
    gen = torch.Generator().manual_seed(0)
    order = torch.randperm(len(dataset), generator=gen)[:n].tolist()
    t0 = time.perf_counter()
    samples = [dataset[i] for i in order]
    load_s = (time.perf_counter() - t0) / len(samples)
    batches = [samples[k : k + args.batch_size] for k in range(0, n, args.batch_size)]
    kept = sum(s.view0.point_index.numel() + s.view1.point_index.numel() for s in samples)
    print(
        f"device {device}, torch threads {torch.get_num_threads()}, batch {args.batch_size}, "
        f"{kept / (2 * len(samples)):.0f} kept points per view; data loading "
        f"{load_s * 1000:.0f} ms per pair (one process)",
        flush=True,
    )
    print(
        f"{'variant':10s} {'arch':12s} {'batch':>5s} {'steps/s':>8s} {'s/step':>8s} "
        f"{'pairs/s':>8s} {'ratio':>6s} {'peak GPU MiB':>13s}"
    )
    reference = None
    for arch in archs:
        for variant in variants:
            if variant == "self-posed":
                for extra in [""] + (args.self_posed_options or []):
                    per, batch = _self_posed(args, arch, samples, seqs, order, device, extra)
                    rate = batch / per
                    reference = reference or rate
                    label = f"{variant} {extra}".strip()
                    print(
                        f"{label:10s} {arch:12s} {batch:5d} {1 / per:8.3f} {per:8.2f} "
                        f"{rate:8.2f} {rate / reference:6.2f} {'-':>13s}",
                        flush=True,
                    )
                continue
            config = TrainConfig(
                variant=variant, arch=arch, batch_size=args.batch_size, amp=args.amp
            )
            model = build_model(config, 0, mixed_precision(config, device)).to(device).train()
            opt = build_optimizer(model, config)
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
            times = []
            for k, batch in enumerate(batches):
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                t = time.perf_counter()
                terms = model(batch)
                opt.zero_grad(set_to_none=True)
                terms.total.backward()
                opt.step()
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                if k >= args.warmup:
                    times.append(time.perf_counter() - t)
            per = sum(times) / len(times)
            peak = (
                f"{torch.cuda.max_memory_allocated(device) / 2**20:13.0f}"
                if device.type == "cuda"
                else f"{'-':>13s}"
            )
            rate = args.batch_size / per
            reference = reference or rate
            print(
                f"{variant:10s} {arch:12s} {args.batch_size:5d} {1 / per:8.3f} {per:8.2f} "
                f"{rate:8.2f} {rate / reference:6.2f} {peak}",
                flush=True,
            )
            del model, opt


def _overrides(text: str) -> dict:
    out = {}
    for item in filter(None, text.split(",")):
        key, value = item.split("=")
        out[key] = {"true": True, "false": False}.get(value, None)
        if out[key] is None:
            out[key] = float(value)
    return out


def _self_posed(args, arch, samples, seqs, order, device, extra=""):
    """Median seconds per self-posed step over the same pairs; returns (s/step, batch)."""
    import numpy as np

    from byoc_cli.models.encoder import build_encoder
    from byoc_cli.training.config import TrainConfig
    from byoc_cli.training.loop import build_optimizer
    from byoc_cli.training.pseudo_poses import frame_points
    from byoc_cli.training.self_posed import CACHE_VOXEL_FACTOR, training_step
    from byoc_cli.training.self_posed_data import cache_frame

    del samples
    batch_size = args.self_posed_batch
    config = TrainConfig(
        variant="self-posed", arch=arch, batch_size=batch_size, **_overrides(extra)
    )
    seq = seqs[0]
    posed = {i for i in range(len(seq.frames)) if seq.pose(i) is not None}
    starts = [i for i in order if i in posed and i + 20 in posed]
    steps = args.steps + args.warmup
    starts = (starts * (1 + batch_size * steps // max(len(starts), 1)))[: batch_size * steps]
    frames = {}
    for i in sorted({f for s in starts for f in (s, s + 20)}):
        frames[i] = cache_frame(frame_points(seq, i), CACHE_VOXEL_FACTOR * config.voxel_size)
    poses = {i: seq.pose(i) for i in frames}
    encoder = build_encoder(arch).to(device).train()
    opt = build_optimizer(encoder, config, fused=True)
    gen = torch.Generator().manual_seed(0)
    times = []
    for k in range(steps):
        batch = []
        for s in starts[k * batch_size : (k + 1) * batch_size]:
            T = torch.from_numpy(np.linalg.inv(poses[s]) @ poses[s + 20])
            batch.append((frames[s], frames[s + 20], T))
        t = time.perf_counter()
        loss, _ = training_step(encoder, batch, config, gen)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if k >= args.warmup:
            times.append(time.perf_counter() - t)
    return float(np.median(times)), batch_size


if __name__ == "__main__":
    sys.exit(main())

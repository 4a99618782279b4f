"""Training throughput: steps/s at batch 8 for byoc-geo and byoc with each encoder.

Usage::

    python benchmarks/train.py [--rgbd-dir ../shared/data/rgbd/tum_fr1_rpy] [--steps 3]
        [--device auto] [--arch compact --arch minkunet34c] [--variant byoc-geo --variant byoc]

Batches are read once up front (data loading is measured separately, per sample), so the
figure is the model's forward + backward + Adam step. On CUDA the peak GPU memory is
printed too.
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
    args = parser.parse_args()

    from byoc_cli.io.rgbd import discover_sequences
    from byoc_cli.training.config import TrainConfig
    from byoc_cli.training.data import PairDataset
    from byoc_cli.training.distributed import resolve_device
    from byoc_cli.training.trainer import _amp_dtype, build_model, build_optimizer

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
    print(f"{'variant':10s} {'arch':12s} {'steps/s':>8s} {'s/step':>8s} {'peak GPU MiB':>13s}")
    for arch in archs:
        for variant in variants:
            config = TrainConfig(
                variant=variant, arch=arch, batch_size=args.batch_size, amp=args.amp
            )
            model = build_model(config, 0, _amp_dtype(config, device)).to(device).train()
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
            print(f"{variant:10s} {arch:12s} {1 / per:8.3f} {per:8.2f} {peak}", flush=True)
            del model, opt


if __name__ == "__main__":
    sys.exit(main())

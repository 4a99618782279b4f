"""torchrun with two CPU processes (gloo): one set of checkpoints, weights written (slow)."""

import json
import os
import subprocess
import sys

import pytest

from byoc_cli.pipeline.weights import load_weights


@pytest.mark.slow
def test_torchrun_two_cpu_processes(shared_data, tmp_path):
    run = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc-per-node",
        "2",
        "--master-port",
        "29517",
        "-m",
        "byoc_cli.cli.main",
        "train",
        "--rgbd-dir",
        str(shared_data / "rgbd" / "tum_fr1_xyz"),
        "--variant",
        "byoc-geo",
        "--steps",
        "3",
        "--batch-size",
        "2",
        "--view-spacing",
        "2",
        "--checkpoint-every",
        "2",
        "--val-every",
        "0",
        "--num-workers",
        "0",
        "--device",
        "cpu",
        "--log-every",
        "1",
        "--out",
        str(run),
        "--quiet",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    ckpts = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert ckpts == ["step-00000002.pt", "step-00000003.pt"]
    assert json.loads((run / "config.json").read_text())["world_size"] == 2
    steps = [json.loads(x)["step"] for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3]  # rank 0 only writes
    loaded = load_weights(run / "weights.safetensors")
    assert loaded.metadata["training"]["steps"] == 3
    assert proc.stdout.count("weights.safetensors") == 1

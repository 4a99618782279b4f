"""Exact resume: in-process checkpoint round trip, and SIGKILL of a real CLI run (slow)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from byoc_cli.training.checkpoint import (
    capture_rng_state,
    list_checkpoints,
    load_latest_checkpoint,
    restore_rng_state,
)
from byoc_cli.training.config import TrainConfig
from byoc_cli.training.trainer import resume_config, train


def _tensors(path):
    return load_file(str(path))


def _assert_identical(a, b):
    ta, tb = _tensors(a), _tensors(b)
    assert ta.keys() == tb.keys()
    for name in ta:
        assert torch.equal(ta[name], tb[name]), name


def test_rng_state_round_trip():
    import random

    import numpy as np

    g = torch.Generator().manual_seed(5)
    state = capture_rng_state({"g": g})
    a = (torch.rand(3), random.random(), np.random.rand(), torch.rand(2, generator=g))  # noqa: NPY002
    restore_rng_state(state, {"g": g})
    b = (torch.rand(3), random.random(), np.random.rand(), torch.rand(2, generator=g))  # noqa: NPY002
    assert torch.equal(a[0], b[0]) and a[1] == b[1] and a[2] == b[2] and torch.equal(a[3], b[3])


def _tiny(shared_data, out, **kw):
    values = dict(
        rgbd_dir=(str(shared_data / "rgbd" / "tum_fr1_xyz"),),
        out=str(out),
        variant="byoc-geo",
        steps=4,
        batch_size=2,
        view_spacing=2,
        checkpoint_every=2,
        val_every=0,
        log_every=1,
        num_workers=0,
        device="cpu",
    )
    values.update(kw)
    return TrainConfig(**values)


def test_checkpoint_round_trip_in_process(shared_data, tmp_path):
    full = train(_tiny(shared_data, tmp_path / "a"))
    assert full.steps == 4
    train(_tiny(shared_data, tmp_path / "b", steps=2))
    state, path = load_latest_checkpoint(tmp_path / "b")
    assert state["step"] == 2 and path.name == "step-00000002.pt"
    resumed = train(resume_config(tmp_path / "b", {"steps": 4}), resume=True)
    assert resumed.steps == 4
    _assert_identical(full.weights_path, resumed.weights_path)
    # the metrics of the resumed run are those of the uninterrupted one
    la = [r["loss"] for r in _records(tmp_path / "a")]
    lb = [r["loss"] for r in _records(tmp_path / "b")]
    assert la == lb
    assert [s for s, _ in list_checkpoints(tmp_path / "b")] == [2, 4]


def _records(run):
    import json

    return [
        json.loads(x)
        for x in (Path(run) / "metrics.jsonl").read_text().splitlines()
        if json.loads(x)["kind"] == "train"
    ]


def test_resume_refuses_fixed_keys(shared_data, tmp_path):
    train(_tiny(shared_data, tmp_path / "r", steps=2, checkpoint_every=0))
    with pytest.raises(ValueError, match="cannot change 'lr'"):
        resume_config(tmp_path / "r", {"lr": 0.5})


def _cli(args, env):
    return subprocess.Popen(
        [sys.executable, "-m", "byoc_cli.cli.main", "train", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )


@pytest.mark.slow
def test_sigkill_then_resume_is_bit_identical(shared_data, tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    args = [
        "--rgbd-dir",
        str(shared_data / "rgbd" / "tum_fr1_desk"),
        "--variant",
        "byoc-rot",
        "--steps",
        "4",
        "--batch-size",
        "2",
        "--view-spacing",
        "2",
        "--checkpoint-every",
        "2",
        "--val-every",
        "0",
        "--num-workers",
        "1",
        "--device",
        "cpu",
        "--quiet",
    ]
    ref = _cli([*args, "--out", str(tmp_path / "ref")], env)
    _out, err = ref.communicate(timeout=600)
    assert ref.returncode == 0, err.decode()

    run = tmp_path / "killed"
    proc = _cli([*args, "--out", str(run)], env)
    deadline = time.time() + 600
    while not (run / "checkpoints" / "step-00000002.pt").exists():
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.time() < deadline
        time.sleep(0.05)
    time.sleep(0.3)  # somewhere inside step 3
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not (run / "weights.safetensors").exists()

    resumed = _cli(["--resume", str(run), "--quiet"], env)
    _out, err = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, err.decode()
    _assert_identical(tmp_path / "ref" / "weights.safetensors", run / "weights.safetensors")
    steps = [r["step"] for r in _records(run)]
    assert steps == sorted(set(steps)) and steps[-1] == 4

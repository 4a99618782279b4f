"""The shipped weights: the headline command with no flags, weights info, eval, checksum."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli
from byoc_cli.io import read_transform
from byoc_cli.pipeline import default_weights

pytestmark = pytest.mark.skipif(
    default_weights.default_weights_path() is None, reason="this checkout ships no weights"
)


@pytest.fixture
def runner():
    return CliRunner()


def _rotation_error_deg(R, R_gt):
    cos = (np.trace(R @ R_gt.T) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


@pytest.mark.realdata
def test_headline_command_registers_the_demo_pair_with_no_flags(runner, shared_data, tmp_path):
    demo = shared_data / "pairs" / "3dmatch_demo"
    out = tmp_path / "T.txt"
    report = tmp_path / "r.json"
    res = runner.invoke(
        cli,
        ["register", str(demo / "source.ply"), str(demo / "target.ply"), "-o", str(out),
         "--json", str(report)],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    T, T_gt = read_transform(out), read_transform(demo / "T_gt.txt")
    assert _rotation_error_deg(T[:3, :3], T_gt[:3, :3]) < 5.0
    assert np.linalg.norm(T[:3, 3] - T_gt[:3, 3]) < 0.10
    r = json.loads(report.read_text())
    assert r["features"] == "byoc" and r["weights"]["path"].endswith("default.safetensors")
    assert r["weights_sha256"] == default_weights.verify_default_weights()


def test_weights_info_without_a_file_describes_the_shipped_weights(runner):
    res = runner.invoke(cli, ["weights", "info"])
    assert res.exit_code == 0, res.output
    meta = json.loads(res.stdout)
    assert meta["shipped"] is True and meta["training"]["variant"] == "self-posed"
    for key in ("data", "steps", "metrics", "recipe"):
        assert meta["training"][key]
    assert meta["file_sha256"] == default_weights.verify_default_weights()


def test_shipped_weights_are_small_and_float16():
    from safetensors.torch import load_file

    path = default_weights.default_weights_path()
    assert path.stat().st_size <= 20 * 2**20
    tensors = load_file(str(path))
    assert {t.dtype for t in tensors.values() if t.is_floating_point()} == {
        __import__("torch").float16
    }


def test_a_damaged_install_is_refused(runner, tmp_path, monkeypatch):
    bad = tmp_path / "default.sha256"
    bad.write_text("0" * 64 + "\n")
    monkeypatch.setattr(default_weights, "DEFAULT_CHECKSUM", bad)
    res = runner.invoke(cli, ["weights", "info"])
    assert res.exit_code == 1 and "checksum" in res.stderr


@pytest.mark.realdata
def test_without_shipped_weights_byoc_needs_weights(runner, shared_data, tmp_path, monkeypatch):
    monkeypatch.setattr(default_weights, "DEFAULT_WEIGHTS", tmp_path / "none.safetensors")
    src = tmp_path / "a.npy"
    np.save(src, np.random.default_rng(0).uniform(0, 1, (500, 3)))
    res = runner.invoke(cli, ["register", str(src), str(src), "-o", "-"])
    assert res.exit_code == 2 and "--weights" in res.stderr
    res = runner.invoke(cli, ["weights", "info"])
    assert res.exit_code == 2 and "ships no trained weights" in res.stderr
    seq = shared_data / "rgbd" / "tum_fr1_desk"
    res = runner.invoke(
        cli, ["eval-pairs", "--rgbd-dir", str(seq), "--spacing", "2", "--method", "byoc"]
    )
    assert res.exit_code == 2 and "byoc-random" in res.stderr


def test_the_package_data_installs_the_weights_and_their_checksum():
    import tomllib
    from pathlib import Path

    pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
    data = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["package-data"]["byoc_cli"]
    root = Path(default_weights.__file__).resolve().parents[1]
    for path in (default_weights.DEFAULT_WEIGHTS, default_weights.DEFAULT_CHECKSUM):
        assert str(path.relative_to(root)) in data

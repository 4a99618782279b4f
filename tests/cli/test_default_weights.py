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


def test_weights_info_json_describes_the_shipped_weights(runner):
    res = runner.invoke(cli, ["weights", "info", "--json"])
    assert res.exit_code == 0, res.output
    meta = json.loads(res.stdout)
    assert meta["shipped"] is True and meta["training"]["variant"] == "self-posed"
    for key in ("data", "steps", "metrics", "recipe", "validation_data", "held_out"):
        assert meta["training"][key]
    assert meta["file_sha256"] == default_weights.verify_default_weights()
    assert res.stderr == ""


def test_weights_info_prints_a_summary_on_stderr(runner):
    res = runner.invoke(cli, ["weights", "info"])
    assert res.exit_code == 0, res.output
    assert res.stdout == ""
    meta = json.loads(runner.invoke(cli, ["weights", "info", "--json"]).stdout)
    lines = {line[:12].strip(): line[12:] for line in res.stderr.splitlines() if line[:1] != " "}
    assert f"{meta['num_parameters']:,} parameters" in lines["model"]
    assert lines["training"].startswith(f"self-posed, {meta['training']['steps']} steps")
    assert lines["data"] == ", ".join(meta["training"]["data"])
    assert lines["validation"].startswith("tum_fr3_cabinet, spacing 2: fmr 1, inlier_ratio")
    assert "lr 0.0001" in lines["recipe"] and "crop_radius 0.6" in lines["recipe"]
    assert "tum_fr3_cabinet, spacing 2: rot_acc_5 64.3, trans_acc_10 53.6" in res.stderr
    assert lines["sha256"].startswith(default_weights.verify_default_weights() + " (file)")
    assert runner.invoke(cli, ["weights", "info", "-q"]).stderr == res.stderr  # -q: no logs


def _strings(metadata) -> list[str]:
    """Every string in a JSON value (keys too)."""
    if isinstance(metadata, dict):
        return [s for k, v in metadata.items() for s in [k, *_strings(v)]]
    if isinstance(metadata, list):
        return [s for v in metadata for s in _strings(v)]
    return [metadata] if isinstance(metadata, str) else []


def test_the_shipped_file_names_datasets_not_folders():
    """A shipped file names datasets, never a folder of the machine it was trained on."""
    import re
    import struct

    blob = default_weights.DEFAULT_WEIGHTS.read_bytes()
    # strings-style over the whole file, tensors included
    for marker in (b"/work/", b"/home/", b"/root/", b"/tmp/", b"/Users/", b"/mnt/", b"C:\\"):
        assert marker not in blob, marker
    size = struct.unpack("<Q", blob[:8])[0]
    meta = json.loads(json.loads(blob[8 : 8 + size])["__metadata__"]["byoc"])
    path_like = re.compile(r"^(/|~|[A-Za-z]:[\\/])|(^|/)\.\.(/|$)")
    assert meta["training"]["data"] == ["tum_fr1_rpy", "realsense_office", "tum_fr1_xyz"]
    for text in _strings(meta):
        assert not path_like.search(text), text
    assert meta["training"]["init_weights"]["file"] == "sp1-4900.safetensors"


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


def test_a_damaged_install_is_refused_before_any_pair(tmp_path, monkeypatch):
    """The shipped tensors are read on first use, but the file's checksum is checked when the
    registrar is made."""
    from byoc_cli.errors import WeightsError
    from byoc_cli.pipeline.registrar import Registrar

    bad = tmp_path / "default.sha256"
    bad.write_text("0" * 64 + "\n")
    monkeypatch.setattr(default_weights, "DEFAULT_CHECKSUM", bad)
    with pytest.raises(WeightsError, match="checksum"):
        Registrar()

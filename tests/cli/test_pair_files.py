"""The files a registered pair writes besides T: ``--aligned`` by extension and ``--qc DIR``
(``register``: always; ``register-batch``: only the pairs below the gate)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from byoc_cli.cli.main import cli
from byoc_cli.evaluation.qc import SOURCE_RGB, TARGET_RGB
from byoc_cli.io import write_ply
from byoc_cli.io.e57 import read_e57_points

#: for tests of the files, which any recipe shows: small and fast
FAST = ["--max-points", "1000", "--num-correspondences", "100", "--refine", "none"]


def _room(tmp_path: Path) -> tuple[Path, Path]:
    """A room corner (floor and two walls) and the same corner turned 15 deg and moved."""
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1, (6000, 3)) * [3.0, 2.5, 2.0]
    face = rng.integers(0, 3, len(points))
    for axis in range(3):
        points[face == axis, (2, 0, 1)[axis]] = 0.0
    a = np.radians(15.0)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    write_ply(tmp_path / "src.ply", points)
    write_ply(tmp_path / "tgt.ply", points @ R.T + [0.3, -0.2, 0.05])
    return tmp_path / "src.ply", tmp_path / "tgt.ply"


def _colours(png: Path) -> tuple[int, int]:
    pixels = np.asarray(Image.open(png).convert("RGB")).astype(int)
    top = pixels[: pixels.shape[0] // 2]
    return tuple(int(np.all(top == c, axis=-1).sum()) for c in (TARGET_RGB, SOURCE_RGB))


def test_register_qc_writes_the_two_files_and_reports_them(tmp_path):
    src, tgt = _room(tmp_path)
    qc = tmp_path / "qc"
    report = tmp_path / "r.json"
    args = ["-o", str(tmp_path / "T.txt"), "--json", str(report), "--qc", str(qc), *FAST]
    result = CliRunner().invoke(cli, ["register", str(src), str(tgt), *args])
    assert result.exit_code in (0, 3), result.output
    assert sorted(p.name for p in qc.iterdir()) == ["src__tgt_qc.png", "src__tgt_residual.ply"]
    blue, orange = _colours(qc / "src__tgt_qc.png")
    assert blue > 1000 and orange > 1000
    entry = json.loads(report.read_text())["qc"]
    assert entry["ply"] == str(qc / "src__tgt_residual.ply")
    assert entry["residual_clip"] > 0 and 0 <= entry["within_clip"] <= 1


def test_aligned_e57_and_misuse_of_the_outputs(tmp_path):
    src, tgt = _room(tmp_path)
    base = ["register", str(src), str(tgt), "-o", str(tmp_path / "T.txt"), *FAST]
    result = CliRunner().invoke(cli, [*base, "--aligned", str(tmp_path / "m.e57")])
    assert result.exit_code in (0, 3), result.output
    T = np.loadtxt(tmp_path / "T.txt")
    from byoc_cli.io import read_point_cloud

    expected = read_point_cloud(src).points @ T[:3, :3].T + T[:3, 3]
    assert np.abs(read_e57_points(tmp_path / "m.e57") - expected).max() < 1e-5
    for extra, phrase in (
        (["--aligned", str(tmp_path / "m.las")], "copies the header and point records"),
        (["--qc", str(src)], "is not a folder (--qc)"),
    ):
        (tmp_path / "T.txt").unlink(missing_ok=True)
        result = CliRunner().invoke(cli, [*base, *extra])
        assert result.exit_code == 1, result.output
        assert result.stderr.count("\n") == 1 and phrase in result.stderr, result.stderr
        assert not (tmp_path / "T.txt").exists() and not (tmp_path / "m.las").exists()


@pytest.mark.parametrize(("gate", "written"), [("1.0", True), ("0.0", False)])
def test_batch_qc_is_only_for_pairs_below_the_gate(tmp_path, gate, written):
    src, tgt = _room(tmp_path)
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"{src} {tgt}\n")
    qc = tmp_path / "qc"
    args = ["--out-dir", str(tmp_path / "out"), "--qc", str(qc), "--min-confidence", gate]
    result = CliRunner().invoke(cli, ["register-batch", str(listing), *args, *FAST])
    assert result.exit_code == (3 if written else 0), result.output
    record = json.loads((tmp_path / "out" / "summary.jsonl").read_text())
    if written:
        assert sorted(p.name for p in qc.iterdir()) == [
            "src__tgt_qc.png",
            "src__tgt_residual.ply",
        ]
        assert record["qc"]["png"] == str(qc / "src__tgt_qc.png")
        assert min(_colours(qc / "src__tgt_qc.png")) > 1000
    else:
        assert not qc.exists() and "qc" not in record

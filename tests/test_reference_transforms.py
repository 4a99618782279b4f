"""The T files of the demo pair and the 3DMatch sample pairs, to their last bits.

``reference_transforms.json`` holds what ``byoc register-batch`` (no flags) writes for each
pair. A commit that means to change results updates it and says so; any other commit (a
restructuring, a speed-up) leaves every number as it was: within :data:`PLATFORM`, because
the same code rounds the last bits of a float64 otherwise on another CPU (an AMD EPYC machine
writes every file of the reference within 5.6e-16 of it), while a change of a result moves
it by far more.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli

REFERENCE = Path(__file__).with_name("reference_transforms.json")
#: the largest difference of one number of a T file from the reference that is no change
PLATFORM = 1e-12


def _pairs(shared_data: Path) -> dict[str, tuple[Path, Path]]:
    """``name -> (source, target)`` of the reference pairs (the names of the JSON file)."""
    sample = shared_data / "3dmatch" / "sample"
    pairs = {}
    for bench in ("3DMatch", "3DLoMatch"):
        for scene in sorted(p for p in (sample / bench).iterdir() if p.is_dir()):
            if scene.name.endswith("-evaluation"):
                continue
            log = (sample / bench / f"{scene.name}-evaluation" / "gt.log").read_text().split("\n")
            for k in range(0, len(log) - 1, 5):
                i, j, _ = log[k].split()
                pairs[f"{bench}_{i}_{j}"] = (
                    scene / f"cloud_bin_{j}.ply",
                    scene / f"cloud_bin_{i}.ply",
                )
    demo = shared_data / "pairs" / "3dmatch_demo"
    pairs["demo"] = (demo / "source.ply", demo / "target.ply")
    return pairs


@pytest.mark.realdata
@pytest.mark.slow
def test_every_reference_pair_gives_its_t_file_to_the_last_bits(shared_data, tmp_path):
    reference = json.loads(REFERENCE.read_text())
    pairs = _pairs(shared_data)
    assert sorted(pairs) == sorted(reference)
    lines = [f"{src} {tgt} {tmp_path / (name + '.txt')}" for name, (src, tgt) in pairs.items()]
    (tmp_path / "pairs.txt").write_text("\n".join(lines) + "\n")
    run = CliRunner().invoke(cli, ["register-batch", str(tmp_path / "pairs.txt"), "-q"])
    assert run.exit_code in (0, 3), run.output
    gaps = {n: _gap((tmp_path / f"{n}.txt").read_text(), reference[n]) for n in pairs}
    changed = {n: gap for n, gap in gaps.items() if not gap <= PLATFORM}
    assert not changed, f"T files changed (largest difference of a number): {changed}"


def _gap(written: str, reference: str) -> float:
    """The largest difference between the numbers of two T files (inf: not the same shape)."""
    a, b = (
        [[float(x) for x in line.split()] for line in t.splitlines()] for t in (written, reference)
    )
    if [len(row) for row in a] != [len(row) for row in b]:
        return float("inf")
    pairs = (xy for ra, rb in zip(a, b, strict=True) for xy in zip(ra, rb, strict=True))
    return max(abs(x - y) for x, y in pairs)


def test_last_bits_are_no_change_and_anything_more_is():
    T = "0.9523037728933232 -0.15 0.26 0.348\n0.17 0.98 -0.06 -0.003\n0 0 1 0.3\n0 0 0 1\n"
    assert _gap(T, T) == 0.0
    assert _gap(T.replace("0.9523037728933232", "0.9523037728933229"), T) <= PLATFORM
    assert _gap(T.replace("0.348", "0.348001"), T) > PLATFORM
    assert _gap(T + "0 0 0 1\n", T) == float("inf")

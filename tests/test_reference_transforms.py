"""The T files of the demo pair and the 3DMatch sample pairs, byte for byte.

``reference_transforms.json`` holds what ``byoc register-batch`` (no flags) writes for each
pair. A commit that means to change results updates it and says so; any other commit (a
restructuring, a speed-up) leaves every byte as it was.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli

REFERENCE = Path(__file__).with_name("reference_transforms.json")


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
def test_every_reference_pair_gives_its_t_file_byte_for_byte(shared_data, tmp_path):
    reference = json.loads(REFERENCE.read_text())
    pairs = _pairs(shared_data)
    assert sorted(pairs) == sorted(reference)
    lines = [f"{src} {tgt} {tmp_path / (name + '.txt')}" for name, (src, tgt) in pairs.items()]
    (tmp_path / "pairs.txt").write_text("\n".join(lines) + "\n")
    run = CliRunner().invoke(cli, ["register-batch", str(tmp_path / "pairs.txt"), "-q"])
    assert run.exit_code in (0, 3), run.output
    changed = [n for n in pairs if (tmp_path / f"{n}.txt").read_text() != reference[n]]
    assert not changed, f"T files changed: {changed}"

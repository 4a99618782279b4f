"""What `register` and `register-batch` say of an ambiguous result (`--turns`: another turned
try fits about as well elsewhere; the check with another seed ends elsewhere) and of one that
sees through the other scan (the visibility check), or whose source turned about the up axis
fits as well (the structure check): one line naming it, and a rerun counts it below the
gate."""

from __future__ import annotations

import json
from types import SimpleNamespace

from byoc_cli.cli.batch_summary import init_reason, recorded_below, recorded_results
from byoc_cli.cli.register import failure_line

TURNS = {
    "up_axis": [0.0, 0.0, 1.0],
    "tries": [
        {"degrees": 0.0, "confidence": 0.2, "T_tgt_src": None},
        {"degrees": 120.0, "confidence": 0.91, "T_tgt_src": None},
        {"degrees": 240.0, "confidence": 0.88, "T_tgt_src": None},
    ],
    "kept_deg": 120.0,
    "ambiguous": True,
}

CHECK = {
    "seed": 1,
    "model_confidence": 0.41,
    "apart": {"rotation_deg": 14.6, "translation": 1.14, "voxels": 45.6},
    "agrees": False,
    "ambiguous": True,
    "alternatives": [
        {"seed": 0, "confidence": 0.495, "T_tgt_src": None},
        {"seed": 1, "confidence": 0.261, "T_tgt_src": None},
    ],
    "kept_seed": 0,
}


VISIBILITY = {
    "source_in_target": 0.012,
    "target_in_source": 0.138,
    "seen": [3472, 3271],
    "free_space": 0.138,
    "max_free_space": 0.09,
    "consistent": False,
    "seconds": 0.004,
}


def _result(confidence: float, **fields) -> SimpleNamespace:
    """A stand-in of a global-path ``Registration`` with ``confidence`` and ``fields`` (the
    reports ``turns``, ``check``, ``visibility``, ``cues``), none by default."""
    base = {"turns": None, "init": None, "path": "global", "check": None, "visibility": None}
    return SimpleNamespace(**{**base, "cues": {}, "confidence": confidence, **fields})


def _batch_says(line: str) -> str:
    """What ``register-batch`` names of a pair whose ``register`` line is ``line``."""
    return line.removeprefix("byoc: ").split(": T is")[0]


def _rerun_counts_it_below(tmp_path, record: dict) -> bool:
    """Whether a rerun of ``register-batch`` counts ``record``, read back from a summary,
    below a gate of 0.45."""
    summary = tmp_path / "summary.jsonl"
    summary.write_text(json.dumps(record) + "\n")
    (earlier,) = recorded_results(summary).values()
    return recorded_below(earlier, 0.45)


def test_register_says_ambiguous_with_the_rivals_confidences():
    result = _result(0.91, turns=TURNS)
    line = failure_line(result, 0.45, "m")
    assert line.startswith("byoc: ambiguous: the source fits at more than one pose")
    assert "0.910 turned 120 deg, 0.880 turned 240 deg" in line and "\n" not in line


def test_a_result_that_is_not_ambiguous_is_below_the_gate_as_before():
    result = _result(
        0.3,
        turns={**TURNS, "ambiguous": False},
        check={**CHECK, "ambiguous": False, "alternatives": []},
        visibility={**VISIBILITY, "consistent": True},
    )
    result.cues = {"structure_rival": -0.3}
    assert "below --min-confidence 0.45" in failure_line(result, 0.45, "m")


def test_batch_names_why_and_a_rerun_counts_it_below_the_gate(tmp_path):
    record = {"status": "low_confidence", "confidence": 0.91, "turns": TURNS, "output": "a.txt"}
    assert init_reason(record).startswith("ambiguous:")
    assert _rerun_counts_it_below(tmp_path, record)  # its confidence alone would pass


def test_register_and_batch_say_where_the_two_seeds_put_the_source(tmp_path):
    result = _result(0.495, check=CHECK)
    line = failure_line(result, 0.45, "m")
    assert line == (
        "byoc: ambiguous: seeds 0 and 1 fit the source 14.6 deg / 1.14 m apart (confidences "
        "0.495 and 0.261): T is likely wrong (written all the same)"
    )
    far = {**CHECK, "apart": {**CHECK["apart"], "translation": 22.8}}
    unknown_unit = SimpleNamespace(**{**vars(result), "check": far})
    assert "14.6 deg / 22.8 input units apart" in failure_line(unknown_unit, 0.45, None)
    record = {"status": "low_confidence", "confidence": 0.495, "check": CHECK, "unit": "m"}
    record["output"] = "a.txt"
    assert init_reason(record) == _batch_says(line)
    assert _rerun_counts_it_below(tmp_path, record)  # its confidence alone would pass


def test_register_exits_3_with_both_poses_when_the_check_lands_elsewhere(tmp_path, monkeypatch):
    """`byoc register` end to end with the matching stood in: the first try passes at 0.8
    with an overlap of 0.3, the check (seed 1) ends 1.5 m away at 0.6."""
    import numpy as np
    from click.testing import CliRunner

    from byoc_cli.cli.main import cli
    from byoc_cli.pipeline.registrar import Registrar
    from byoc_cli.pipeline.results import Registration
    from tests.pipeline._clouds import cube, moved

    def match_alone(self, src, tgt, **kw):
        seed = kw["seed"] or 0  # None: the recipe's, 0
        T = np.eye(4)
        T[0, 3] = 1.5 * seed
        confidence = 0.8 if seed == 0 else 0.6
        return Registration(
            T, confidence, True, 10, 20, 0.5, 0.3, 100, 100, 0.05, 0.025, "byoc", "ransac",
            "multiscale", 1000, 100, seed, None, {"fit": 0.1},
        )  # fmt: skip

    monkeypatch.setattr(Registrar, "match_alone", match_alone)
    np.save(tmp_path / "a.npy", cube(1))
    np.save(tmp_path / "b.npy", moved(cube(1))[0])
    args = ["register", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--voxel-size", "0.025"]
    args += ["-o", str(tmp_path / "T.txt"), "--json", str(tmp_path / "r.json")]
    run = CliRunner().invoke(cli, args)
    assert run.exit_code == 3, run.output
    assert (  # an .npy declares no unit; 0.6 discounted for two tries reads 0.429
        "ambiguous: seeds 0 and 1 fit the source 0.0 deg / 1.5 input units apart (confidences "
        "0.800 and 0.429)" in run.stderr
    )
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["passed"] is False and report["check"]["ambiguous"]
    assert [a["seed"] for a in report["check"]["alternatives"]] == [0, 1]
    assert np.loadtxt(tmp_path / "T.txt")[0, 3] == 0.0  # the more confident pose is written
    run = CliRunner().invoke(cli, [*args, "--no-recheck", "--no-visibility"])
    assert run.exit_code == 0, run.output


def test_register_and_batch_say_what_lies_in_the_other_scans_free_space(tmp_path):
    result = _result(0.631, visibility=VISIBILITY)
    line = failure_line(result, 0.45, "m")
    assert line == (
        "byoc: inconsistent: under T 1% of the source lies in space the target's sensor saw "
        "empty, 14% of the target in the source's (at most 9%; sensors at the clouds' origins, "
        "--no-visibility if they are not): T is likely wrong (written all the same)"
    )
    record = {"status": "low_confidence", "confidence": 0.631, "visibility": VISIBILITY}
    record["output"] = "a.txt"
    assert init_reason(record) == _batch_says(line)
    assert _rerun_counts_it_below(tmp_path, record)  # its confidence alone would pass
    consistent = {**record, "visibility": {**VISIBILITY, "consistent": True}}
    assert init_reason(consistent) is None


def test_register_and_batch_say_a_turn_of_the_source_fits_as_well(tmp_path):
    result = _result(0.1)
    result.cues = {"fitness": 0.8, "structure_rival": -0.03}
    line = failure_line(result, 0.45, "m")
    assert line == (
        "byoc: ambiguous: the source turned about the up axis fits what stands in the scene as "
        "well as under T (clutter fit -0.03 against T's; -0.05 at most): T is likely wrong "
        "(written all the same)"
    )
    record = {"status": "low_confidence", "confidence": 0.1, "cues": result.cues}
    record["output"] = "a.txt"
    assert init_reason(record) == _batch_says(line)
    assert init_reason({**record, "cues": {"structure_rival": -0.2}}) is None
    assert init_reason({**record, "cues": {"structure_rival": float("nan")}}) is None


def test_register_exits_3_when_the_source_lies_in_the_targets_free_space(tmp_path, monkeypatch):
    """`byoc register` end to end with the matching stood in: two views of a wall 3 m in
    front of the sensor, and a result that passes at 0.8 with the source a metre in front of
    the wall the target saw."""
    import numpy as np
    from click.testing import CliRunner

    from byoc_cli.cli.main import cli
    from byoc_cli.pipeline.registrar import Registrar
    from byoc_cli.pipeline.results import Registration

    def match_alone(self, src, tgt, **kw):
        T = np.eye(4)
        T[2, 3] = -1.0
        return Registration(
            T, 0.8, True, 10, 20, 0.5, 0.9, 100, 100, 0.05, 0.025, "byoc", "ransac",
            "multiscale", 1000, 100, kw["seed"] or 0, None, {"fit": 0.1},
        )  # fmt: skip

    monkeypatch.setattr(Registrar, "match_alone", match_alone)
    ticks = np.arange(-1.0, 1.01, 0.02)
    x, y = np.meshgrid(ticks, ticks, indexing="ij")
    wall = np.stack([x.ravel(), y.ravel(), np.full(x.size, 3.0)], axis=1).astype(np.float32)
    np.save(tmp_path / "a.npy", wall)
    np.save(tmp_path / "b.npy", wall)
    args = ["register", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--voxel-size", "0.025"]
    args += ["-o", str(tmp_path / "T.txt"), "--json", str(tmp_path / "r.json")]
    run = CliRunner().invoke(cli, args)
    assert run.exit_code == 3, run.output
    assert "inconsistent: under T 100% of the source lies in space the target's sensor" in (
        run.stderr
    )
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["passed"] is False and not report["visibility"]["consistent"]
    assert report["visibility"]["source_in_target"] == 1.0
    assert np.loadtxt(tmp_path / "T.txt")[2, 3] == -1.0  # T is written all the same
    run = CliRunner().invoke(cli, [*args, "--no-visibility"])
    assert run.exit_code == 0, run.output
    assert json.loads((tmp_path / "r.json").read_text())["visibility"] is None

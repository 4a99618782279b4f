"""The self-posed variant end to end: no ground truth read, exact resume, CLI."""

from __future__ import annotations

import shutil
import sys

import pytest
import torch
from safetensors.torch import load_file

from byoc_cli.training.config import TrainConfig
from byoc_cli.training.trainer import resume_config, train

pytestmark = [pytest.mark.slow, pytest.mark.realdata]

#: file names that hold poses in the layouts the readers accept
_POSE_NAMES = ("groundtruth.txt",)
_opened: list[str] | None = None


def _audit(event: str, args: tuple) -> None:
    if _opened is not None and event == "open" and args and isinstance(args[0], str | bytes):
        _opened.append(str(args[0]))


sys.addaudithook(_audit)


def _config(data, out, **kw) -> TrainConfig:
    values = dict(
        rgbd_dir=(str(data),),
        out=str(out),
        variant="self-posed",
        steps=4,
        batch_size=2,
        lr=1e-3,
        checkpoint_every=2,
        val_every=0,
        log_every=1,
        num_positives=128,
        pair_gaps=(2, 4),
        seed=3,
    )
    values.update(kw)
    return TrainConfig(**values)


def _assert_identical(a, b) -> None:
    ta, tb = load_file(str(a)), load_file(str(b))
    assert ta.keys() == tb.keys()
    for name in ta:
        assert torch.equal(ta[name], tb[name]), name


@pytest.fixture(scope="module")
def sequence_copies(shared_data, tmp_path_factory):
    """tum_fr1_xyz as shipped, and a copy whose ground truth is gone."""
    src = shared_data / "rgbd" / "tum_fr1_xyz"
    root = tmp_path_factory.mktemp("seqs")
    without = root / "tum_fr1_xyz"
    shutil.copytree(src, without)
    (without / "groundtruth.txt").unlink()
    return src, without


def test_training_reads_no_ground_truth(sequence_copies, tmp_path):
    global _opened
    with_gt, without_gt = sequence_copies
    _opened = []
    # two rounds: the second poses the frames again with the encoder being trained
    rounds = {"round_steps": 2, "round_gaps": (6,)}
    try:
        first = train(_config(with_gt, tmp_path / "a", **rounds))
    finally:
        opened, _opened = _opened, None
    assert any(p.endswith(".png") for p in opened)  # the hook does see the data being read
    assert not [p for p in opened if p.endswith(_POSE_NAMES)]
    # positive control: ordinary discovery (evaluation) does open the ground truth
    from byoc_cli.io.rgbd import discover_sequences

    _opened = []
    try:
        discover_sequences(with_gt)
    finally:
        control, _opened = _opened, None
    assert [p for p in control if p.endswith(_POSE_NAMES)]
    # and the result does not depend on the ground truth being there at all
    second = train(_config(without_gt, tmp_path / "b", **rounds))
    _assert_identical(first.weights_path, second.weights_path)
    assert sorted((tmp_path / "b" / "pseudo_pairs" / "round-2").glob("*.json"))
    pairs = sorted((tmp_path / "a" / "pseudo_pairs").glob("*.json"))
    assert pairs and (tmp_path / "a" / "pseudo_pairs" / pairs[0].name).stat().st_size > 0


def test_resume_is_exact_and_reuses_the_pair_cache(sequence_copies, tmp_path):
    data, _ = sequence_copies
    straight = train(_config(data, tmp_path / "straight"))
    first = train(_config(data, tmp_path / "resumed", steps=2))
    assert first.steps == 2
    cache = sorted((tmp_path / "resumed" / "pseudo_pairs").glob("*.json"))
    stamp = cache[0].stat().st_mtime_ns
    config = resume_config(tmp_path / "resumed", {"steps": 4})
    second = train(config, resume=True)
    assert second.steps == 4
    assert cache[0].stat().st_mtime_ns == stamp  # not estimated again
    _assert_identical(straight.weights_path, second.weights_path)
    assert second.last_loss is not None and second.last_loss > 0


def test_fine_tuning_starts_from_the_shipped_weights_and_resume_does_not_reload_them(
    sequence_copies, tmp_path
):
    from byoc_cli.pipeline.default_weights import default_weights_path
    from byoc_cli.pipeline.weights import load_weights

    data, _ = sequence_copies
    shipped = load_weights(default_weights_path())
    # one step at a vanishing learning rate: the exported encoder is the shipped one
    tuned = train(_config(data, tmp_path / "tuned", steps=1, lr=1e-12, init_weights="shipped"))
    got = load_weights(tuned.weights_path)
    ref = shipped.encoder.state_dict()
    for name, value in got.encoder.state_dict().items():
        if value.is_floating_point() and "running" not in name:
            assert torch.allclose(value, ref[name], atol=1e-5), name
    init = got.metadata["training"]["init_weights"]
    assert init["sha256"] == shipped.file_sha256 and init["file"] == "default.safetensors"
    assert init["description"].startswith("the weights shipped with byoc-cli ")
    # resumed runs continue from their checkpoint, not from the initial weights again
    straight = train(_config(data, tmp_path / "straight", init_weights="shipped"))
    train(_config(data, tmp_path / "resumed", steps=2, init_weights="shipped"))
    resumed = train(resume_config(tmp_path / "resumed", {"steps": 4}), resume=True)
    _assert_identical(straight.weights_path, resumed.weights_path)


@pytest.mark.parametrize("mode", ["quiet", "lines", "bar"])
def test_cli_self_posed_run_with_validation(shared_data, tmp_path, monkeypatch, mode):
    # the progress bar (a terminal's) shows the loss (it once looked up the paper variants'
    # three losses and crashed at the first step); off a terminal, lines; -q, nothing
    from click.testing import CliRunner

    import byoc_cli.cli.train as train_command
    from byoc_cli.cli.main import cli

    if mode == "bar":
        display = train_command._Display
        monkeypatch.setattr(train_command, "_Display", lambda quiet, bar: display(quiet, True))
    quiet = mode == "quiet"

    toml = tmp_path / "recipe.toml"
    toml.write_text("num_positives = 64\npair_gaps = [2, 4]\n")
    result = CliRunner().invoke(
        cli,
        [
            "train",
            "--rgbd-dir",
            str(shared_data / "rgbd" / "tum_fr1_xyz"),
            "--variant",
            "self-posed",
            "--steps",
            "2",
            "--batch-size",
            "1",
            "--val-dir",
            str(shared_data / "rgbd" / "tum_fr1_desk"),
            "--val-spacing",
            "4",
            "--val-every",
            "2",
            "--config",
            str(toml),
            "--out",
            str(tmp_path / "run"),
            *(["--quiet"] if quiet else []),
        ],
    )
    assert result.exit_code == 0, result.output
    if quiet:
        assert result.stderr == ""
    else:
        assert "feature-match recall" in result.stderr
        # the closing summary names the self-posed figures (it once printed "rot@5deg -% ->
        # -%")
        summary = [line for line in result.stderr.splitlines() if "(start) ->" in line]
        assert len(summary) == 1 and "byoc: validation feature-match recall" in summary[0]
        assert "-%" not in summary[0]
    from byoc_cli.pipeline.weights import load_weights

    loaded = load_weights(tmp_path / "run" / "weights.safetensors")
    assert loaded.metadata["training"]["variant"] == "self-posed"
    assert loaded.metadata["training"]["recipe"]["num_positives"] == 64
    assert "val_fmr" in loaded.metadata["training"]["metrics"]
    # datasets by name, never the folders of this machine
    assert loaded.metadata["training"]["data"] == ["tum_fr1_xyz"]
    assert loaded.metadata["training"]["validation_data"] == ["tum_fr1_desk"]
    assert loaded.metadata["training"]["val_spacing"] == 4
    # a checkpoint exported later names them the same way
    from byoc_cli.training.self_posed_eval import export_checkpoint

    checkpoint = sorted((tmp_path / "run" / "checkpoints").glob("step-*.pt"))[-1]
    export_checkpoint(checkpoint, tmp_path / "later.safetensors")
    later = load_weights(tmp_path / "later.safetensors").metadata["training"]
    assert later["data"] == ["tum_fr1_xyz"] and later["validation_data"] == ["tum_fr1_desk"]


def test_pairs_from_reuses_an_earlier_runs_pairs(sequence_copies, tmp_path, monkeypatch):
    data, _ = sequence_copies
    train(_config(data, tmp_path / "first", steps=1))
    import byoc_cli.training.self_posed as sp

    def no_estimation(*_args, **_kw):
        raise AssertionError("pairs were estimated again")

    monkeypatch.setattr(sp, "estimate_pairs", no_estimation)
    second = train(_config(data, tmp_path / "second", steps=1, pairs_from=str(tmp_path / "first")))
    assert second.steps == 1
    a = sorted((tmp_path / "first" / "pseudo_pairs").glob("*.json"))
    b = sorted((tmp_path / "second" / "pseudo_pairs").glob("*.json"))
    assert [p.name for p in a] == [p.name for p in b]
    import json

    assert json.loads(a[0].read_text())["pairs"] == json.loads(b[0].read_text())["pairs"]
    # other settings: not reused
    with pytest.raises(AssertionError, match="estimated again"):
        train(
            _config(
                data,
                tmp_path / "third",
                steps=1,
                pair_gaps=(3,),
                pairs_from=str(tmp_path / "first"),
            )
        )


def test_hardest_contrastive_loss_trains_and_is_recorded(sequence_copies, tmp_path, monkeypatch):
    data, _ = sequence_copies
    first = train(_config(data, tmp_path / "infonce", steps=2))
    import byoc_cli.training.self_posed as sp

    calls = []
    real = sp.hardest_contrastive

    def counting(*args, **kw):
        calls.append(kw)
        return real(*args, **kw)

    monkeypatch.setattr(sp, "hardest_contrastive", counting)
    options = dict(steps=2, loss="hardest-contrastive", neg_margin=1.2)
    second = train(_config(data, tmp_path / "hc", pairs_from=str(tmp_path / "infonce"), **options))
    # batch 2, 2 steps: one call per pair, with the configured margins
    assert len(calls) == 4 and all(c["neg_margin"] == 1.2 for c in calls)
    assert second.steps == 2
    from byoc_cli.pipeline.weights import load_weights

    recipe = load_weights(tmp_path / "hc" / "weights.safetensors").metadata["training"]["recipe"]
    assert (recipe["loss"], recipe["pos_margin"], recipe["neg_margin"]) == (
        "hardest-contrastive",
        0.1,
        1.2,
    )
    a = load_file(str(tmp_path / "infonce" / "weights.safetensors"))
    b = load_file(str(tmp_path / "hc" / "weights.safetensors"))
    assert any(not torch.equal(a[k], b[k]) for k in a)  # same seed and pairs, other loss
    assert first.steps == 2


def test_rounds_pose_again_with_the_trained_encoder_and_resume_exactly(sequence_copies, tmp_path):
    import json

    from byoc_cli.pipeline.weights import load_weights
    from byoc_cli.training.plot import read_metrics

    data, _ = sequence_copies
    rounds = {"round_steps": 2, "round_gaps": (6,), "checkpoint_every": 3}
    straight = train(_config(data, tmp_path / "straight", **rounds))
    run = tmp_path / "straight"
    first = json.loads(next((run / "pseudo_pairs").glob("*.json")).read_text())
    second = json.loads(next((run / "pseudo_pairs" / "round-2").glob("*.json")).read_text())
    assert first["global_start"] == "fpfh" and first["config"]["gaps"] == [2, 4]
    assert second["global_start"] == "learned" and second["round"] == 2
    assert second["config"]["gaps"] == [2, 4, 6]  # the wider gaps of later rounds
    assert second["candidates"]["6"] >= 1
    logged = [r for r in read_metrics(run / "metrics.jsonl") if r["kind"] == "round"]
    assert [(r["round"], r["step"]) for r in logged] == [(1, 0), (2, 2)]
    assert logged[1]["pairs"] == len(second["pairs"])
    assert logged[1]["sequences"]["tum_fr1_xyz"]["kept"] == second["kept"]
    recipe = load_weights(straight.weights_path).metadata["training"]["recipe"]
    assert recipe["rounds"] == 2 and recipe["round_steps"] == 2
    # the end of a round is checkpointed (here not a multiple of checkpoint_every); a run
    # stopped there poses round 2 on resume from that checkpoint and ends bit-identical
    train(_config(data, tmp_path / "resumed", steps=2, **rounds))
    assert (tmp_path / "resumed" / "checkpoints" / "step-00000002.pt").exists()
    assert not (tmp_path / "resumed" / "pseudo_pairs" / "round-2").exists()
    resumed = train(resume_config(tmp_path / "resumed", {"steps": 4}), resume=True)
    _assert_identical(straight.weights_path, resumed.weights_path)
    again = read_metrics(tmp_path / "resumed" / "metrics.jsonl")
    assert [r["round"] for r in again if r["kind"] == "round"] == [1, 2]


def test_too_short_a_video_is_one_line_naming_pair_gaps(shared_data, tmp_path):
    """4 frames: no pair at the smallest gap (5); one line saying what to change (the error
    once raised a TypeError)."""
    import shutil

    from click.testing import CliRunner

    from byoc_cli.cli.main import cli

    source, seq = shared_data / "rgbd" / "tum_fr1_xyz", tmp_path / "seq"
    (seq / "depth").mkdir(parents=True)
    shutil.copy(source / "intrinsics.json", seq)
    lines = (source / "depth.txt").read_text().splitlines()[:5]  # a comment, 4 frames
    (seq / "depth.txt").write_text("\n".join(lines) + "\n")
    for line in lines[1:]:
        shutil.copy(source / line.split()[1], seq / line.split()[1])
    result = CliRunner().invoke(
        cli, ["train", "--rgbd-dir", str(seq), "--steps", "1", "--out", str(tmp_path / "run")]
    )
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()  # the pseudo-poses' progress, then the error
    error = [line for line in lines if line.startswith("byoc: error")]
    assert error == lines[-1:] and error[0].startswith(f"byoc: error: {seq}: no self-posed pair")
    assert "pair_gaps in --config, now 5, 10" in error[0]
    assert not (tmp_path / "run").exists()  # a failed first step leaves no run folder

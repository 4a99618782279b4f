import json

import pytest
from click.testing import CliRunner

from byoc_cli.cli.main import cli


def _run(args):
    return CliRunner().invoke(cli, ["train", *args])


def test_help_lists_the_options():
    result = _run(["--help"])
    assert result.exit_code == 0
    for flag in (
        "--rgbd-dir",
        "--view-spacing",
        "--num-workers",
        "--steps",
        "--batch-size",
        "--lr",
        "--seed",
        "--device",
        "--arch",
        "--variant",
        "--val-every",
        "--checkpoint-every",
        "--out",
        "--config",
        "--resume",
        "--quiet",
        "--val-dir",
        "--init-weights",
    ):
        assert flag in result.output


def test_missing_rgbd_dir_is_exit_1_naming_the_folder(tmp_path):
    missing = tmp_path / "no_such_scans"
    result = _run(["--rgbd-dir", str(missing), "--out", str(tmp_path / "run")])
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("byoc: error:") and str(missing) in lines[0]


def test_empty_rgbd_dir_is_exit_1(tmp_path):
    (tmp_path / "empty").mkdir()
    result = _run(["--rgbd-dir", str(tmp_path / "empty"), "--out", str(tmp_path / "run")])
    assert result.exit_code == 1
    assert str(tmp_path / "empty") in result.stderr


def test_no_data_is_usage_error():
    assert _run([]).exit_code == 2


def test_bad_variant_is_usage_error(tmp_path):
    assert _run(["--rgbd-dir", str(tmp_path), "--variant", "nope"]).exit_code == 2


def test_misspelled_config_key_is_exit_1(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("num_correspodances = 100\n")
    result = _run(["--config", str(cfg), "--rgbd-dir", str(tmp_path)])
    assert result.exit_code == 1
    assert "num_correspondences" in result.stderr and str(cfg) in result.stderr


def test_out_of_range_config_value_is_a_usage_error_naming_the_file(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text('loss = "triplet"\n')
    result = _run(["--config", str(cfg), "--rgbd-dir", str(tmp_path), "--out", str(tmp_path / "r")])
    assert result.exit_code == 2
    assert f"{cfg}: loss must be one of infonce, hardest-contrastive" in result.stderr
    assert not (tmp_path / "r").exists()
    # an error about a value the flags set (overriding the file, or not in it) does not blame it
    from byoc_cli.cli.train import _blame_file

    message = "lr must be > 0, got -1.0"
    assert _blame_file(message, cfg, {"lr": 1e-3}, {"lr": -1.0}) == message
    assert _blame_file(message, cfg, {"steps": 5}, {"lr": -1.0}) == message
    assert _blame_file(message, cfg, {"lr": -1.0}, {}) == f"{cfg}: {message}"


def test_resume_of_a_non_run_is_exit_1(tmp_path):
    result = _run(["--resume", str(tmp_path / "nope")])
    assert result.exit_code == 1 and str(tmp_path / "nope") in result.stderr


@pytest.mark.slow
def test_config_precedence_end_to_end(shared_data, tmp_path):
    cfg = tmp_path / "c.toml"
    data = shared_data / "rgbd" / "tum_fr1_xyz"
    cfg.write_text(
        f'rgbd_dir = "{data}"\nsteps = 2\nlr = 0.001\nbatch_size = 2\n'
        'view_spacing = 2\nval_every = 0\nnum_workers = 0\nvariant = "byoc-geo"\n'
    )
    run = tmp_path / "run"
    result = _run(
        ["--config", str(cfg), "--lr", "0.0005", "--out", str(run), "--quiet", "--device", "cpu"]
    )
    assert result.exit_code == 0, result.stderr
    assert result.stderr == ""  # --quiet: errors only; the result is the stdout line
    assert len(result.stdout.splitlines()) == 1
    saved = json.loads((run / "config.json").read_text())
    assert saved["config"]["lr"] == 0.0005 and saved["config"]["steps"] == 2
    assert saved["config"]["seed"] == 8 and "byoc_cli_version" in saved
    assert (run / "training.png").stat().st_size > 0
    assert result.stdout.strip().split("\t")[0] == str(run / "weights.safetensors")
    # the weights work with byoc register
    from byoc_cli.pipeline.weights import load_weights

    meta = load_weights(run / "weights.safetensors").metadata
    assert meta["training"]["variant"] == "byoc-geo" and meta["training"]["steps"] == 2
    assert meta["training"]["seed"] == 8
    # a second training into the same folder is refused
    again = _run(["--config", str(cfg), "--out", str(run), "--quiet", "--device", "cpu"])
    assert again.exit_code == 1 and "--resume" in again.stderr


@pytest.mark.slow
def test_validation_on_posed_video_is_logged_plotted_and_summarised(shared_data, tmp_path):
    run = tmp_path / "run"
    result = _run(
        [
            "--rgbd-dir",
            str(shared_data / "rgbd" / "tum_fr1_desk"),
            "--val-dir",
            str(shared_data / "rgbd" / "tum_fr1_xyz"),
            "--val-spacing",
            "3",
            "--val-every",
            "1",
            "--variant",
            "byoc-geo",
            "--steps",
            "2",
            "--batch-size",
            "2",
            "--view-spacing",
            "2",
            "--num-workers",
            "0",
            "--device",
            "cpu",
            "--out",
            str(run),
        ]
    )
    assert result.exit_code == 0, result.stderr
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    val = [r for r in records if r["kind"] == "val"]
    # before the first step (the random encoder), then after each step
    assert [r["step"] for r in val] == [0, 1, 2]
    for r in val:
        assert r["num_pairs"] == 3  # frames 0, 3, 6, 9 of tum_fr1_xyz
        for key in ("rot_acc_5", "rot_median_deg", "trans_acc_25", "inlier_pct_mean", "corr_fmr"):
            assert 0.0 <= r[key] < 1e4, key
    assert "validation at step 2 (3 pairs)" in result.stderr
    assert "inlier correspondences" in result.stderr
    summary = [line for line in result.stderr.splitlines() if "validation rot@5deg" in line]
    assert len(summary) == 1 and "(start) ->" in summary[0]
    from byoc_cli.pipeline.weights import load_weights

    meta = load_weights(run / "weights.safetensors").metadata
    assert meta["training"]["metrics"]["val_rot_acc_5"] == val[-1]["rot_acc_5"]
    assert "val_inlier_pct_mean" in meta["training"]["metrics"]


def test_sigterm_checkpoints_the_last_step_and_resume_finishes(shared_data, tmp_path):
    """SIGTERM (a scheduler's stop) loses nothing: a checkpoint of the last finished step."""
    import os
    import signal
    import subprocess
    import sys
    import time

    run = tmp_path / "run"
    args = [
        "--rgbd-dir",
        str(shared_data / "rgbd" / "tum_fr1_desk"),
        "--variant",
        "byoc-geo",
        "--steps",
        "1000",
        "--batch-size",
        "1",
        "--view-spacing",
        "2",
        "--checkpoint-every",
        "0",
        "--val-every",
        "0",
        "--log-every",
        "1",
        "--num-workers",
        "0",
        "--device",
        "cpu",
        "--quiet",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "byoc_cli.cli.main", "train"]
    proc = subprocess.Popen(
        [*command, *args, "--out", str(run)],
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env=env,
    )
    metrics = run / "metrics.jsonl"
    deadline = time.time() + 300
    while not (metrics.exists() and metrics.read_text().count('"train"') >= 2):
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.time() < deadline
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode != 0
    saved = sorted((run / "checkpoints").glob("step-*.pt"))
    assert saved, err.decode()
    step = int(saved[-1].stem.split("-")[1])
    assert step >= 2
    assert not (run / "weights.safetensors").exists()

    done = subprocess.run(
        [*command, "--resume", str(run), "--steps", str(step + 1), "--quiet"],
        capture_output=True,
        env=env,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr.decode()
    assert (run / "weights.safetensors").exists()


def test_help_is_plain_text_and_documents_seed_and_device():
    result = _run(["--help"])
    assert "``" not in result.output
    lines = result.output.splitlines()
    for flag in ("--seed", "--device"):
        line = next(k for k, text in enumerate(lines) if text.strip().startswith(flag))
        assert len(" ".join(lines[line : line + 3]).split()) > 4, flag  # more than a default


def test_out_folder_with_other_files_is_refused(tmp_path):
    out = tmp_path / "results"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    result = _run(["--rgbd-dir", str(tmp_path), "--out", str(out)])
    assert result.exit_code == 1
    assert str(out) in result.stderr and "notes.txt" in result.stderr
    assert (out / "notes.txt").read_text() == "mine"


def _weights_file(path, seed, voxel_size=0.025):
    from byoc_cli.pipeline.weights import init_weights, save_weights

    encoder, meta = init_weights("compact", seed, voxel_size)
    save_weights(path, encoder, meta)
    return path


def _geo_args(shared_data, run, *extra):
    data = shared_data / "rgbd" / "tum_fr1_xyz"
    return [
        "--rgbd-dir", str(data), "--variant", "byoc-geo", "--steps", "1", "--batch-size", "1",
        "--view-spacing", "2", "--val-every", "0", "--num-workers", "0", "--quiet",
        "--device", "cpu", "--out", str(run), *extra,
    ]  # fmt: skip


def test_init_weights_start_the_geometric_encoder_from_a_file(shared_data, tmp_path):
    import hashlib

    import torch

    from byoc_cli.pipeline.weights import load_weights

    start = _weights_file(tmp_path / "start.safetensors", seed=5)
    # a learning rate so small that one step leaves the weights where they started
    tiny = ["--lr", "1e-12"]
    result = _run(_geo_args(shared_data, tmp_path / "a", "--init-weights", str(start), *tiny))
    assert result.exit_code == 0, result.stderr
    plain = _run(_geo_args(shared_data, tmp_path / "b", *tiny))
    assert plain.exit_code == 0, plain.stderr
    ref = load_weights(start).encoder.state_dict()
    tuned = load_weights(tmp_path / "a" / "weights.safetensors")
    fresh = load_weights(tmp_path / "b" / "weights.safetensors").encoder.state_dict()
    floats = [k for k, v in ref.items() if v.is_floating_point() and "running" not in k]
    assert all(torch.allclose(tuned.encoder.state_dict()[k], ref[k], atol=1e-6) for k in floats)
    assert not all(torch.allclose(fresh[k], ref[k], atol=1e-3) for k in floats)
    recorded = tuned.metadata["training"]["init_weights"]
    assert recorded == {  # the file's name: a weights file names no folder of this machine
        "file": start.name,
        "sha256": hashlib.sha256(start.read_bytes()).hexdigest(),
    }
    saved = json.loads((tmp_path / "a" / "config.json").read_text())
    assert saved["config"]["init_weights"] == str(start)


@pytest.mark.parametrize("case", ["missing", "voxel", "no_geometric"])
def test_bad_init_weights_are_exit_1_naming_the_file(shared_data, tmp_path, case):
    if case == "missing":
        path, extra, phrase = tmp_path / "none.safetensors", [], "no such file"
    elif case == "voxel":
        path = _weights_file(tmp_path / "w5.safetensors", seed=1, voxel_size=0.05)
        extra, phrase = [], "voxel size"
    else:
        path = _weights_file(tmp_path / "w.safetensors", seed=1)
        extra, phrase = ["--variant", "byoc-vis"], "no geometric encoder"
    result = _run(_geo_args(shared_data, tmp_path / "run", "--init-weights", str(path), *extra))
    assert result.exit_code == 1, result.stderr
    lines = [ln for ln in result.stderr.splitlines() if ln.startswith("byoc: error")]
    assert len(lines) == 1 and str(path) in lines[0] and phrase in lines[0], result.stderr
    assert not (tmp_path / "run" / "weights.safetensors").exists()


def test_defaults_fine_tune_the_shipped_weights_and_bar_and_summary_agree(
    shared_data, tmp_path, monkeypatch
):
    """``byoc train --rgbd-dir SEQ --steps 3 --out run``, no other flag: the shipped recipe
    (self-posed, a fine-tune of the shipped weights), which learns on a CPU; off a terminal
    the progress is plain lines (the self-posed pairs' stages first), and the one metrics
    line's loss is the summary's."""
    import re

    monkeypatch.chdir(tmp_path)
    data = shared_data / "rgbd" / "tum_fr1_xyz"
    result = _run(["--rgbd-dir", str(data), "--steps", "3", "--out", "run"])
    assert result.exit_code == 0, result.stderr
    config = json.loads((tmp_path / "run" / "config.json").read_text())["config"]
    assert config["variant"] == "self-posed" and config["init_weights"] == "shipped"
    assert (config["batch_size"], config["lr"], config["crop_radius"]) == (2, 1e-4, 0.6)
    lines = result.stderr.splitlines()
    assert lines[0].startswith("byoc: self-posed pairs: reading frames 1/"), lines[0]
    bar = re.findall(r"step 3: loss (\d+\.\d{4})", result.stderr)
    summary = re.findall(r"trained 3 steps in run: loss (\S+) \(the mean of its one", lines[-1])
    assert bar and summary and bar[-1] == summary[0], result.stderr
    records = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    last = [json.loads(r) for r in records if '"train"' in r][-1]
    assert f"{last['loss']:.4f}" == bar[-1]


def test_a_random_start_and_the_paper_variants_keep_their_defaults():
    from byoc_cli.training.config import resolve_config

    assert resolve_config({}, {"init_weights": "none"}).init_weights is None
    paper = resolve_config({}, {"variant": "byoc-geo"})
    assert (paper.steps, paper.batch_size, paper.crop_radius, paper.init_weights) == (
        200_000,
        8,
        0.0,
        None,
    )
    # the shipped weights cannot start another architecture: a random start then
    assert resolve_config({}, {"arch": "minkunet34c"}).init_weights is None
    assert resolve_config({"batch_size": 4}, {}).batch_size == 4  # the file over the recipe


def test_too_few_pairs_names_the_option_to_change(shared_data, tmp_path):
    data = shared_data / "rgbd" / "tum_fr1_xyz"  # 10 frames
    args = ["--rgbd-dir", str(data), "--variant", "byoc-geo", "--steps", "1", "--device", "cpu"]
    result = _run([*args, "--out", str(tmp_path / "run")])
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "set --view-spacing 2 or less (8 pairs)" in lines[0]
    result = _run([*args, "--batch-size", "10", "--out", str(tmp_path / "run")])
    assert "set --batch-size 9 or less (at --view-spacing 1)" in result.stderr


def _corrupt_sequence(shared_data, root):
    """tum_fr1_xyz's layout with every depth frame replaced by bytes that are no image."""
    import shutil

    data = shared_data / "rgbd" / "tum_fr1_xyz"
    (root / "depth").mkdir(parents=True)
    for name in ("depth.txt", "intrinsics.json"):
        shutil.copy(data / name, root / name)
    for png in (data / "depth").iterdir():
        (root / "depth" / png.name).write_bytes(b"not a png\n")
    return root


@pytest.mark.parametrize("variant", ["self-posed", "byoc-geo"])
def test_a_run_whose_frames_are_all_corrupt_leaves_no_run_folder(shared_data, tmp_path, variant):
    data = _corrupt_sequence(shared_data, tmp_path / "seq")
    out = tmp_path / "new" / "run"
    args = ["--rgbd-dir", str(data), "--variant", variant, "--steps", "2", "--device", "cpu"]
    args += ["--batch-size", "1", "--view-spacing", "2", "--num-workers", "0"]
    result = _run([*args, "--out", str(out)])
    assert result.exit_code == 1, result.output
    assert "not an image file" in result.stderr and "Traceback" not in result.output
    assert not (tmp_path / "new").exists()  # nor the parent the run would have made
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _run([*args, "--out", str(empty)]).exit_code == 1
    assert list(empty.iterdir()) == []

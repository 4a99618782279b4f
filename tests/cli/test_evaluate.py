"""`byoc eval-fmr` / `byoc eval-pairs` end to end, checked against a brute-force reference."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from byoc_cli.cli.evaluate import expand_method_args
from byoc_cli.cli.main import cli
from byoc_cli.evaluation.cache import FeatureCache, file_identity
from tests.evaluation import _reference as ref

SCENE = "7-scenes-redkitchen"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _invoke(args: list[str]):
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module", params=["3DMatch", "3DLoMatch"])
def fmr_run(request, shared_data, tmp_path_factory):
    """One CLI run per sample benchmark (the bar command, plus gt.info, a cache and a plot)."""
    suite = request.param
    tmp = tmp_path_factory.mktemp(f"fmr_{suite}")
    root = shared_data / "3dmatch" / "sample" / suite
    gt_dir = shared_data / "3dmatch" / "benchmarks" / suite
    args = [
        "eval-fmr", root, "--method", "byoc-random", "fpfh-ransac", "--json", tmp / "report.json",
        "--cache-dir", tmp / "cache", "--gt-dir", gt_dir, "--plot", tmp / "plot.png",
    ]  # fmt: skip
    result = _invoke(args)
    assert result.exit_code == 0, result.output
    report = json.loads((tmp / "report.json").read_text())
    return {"suite": suite, "root": root, "gt_dir": gt_dir, "tmp": tmp, "args": args,
            "result": result, "report": report}  # fmt: skip


def _features(cache_dir: Path, method: dict, path: Path):
    identity = {k: v for k, v in method["features"].items() if k != "key"}

    def fail():
        raise AssertionError(f"features of {path} not in the cache")

    cloud = FeatureCache(cache_dir).get(identity, file_identity(path), fail)
    return cloud.points.numpy(), cloud.feats.numpy()


@pytest.mark.realdata
def test_eval_fmr_agrees_with_brute_force_reference(fmr_run):
    """Every per-pair and summary figure of the bar command, recomputed independently on the
    same (cached) features: numpy full distance matrices, explicit tie handling."""
    report, root = fmr_run["report"], fmr_run["root"]
    result = fmr_run["result"]
    assert result.stdout == ""
    assert "FMR % (pooled)" in result.stderr and "fpfh-ransac" in result.stderr
    logs = ref.parse_blocks(root / f"{SCENE}-evaluation" / "gt.log", 4)
    infos = ref.parse_blocks(fmr_run["gt_dir"] / SCENE / "gt.info", 6)
    assert report["num_pairs"] == len(logs) == {"3DMatch": 3, "3DLoMatch": 5}[fmr_run["suite"]]
    assert [(r["i"], r["j"]) for r in report["pairs"]] == list(logs)
    settings = report["settings"]
    assert (settings["tau1"], settings["tau2"], settings["num_samples"]) == (0.1, 0.05, 5000)
    assert report["versions"]["byoc_cli"] and report["versions"]["torch"]
    assert report["versions"]["open3d"] and set(report["protocols"]) >= {"fmr-fcgf", "rr-3dmatch"}
    methods = {m["name"]: m for m in report["methods"]}
    assert list(methods) == ["byoc-random", "fpfh-ransac"]
    assert methods["byoc-random"]["features_info"]["source"] == "random-init"

    tau1, tau2, k, seed = settings["tau1"], settings["tau2"], settings["top_k"], report["seed"]
    flags: dict[str, list[bool]] = {"byoc-random": [], "fpfh": []}
    corr_flags: dict[str, list[bool]] = {"byoc-random": [], "fpfh": []}
    for record in report["pairs"]:
        i, j = record["i"], record["j"]
        T_gt = logs[(i, j)]
        pseed = ref.pair_seed(seed, SCENE, i, j)
        for name in ("byoc-random", "fpfh-ransac"):
            key = methods[name]["features"]["key"]
            got = record["features"][key]
            ps, fs = _features(
                fmr_run["tmp"] / "cache", methods[name], root / SCENE / f"cloud_bin_{j}.ply"
            )
            pt, ft = _features(
                fmr_run["tmp"] / "cache", methods[name], root / SCENE / f"cloud_bin_{i}.ply"
            )
            idx_s, idx_t = ref.sample(len(ps), len(pt), settings["num_samples"], pseed)
            ps, fs, pt, ft = ps[idx_s], fs[idx_s], pt[idx_t], ft[idx_t]
            lo, hi, count = ref.nn_inlier_bounds(ps, fs, pt, ft, T_gt, tau1)
            assert got["num_matches"] == count
            inliers = round(got["inlier_ratio"] * count)
            assert lo <= inliers <= hi, (name, i, j, lo, inliers, hi)
            # near-tied feature neighbours (random byoc features are nearly constant on
            # smooth surfaces) leave a narrow range; it must stay informative
            assert hi - lo <= 0.02 * count
            assert got["recalled"] == (inliers / count >= tau2)
            assert (lo / count >= tau2) == (hi / count >= tau2) == got["recalled"]
            clo, chi, ccount = ref.corr_inlier_bounds(ps, fs, pt, ft, T_gt, tau1, k)
            assert got["num_correspondences"] == ccount
            cinliers = round(got["corr_inlier_ratio"] * ccount)
            assert clo <= cinliers <= chi, (name, i, j, clo, cinliers, chi)
            assert (clo / ccount >= tau2) == (chi / ccount >= tau2) == got["corr_recalled"]
            assert chi - clo <= 0.02 * ccount
            flags[key].append(got["recalled"])
            corr_flags[key].append(got["corr_recalled"])

    # summaries: per scene (one scene here), mean and std over scenes, pooled
    for name in ("byoc-random", "fpfh-ransac"):
        key = methods[name]["features"]["key"]
        summary = report["results"][name]
        expected = float(np.mean(flags[key]))
        assert summary["fmr"]["pooled"] == pytest.approx(expected)
        assert summary["fmr"]["mean_over_scenes"] == pytest.approx(expected)
        assert summary["fmr"]["std_over_scenes"] == 0.0
        assert summary["fmr"]["per_scene"][SCENE]["num_pairs"] == len(logs)
        assert summary["corr_fmr"]["pooled"] == pytest.approx(float(np.mean(corr_flags[key])))

        # registration: official RMSE from gt.info, recall over j - i > 1, pose errors
        rmses, registered, rot, trans, success = [], [], [], [], []
        for record in report["pairs"]:
            got = record["methods"][name]
            T_est, T_gt = np.array(got["T_est"]), logs[(record["i"], record["j"])]
            expected_rmse = ref.rmse(T_est, T_gt, infos[(record["i"], record["j"])])
            # gt.log rotations are orthonormal to ~5e-4 only: the two quaternion methods
            # (Shepperd / eigenvector) then differ slightly
            assert got["rmse_m"] == pytest.approx(expected_rmse, rel=1e-4, abs=1e-9)
            assert got["registered"] == (expected_rmse <= 0.2)
            assert record["official"] == (record["j"] - record["i"] > 1)
            rot.append(ref.rotation_error_deg(T_est, T_gt))
            trans.append(100 * np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))
            success.append(rot[-1] < 15 and trans[-1] < 30)
            if record["official"]:
                rmses.append(expected_rmse)
                registered.append(expected_rmse <= 0.2)
        rr = summary["registration_recall"]
        assert rr["num_pairs"] == len(registered)
        assert rr["pooled"] == pytest.approx(float(np.mean(registered)))
        assert summary["success_rate"]["pooled"] == pytest.approx(float(np.mean(success)))
        assert summary["rotation_error_deg"]["mean"] == pytest.approx(float(np.mean(rot)))
        assert summary["rotation_error_deg"]["median"] == pytest.approx(float(np.median(rot)))
        assert summary["translation_error_cm"]["median"] == pytest.approx(float(np.median(trans)))
    assert (fmr_run["tmp"] / "plot.png").read_bytes().startswith(PNG_MAGIC)


def _untimed(report: dict) -> dict:
    out = json.loads(json.dumps(report))
    out.pop("seconds")
    out.pop("cache")
    for summary in out["results"].values():
        summary.pop("seconds_per_pair")
    for record in out["pairs"]:
        for method in record["methods"].values():
            method.pop("seconds")
    return out


@pytest.mark.realdata
def test_eval_fmr_rerun_reads_the_cache(fmr_run):
    first = fmr_run["report"]
    fragments = {p for r in first["pairs"] for p in (r["i"], r["j"])}
    assert first["cache"] == {"hits": 0, "misses": 2 * len(fragments)}
    args = list(fmr_run["args"])
    args[args.index("--json") + 1] = fmr_run["tmp"] / "again.json"
    result = _invoke(args)
    assert result.exit_code == 0, result.output
    second = json.loads((fmr_run["tmp"] / "again.json").read_text())
    assert second["cache"] == {"hits": 2 * len(fragments), "misses": 0}
    assert "feature cache: " + str(2 * len(fragments)) + " read, 0 computed" in result.stderr
    assert _untimed(second) == _untimed(first)


@pytest.mark.realdata
def test_eval_fmr_without_gt_info_and_with_limit_scenes(shared_data, tmp_path):
    root = shared_data / "3dmatch" / "sample" / "3DMatch"
    result = _invoke(
        ["eval-fmr", root, "--method", "identity,fpfh-procrustes", "--limit", "1",
         "--scenes", SCENE, "--json", "-", "--num-samples", "1000", "--quiet"]
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert result.stderr == ""
    report = json.loads(result.stdout)
    assert report["num_pairs"] == 1 and report["num_pairs_listed"] == 3
    assert report["results"]["identity"]["fmr"] is None
    assert report["results"]["fpfh-procrustes"]["registration_recall"] is None
    assert report["results"]["fpfh-procrustes"]["fmr"]["num_pairs"] == 1
    bad = _invoke(["eval-fmr", root, "--scenes", "kitchen", "--method", "identity"])
    assert bad.exit_code == 2 and "unknown scene 'kitchen'" in bad.stderr


def _copy_sample(shared_data: Path, tmp_path: Path) -> Path:
    root = tmp_path / "3DMatch"
    shutil.copytree(shared_data / "3dmatch" / "sample" / "3DMatch", root)
    return root


@pytest.mark.realdata
def test_eval_fmr_missing_fragment(shared_data, tmp_path):
    root = _copy_sample(shared_data, tmp_path)
    (root / SCENE / "cloud_bin_21.ply").unlink()
    result = _invoke(["eval-fmr", root, "--method", "identity"])
    assert result.exit_code == 1
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("byoc: error: ") and "cloud_bin_21.ply: fragment not found" in line
    assert "gt.log line 11" in line
    out = tmp_path / "r.json"
    result = _invoke(["eval-fmr", root, "--method", "identity", "--allow-missing", "--json", out])
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    assert report["num_pairs"] == 2 and report["num_pairs_skipped_missing"] == 1
    assert report["missing_fragments"] == [str(root / SCENE / "cloud_bin_21.ply")]
    assert "1 pair(s) skipped" in result.stderr


@pytest.mark.realdata
def test_eval_fmr_malformed_gt_log(shared_data, tmp_path):
    root = _copy_sample(shared_data, tmp_path)
    gt_log = root / f"{SCENE}-evaluation" / "gt.log"
    lines = gt_log.read_text().splitlines()
    lines[7] = "0.1 0.2 oops 0.4"
    gt_log.chmod(0o644)
    gt_log.write_text("\n".join(lines) + "\n")
    result = _invoke(["eval-fmr", root, "--method", "identity"])
    assert result.exit_code == 1
    assert result.stderr.strip() == (
        f"byoc: error: {gt_log}: line 8: not a number in '0.1 0.2 oops 0.4'"
    )


def test_eval_fmr_bad_inputs(tmp_path):
    result = _invoke(["eval-fmr", tmp_path / "nowhere", "--method", "identity"])
    assert result.exit_code == 1
    assert result.stderr.strip() == (
        f"byoc: error: {tmp_path / 'nowhere'}: benchmark folder does not exist"
    )
    result = _invoke(["eval-fmr", tmp_path, "--method", "identity"])
    assert result.exit_code == 1 and "no 3DMatch scene found" in result.stderr
    result = _invoke(["eval-fmr", tmp_path, "--method", "byoc", "sift"])
    assert result.exit_code == 2  # 'sift' is not a method: taken as an extra argument
    result = _invoke(["eval-fmr", tmp_path, "--method", "byoc,sift"])
    assert result.exit_code == 2 and "unknown method 'sift'" in result.stderr
    result = _invoke(["eval-fmr", tmp_path, "--method", "identity", "--weights", "w.st"])
    assert result.exit_code == 2 and "--weights is for --method byoc" in result.stderr
    result = _invoke(
        ["eval-fmr", tmp_path, "--method", "identity", "--json", tmp_path / "no" / "r.json"]
    )
    assert result.exit_code == 1 and "the folder does not exist" in result.stderr


def test_method_lists_on_the_command_line():
    assert expand_method_args(["R", "--method", "byoc", "fpfh-ransac", "--json", "x"]) == [
        "R", "--method", "byoc", "--method", "fpfh-ransac", "--json", "x",
    ]  # fmt: skip
    assert expand_method_args(["--method", "byoc", "icp-plane,identity", "R"]) == [
        "--method", "byoc", "--method", "icp-plane,identity", "R",
    ]  # fmt: skip
    assert expand_method_args(["--method=byoc", "identity"]) == [
        "--method=byoc", "--method", "identity",
    ]  # fmt: skip
    assert expand_method_args(["--", "--method", "byoc", "identity"]) == [
        "--", "--method", "byoc", "identity",
    ]  # fmt: skip


# ================================================================== eval-pairs


@pytest.mark.realdata
def test_eval_pairs_rgbd_table_json_plot(shared_data, tmp_path):
    plot = tmp_path / "pairs.png"
    result = _invoke(
        ["eval-pairs", "--rgbd-dir", shared_data / "rgbd" / "tum_fr1_desk", "--spacing", "2",
         "--limit", "2", "--method", "identity", "icp-plane", "fpfh-ransac", "byoc",
         "--json", "-", "--plot", plot, "--seed", "3"]
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["num_pairs"] == 2 and report["seed"] == 3
    assert list(report["results"]) == ["identity", "icp-plane", "fpfh-ransac", "byoc"]
    assert report["sources"][0]["layout"] == "tum"
    assert set(report["protocols"]) == {"pairs", "rotation", "translation", "chamfer"}
    assert report["versions"]["open3d"]
    ident = report["results"]["identity"]
    assert ident["rotation_deg"]["mean"] == pytest.approx(
        report["gt_motion"]["rotation_deg"]["mean"]
    )
    for name, summary in report["results"].items():
        for key in ("rotation_deg", "translation_cm", "chamfer"):
            assert summary[key]["mean"] is not None and summary[key]["median"] is not None, name
    table = result.stderr
    assert "rotation acc % < 5 °" in table and "chamfer median" in table
    assert "byoc: the weights that ship with byoc-cli" in table
    assert plot.read_bytes().startswith(PNG_MAGIC)


@pytest.mark.realdata
def test_eval_pairs_prepared_and_several_weights(shared_data, tmp_path):
    for name, seed in (("a", "1"), ("b", "2")):
        init = _invoke(["weights", "init", "--seed", seed, "-o", tmp_path / f"{name}.safetensors"])
        assert init.exit_code == 0, init.output
    out = tmp_path / "r.json"
    result = _invoke(
        ["eval-pairs", "--pairs-dir", shared_data / "pairs" / "3dmatch_demo",
         "--method", "byoc", "--method", "identity", "--weights", tmp_path / "a.safetensors",
         "--weights", tmp_path / "b.safetensors", "--json", out]
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    assert list(report["results"]) == ["byoc[a]", "byoc[b]", "identity"]
    # the table's column labels are printed as text, not swallowed as rich markup
    assert "byoc[a]" in result.output and "byoc[b]" in result.output
    assert report["num_pairs"] == 1
    shas = {m["features"]["tensors_sha256"] for m in report["methods"] if m["kind"] == "byoc"}
    assert len(shas) == 2
    rot = report["pairs"][0]["methods"]
    assert not math.isclose(
        rot["byoc[a]"]["rotation_error_deg"], rot["byoc[b]"]["rotation_error_deg"]
    )


def test_eval_pairs_bad_inputs(tmp_path):
    result = _invoke(["eval-pairs", "--method", "identity"])
    assert result.exit_code == 2 and "--rgbd-dir" in result.stderr
    result = _invoke(["eval-pairs", "--rgbd-dir", tmp_path / "none", "--method", "identity"])
    assert result.exit_code == 1
    assert result.stderr.strip() == f"byoc: error: {tmp_path / 'none'}: folder does not exist"
    result = _invoke(["eval-pairs", "--pairs-dir", tmp_path, "--method", "identity"])
    assert result.exit_code == 1 and "no prepared pair found" in result.stderr


@pytest.mark.parametrize("command", ["eval-fmr", "eval-pairs"])
def test_method_help_lists_every_method_of_the_registry(command):
    from byoc_cli.evaluation.methods import METHOD_NAMES

    result = CliRunner().invoke(cli, [command, "--help"], terminal_width=400)
    text = " ".join(result.output.split())
    assert f"one table column each: {', '.join(METHOD_NAMES)}." in text
    assert "byoc-random" in METHOD_NAMES

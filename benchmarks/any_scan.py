"""`byoc register` with no flags on scans at other scales, densities and noise levels.

Development pairs with ground truth (the demo pair and the 3DMatch sample's 3DMatch pairs),
each made into variants at run time: coordinates scaled by 0.01 to 100; thinned to 1/2, 1/4
and 1/8 of their points by random dropout (both clouds, or the source alone); Gaussian noise
of 0.25 and 0.5 of the 2.5 cm voxel on every coordinate. Each variant is registered in
process with the Python API and the CLI's defaults (`byoc_cli.register`, the same T as
`byoc register A B`), and judged against the ground truth: rotation within 5 deg, translation
within 10 cm times the scale (scaled copies: 10 % of the scan's extent as well).

Prints one row per variant and method: pairs right, wrong results that would exit 0 (confidence
at or above the default --min-confidence), median rotation / translation error, the median
voxel chosen, and time against the unscaled pair's (scaled copies). Methods: byoc, fpfh, and
byoc+fpfh (the learned features with the FPFH fallback below the default --min-confidence).

Usage: python benchmarks/any_scan.py [--methods byoc fpfh byoc+fpfh] [--variants scale thin noise]
    [--weights W.safetensors] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from byoc_cli.api import Registrar, load_cloud
from byoc_cli.io.threedmatch import read_gt_log
from byoc_cli.pipeline.confidence import DEFAULT_MIN_CONFIDENCE

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
DEMO = DATA / "pairs" / "3dmatch_demo"
SAMPLE = DATA / "3dmatch" / "sample" / "3DMatch"
SCALES = (0.01, 0.1, 10.0, 100.0)
THIN = (2, 4, 8)
NOISE = (0.25, 0.5)  # of the 2.5 cm voxel
VOXEL = 0.025


def pairs() -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(name, source (N, 3), target (M, 3), T_tgt_src)`` of the development pairs."""
    out = [
        (
            "demo",
            load_cloud(DEMO / "source.ply"),
            load_cloud(DEMO / "target.ply"),
            np.loadtxt(DEMO / "T_gt.txt"),
        )
    ]
    scene = SAMPLE / "7-scenes-redkitchen"
    for rec in read_gt_log(SAMPLE / "7-scenes-redkitchen-evaluation" / "gt.log"):
        i, j = rec.i, rec.j
        out.append(
            (
                f"kitchen {j}->{i}",
                load_cloud(scene / f"cloud_bin_{j}.ply"),
                load_cloud(scene / f"cloud_bin_{i}.ply"),
                rec.T_tgt_src,
            )
        )
    return out


def variants(kinds: list[str]) -> list[tuple[str, dict]]:
    """``(label, recipe)``: scale s, thin k (both or source only), noise sigma in voxels."""
    out = [("original", {})]
    if "scale" in kinds:
        out += [(f"x{s:g}", {"scale": s}) for s in SCALES]
    if "thin" in kinds:
        for k in THIN:
            out += [(f"1/{k} both", {"thin": k, "both": True})]
            out += [(f"1/{k} source", {"thin": k, "both": False})]
    if "noise" in kinds:
        out += [(f"noise {n:g} voxel", {"noise": n}) for n in NOISE]
    return out


def make(src: np.ndarray, tgt: np.ndarray, recipe: dict, seed: int):
    """The variant of a pair: ``(source, target, scale)``."""
    rng = np.random.default_rng(seed)
    k = recipe.get("thin")
    if k:
        src = src[np.sort(rng.permutation(len(src))[: len(src) // k])]
        if recipe["both"]:
            tgt = tgt[np.sort(rng.permutation(len(tgt))[: len(tgt) // k])]
    sigma = recipe.get("noise", 0.0) * VOXEL
    if sigma:
        src = src + rng.normal(0, sigma, src.shape)
        tgt = tgt + rng.normal(0, sigma, tgt.shape)
    s = recipe.get("scale", 1.0)
    return src * s, tgt * s, s


def errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """Rotation (deg) and translation (units of T) of ``inv(T) @ T_gt``."""
    D = np.linalg.inv(T) @ T_gt
    cos = np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(D[:3, 3]))


def run(method: str, src, tgt, registrar: Registrar) -> dict:
    start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = registrar.register(src, tgt)
    except Exception as exc:  # a refusal is a result of its own
        return {"error": str(exc), "seconds": time.perf_counter() - start}
    return {
        "T": result.T_tgt_src,
        "voxel": result.voxel_size,
        "confidence": result.confidence,
        "seconds": time.perf_counter() - start,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", nargs="+", default=["byoc", "fpfh"])
    parser.add_argument("--variants", nargs="+", default=["scale", "thin", "noise"])
    parser.add_argument("--json", type=Path, default=None, help="write every row here")
    parser.add_argument("--weights", type=Path, default=None, help="for byoc (default: shipped)")
    args = parser.parse_args(argv)
    data = pairs()
    rows = []
    for method in args.methods:
        features, _, fallback = method.partition("+")
        weights = args.weights if features == "byoc" else None
        registrar = Registrar(features, weights=weights, device="cpu", fallback=fallback or None)
        base_time: dict[str, float] = {}
        for label, recipe in variants(args.variants):
            cells = []
            for index, (name, src0, tgt0, T_gt) in enumerate(data):
                src, tgt, s = make(src0, tgt0, recipe, seed=index)
                out = run(method, src, tgt, registrar)
                extent = float(np.max(tgt.max(0) - tgt.min(0)))
                cell = {"pair": name, "variant": label, "method": method, "scale": s}
                cell["seconds"] = out["seconds"]
                if "error" in out:
                    cell.update(error=out["error"], right=False)
                else:
                    T_gt_s = T_gt.copy()
                    T_gt_s[:3, 3] *= s
                    rot, trans = errors(out["T"], T_gt_s)
                    cell.update(
                        rot_deg=rot,
                        trans=trans / s,
                        voxel=out["voxel"] / s,
                        confidence=out["confidence"],
                        right=rot < 5.0 and trans < 0.10 * s,
                        right_extent=rot < 5.0 and trans < 0.10 * extent,
                        passed=out["confidence"] >= DEFAULT_MIN_CONFIDENCE,
                    )
                if label == "original":
                    base_time[name] = out["seconds"]
                cell["time_ratio"] = out["seconds"] / base_time[name]
                cells.append(cell)
            rows += cells
            ok = [c for c in cells if "rot_deg" in c]

            def med(key: str, cs: list = ok) -> float:
                return statistics.median(c[key] for c in cs) if cs else float("nan")

            print(
                f"{method:9s} {label:16s} right {sum(c['right'] for c in cells)}/{len(cells)}"
                f"  wrong exit 0 {sum(c.get('passed', False) and not c['right'] for c in cells)}"
                f"  rot {med('rot_deg'):6.2f} deg  trans {100 * med('trans'):6.1f} cm"
                f"  voxel {100 * med('voxel'):5.2f} cm  time x{med('time_ratio'):.2f}"
                f"  refused {len(cells) - len(ok)}",
                flush=True,
            )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())

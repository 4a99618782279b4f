"""The fit of what is not floor, ceiling or wall (geometry/structure.py) on right and wrong
results: the measurement of docs/experiments/2026-11-27-room-structure-cue.md.

* ``rooms SUMMARY.jsonl ...``: each pair of each `register-batch` summary of the simulated rooms
  (benchmarks/scan_sim.py --sets room), its result judged as benchmarks/objects.py does, and
  the truth (``T_gt.txt``): the clutter fit of the result and of the truth, the share of the
  source that is clutter, and the best clutter fit of the result turned 90, 180 and 270 deg
  about the target's up axis through the moved source's centre in the overlap.
* ``rgbd``: the same of the truth of benchmarks/init.py's Kinect / RealSense pairs
  (`_init_pairs.rgbd_pairs`) and of the 3DMatch sample's pairs (their ``gt.log``).

``--voxel`` sets the structure's voxel (m; default 0.05) and ``--radius`` the fit's radius in
voxels (default 2).

Usage: python benchmarks/structure_cue.py rooms S1.jsonl [S2.jsonl ...] [--voxel 0.05]
       python benchmarks/structure_cue.py rgbd [--voxel 0.05] [--limit 40]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


#: refine the turned alternatives (``--refine``)
REFINE = False


def measure(src, tgt, T, voxel: float, radius: float, truth=None):
    """``(fit of T, fit of its rival, the rival's rotation error to truth)``: of the turned
    alternatives (:func:`turned_alternatives`), the one whose clutter fits best."""
    from byoc_cli.geometry.structure import clutter_fit, turned_alternatives

    fit = clutter_fit(src, tgt, T, radius * voxel)
    alternatives = turned_alternatives(src, tgt, T, voxel)
    if REFINE:
        import torch

        from byoc_cli.pipeline.restarts import refine_starts

        ends, _ = refine_starts(
            torch.from_numpy(src.points),
            torch.from_numpy(tgt.points),
            torch.from_numpy(np.stack(alternatives)),
            voxel,
            max_source_points=2000,
        )
        alternatives = list(ends.numpy())
    fits = [clutter_fit(src, tgt, A, radius * voxel) for A in alternatives]
    best = int(np.argmax([f.clutter for f in fits]))
    rot = float("nan")
    if truth is not None:
        from objects import errors

        rot = errors(alternatives[best], truth)[0]
    return fit, fits[best], rot


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 else float("nan")


def _row(label: str, fit, alt, rot=float("nan")) -> str:
    return (
        f"{label:34s} clutter {fit.clutter:5.2f} c2c {fit.clutter_to_clutter:5.2f} "
        f"struct {fit.structure:5.2f} all {fit.overall:5.2f} share {fit.clutter_share:4.2f} "
        f"c/s {_ratio(fit.clutter, fit.structure):5.2f} "
        f"c2c/s {_ratio(fit.clutter_to_clutter, fit.structure):5.2f} | "
        f"rival: clutter {alt.clutter:5.2f} c2c {alt.clutter_to_clutter:5.2f} "
        f"struct {alt.structure:5.2f} to truth {rot:5.1f}"
    )


def rooms(args) -> None:
    from byoc_cli.api import load_cloud
    from byoc_cli.geometry.structure import structure
    from objects import right

    made = {}
    for summary in args.summaries:
        print(f"# {summary}")
        for line in summary.read_text().splitlines():
            r = json.loads(line)
            folder = (summary.parent / r["source"]).parent
            if folder not in made:
                s = structure(load_cloud(folder / "source.ply", scale=1.0), args.voxel)
                t = structure(load_cloud(folder / "target.ply", scale=1.0), args.voxel)
                made[folder] = (s, t)
                truth = np.loadtxt(folder / "T_gt.txt")
                print(
                    _row(
                        f"{folder.name} truth",
                        *measure(s, t, truth, args.voxel, args.radius, truth),
                    )
                )
            s, t = made[folder]
            T = np.array(r["T_tgt_src"])
            ok, rot, _ = right(T, folder)
            verdict = f"{'right' if ok else 'WRONG'} {rot:5.1f} {r['confidence']:.2f}"
            truth = np.loadtxt(folder / "T_gt.txt")
            print(
                _row(
                    f"{folder.name[:17]} {verdict}",
                    *measure(s, t, T, args.voxel, args.radius, truth),
                )
            )


def rgbd(args) -> None:
    """Each Kinect / RealSense pair (truth refined on the data) and 3DMatch sample pair
    (``gt.log``) registered with the default ``Registrar``: the cue of the result and of the
    truth; right within 5 deg / 10 cm."""
    import warnings

    from _init_pairs import MIN_OVERLAP, errors, overlap, refined_truth, rgbd_pairs
    from byoc_cli.api import Registrar
    from byoc_cli.geometry.structure import structure

    registrar = Registrar(device="cpu")

    def pairs():
        for pair in rgbd_pairs(limit=args.limit):
            src, tgt = pair.load_source(), pair.load_target()
            voxel = registrar.choose_voxel(src, tgt).refine_voxel
            truth, _ = refined_truth(src, tgt, pair.T_gt, voxel)
            yield pair.name, src, tgt, truth, overlap(src, tgt, truth)
        for name, src, tgt, truth in threedmatch_pairs():
            yield name, src, tgt, truth, overlap(src, tgt, truth)

    for name, src, tgt, truth, shared in pairs():
        s, t = structure(src, args.voxel), structure(tgt, args.voxel)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = registrar.register(src, tgt)
        rot, trans = errors(r.T_tgt_src, truth)
        ok = rot < 5 and trans < 0.1
        tag = "determined" if shared >= MIN_OVERLAP else "no-overlap"
        print(
            _row(
                f"{name[:22]} truth ov {shared:.2f} {tag}",
                *measure(s, t, truth, args.voxel, args.radius, truth),
            )
        )
        passed = "pass" if r.passed else "fail"
        print(f"  cue structure_rival {r.cues.get('structure_rival')}")
        verdict = f"{'right' if ok else 'WRONG'} {rot:5.1f} {r.confidence:.2f} {passed}"
        print(
            _row(
                f"{name[:14]} {verdict}",
                *measure(s, t, r.T_tgt_src, args.voxel, args.radius, truth),
            )
        )
        sys.stdout.flush()


def threedmatch_pairs():
    """``(name, source, target, T_gt)`` of the 3DMatch sample's pairs (3DMatch and 3DLoMatch;
    ``gt.log``'s ``j`` is the source, ``i`` the target)."""
    from _init_pairs import DATA
    from byoc_cli.api import load_cloud
    from byoc_cli.io.threedmatch import discover_benchmark, fragment_path, read_gt_log

    for bench in ("3DMatch", "3DLoMatch"):
        for scene in discover_benchmark(DATA / "3dmatch" / "sample" / bench):
            for rec in read_gt_log(scene.gt_log):
                src, tgt = fragment_path(scene, rec.j), fragment_path(scene, rec.i)
                if src.exists() and tgt.exists():
                    name = f"{bench} {rec.j}->{rec.i}"
                    yield name, load_cloud(src), load_cloud(tgt), rec.T_tgt_src


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="step", required=True)
    p = sub.add_parser("rooms")
    p.add_argument("summaries", nargs="+", type=Path)
    q = sub.add_parser("rgbd")
    q.add_argument("--limit", type=int, default=None)
    for s in (p, q):
        s.add_argument("--voxel", type=float, default=0.05)
        s.add_argument("--radius", type=float, default=2.0)
        s.add_argument("--refine", action="store_true", help="refine the turned alternatives")
    args = parser.parse_args()
    global REFINE
    REFINE = args.refine
    {"rooms": rooms, "rgbd": rgbd}[args.step](args)


if __name__ == "__main__":
    main()

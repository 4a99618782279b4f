"""``byoc odometry --eval`` against Open3D's own RGB-D odometry, same sequences, same run.

Usage::

    nice -n 10 python benchmarks/odometry.py [--data ../shared/data] \
        [--sequences tum_fr1_desk_full tum_fr1_rpy] [--max-frames 0] [--pose-graph] \
        [--json results.json]

For each sequence:

* ``byoc odometry --eval --features fpfh`` as a separate process (whole-process wall time,
  the trajectory error from its ``--json`` report); with ``--pose-graph`` a second row with
  the keyframe pose graph;
* Open3D's ``o3d.pipelines.odometry.compute_rgbd_odometry`` frame to frame (frame k onto
  frame k-1, identity start as in Open3D's reconstruction system, chained), depth only (the
  hybrid term on a flat grey image leaves only the depth term) and, when the sequence has
  colour, with colour (hybrid term) on the frames that have a colour image; a failed step
  keeps the identity motion and is counted.

Both are scored with :mod:`byoc_cli.evaluation.trajectory` on the frames with ground truth:
ATE RMSE (rigid alignment, no scale) and RPE per second and per frame (TUM definitions).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DEFAULT_DATA = Path(
    os.environ.get("BYOC_SHARED_DATA", Path(__file__).parents[1] / "../shared/data")
)


def _scores(sequence, frames: list[int], poses: np.ndarray) -> dict:
    from byoc_cli.evaluation.trajectory import absolute_trajectory_error, relative_pose_error

    with_gt = [n for n, f in enumerate(frames) if sequence.frames[f].pose is not None]
    est = poses[with_gt]
    gt = np.stack([sequence.frames[frames[n]].pose for n in with_gt])
    stamps = [sequence.frames[frames[n]].timestamp for n in with_gt]
    out = {"ate_rmse_m": absolute_trajectory_error(est, gt).rmse}
    if all(s is not None for s in stamps):
        rpe = relative_pose_error(est, gt, np.asarray(stamps), 1.0)
        out.update(rpe_s_m=rpe.translation_rmse, rpe_s_deg=rpe.rotation_rmse_deg)
    rpe = relative_pose_error(est, gt, None, 1.0)
    out.update(rpe_f_m=rpe.translation_rmse, rpe_f_deg=rpe.rotation_rmse_deg)
    return out


def run_byoc(seq_dir: Path, max_frames: int, pose_graph: bool) -> dict:
    """``byoc odometry --eval`` in its own process; its JSON figures and wall time."""
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "odometry.json"
        cmd = [sys.executable, "-m", "byoc_cli.cli.main", "odometry", "--rgbd-dir", str(seq_dir),
               "--features", "fpfh", "--eval", "--max-frames", str(max_frames), "--quiet",
               "-o", str(Path(tmp) / "traj.txt"), "--json", str(report)]  # fmt: skip
        if pose_graph:
            cmd.append("--pose-graph")
        start = time.perf_counter()
        subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL)
        seconds = time.perf_counter() - start
        data = json.loads(report.read_text())
    ev = data["evaluation"]
    out = {
        "frames": data["num_frames"],
        "ate_rmse_m": ev["ate_m"]["rmse"],
        "rpe_f_m": ev["rpe"]["per_frame"]["translation_rmse_m"],
        "rpe_f_deg": ev["rpe"]["per_frame"]["rotation_rmse_deg"],
        "seconds": seconds,
        "failed_steps": len(data["lost_frames"]),
    }
    if "per_second" in ev["rpe"]:
        out["rpe_s_m"] = ev["rpe"]["per_second"]["translation_rmse_m"]
        out["rpe_s_deg"] = ev["rpe"]["per_second"]["rotation_rmse_deg"]
    return out


def run_open3d(sequence, max_frames: int, use_color: bool, max_depth: float = 4.0) -> dict:
    """Open3D's frame-to-frame RGB-D odometry, chained; scores and wall time."""
    import open3d as o3d

    odo = o3d.pipelines.odometry
    frames = list(range(len(sequence.frames)))
    frames = frames[:max_frames] if max_frames else frames
    K = sequence.K
    start = time.perf_counter()

    def rgbd(i: int):
        depth = sequence.read_depth(i).astype(np.float32)
        h, w = depth.shape
        color = sequence.read_color(i) if use_color else np.full((h, w, 3), 128, np.uint8)
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(color)),
            o3d.geometry.Image(depth),
            depth_scale=1.0,
            depth_trunc=max_depth,
            convert_rgb_to_intensity=True,
        ), (w, h)

    previous, (w, h) = rgbd(frames[0])
    intrinsic = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    option = odo.OdometryOption(depth_max=max_depth)
    jacobian = odo.RGBDOdometryJacobianFromHybridTerm()
    poses, failed = [np.eye(4)], 0
    for f in frames[1:]:
        current, _ = rgbd(f)
        ok, T_prev_cur, _ = odo.compute_rgbd_odometry(
            current, previous, intrinsic, np.eye(4), jacobian, option
        )
        if not ok:
            failed += 1
            T_prev_cur = np.eye(4)
        poses.append(poses[-1] @ np.asarray(T_prev_cur))
        previous = current
    seconds = time.perf_counter() - start
    return {
        "frames": len(frames),
        **_scores(sequence, frames, np.asarray(poses)),
        "seconds": seconds,
        "failed_steps": failed,
    }


def _row(name: str, r: dict) -> str:
    def f(key, fmt):
        value = r.get(key)
        return "-" if value is None or value != value else format(value, fmt)

    return (
        f"{name:<50} {r['frames']:>6} {f('ate_rmse_m', '.3f'):>8} {f('rpe_s_m', '.3f'):>8} "
        f"{f('rpe_s_deg', '.2f'):>8} {f('rpe_f_m', '.4f'):>8} {f('rpe_f_deg', '.2f'):>8} "
        f"{r['seconds']:>7.1f} {r['frames'] / r['seconds']:>6.1f} {r['failed_steps']:>6}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--sequences", nargs="+", default=["tum_fr1_desk_full", "tum_fr1_rpy"])
    parser.add_argument("--max-frames", type=int, default=0)
    parser.add_argument("--pose-graph", action="store_true", help="also byoc --pose-graph")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from byoc_cli.io.rgbd import discover_sequences

    header = (
        f"{'sequence / method':<50} {'frames':>6} {'ATE m':>8} {'RPE m/s':>8} {'deg/s':>8} "
        f"{'m/frame':>8} {'deg/fr':>8} {'seconds':>7} {'fps':>6} {'failed':>6}"
    )
    print(header)
    results = {}
    for name in args.sequences:
        seq_dir = args.data / "rgbd" / name
        sequence = discover_sequences(seq_dir)[0]
        rows = {"byoc odometry": run_byoc(seq_dir, args.max_frames, False)}
        if args.pose_graph:
            rows["byoc odometry --pose-graph"] = run_byoc(seq_dir, args.max_frames, True)
        rows["open3d rgbd odometry (depth)"] = run_open3d(sequence, args.max_frames, False)
        if any(frame.color_path is not None for frame in sequence.frames):
            # the frames with a colour image (TUM: within 20 ms of the depth stamp)
            colored = discover_sequences(seq_dir, require_color=True)[0]
            rows[f"open3d rgbd odometry (colour, {len(colored)} fr)"] = run_open3d(
                colored, args.max_frames, True
            )
        for method, r in rows.items():
            print(_row(f"{name}: {method}", r), flush=True)
        results[name] = rows
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()

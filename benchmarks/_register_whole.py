"""Whole processes of `benchmarks/register.py` (`--only batch`, `--only whole`): pairs per second
of `byoc register-batch` against a loop of single `byoc register` processes, and whole
`byoc register` processes, the default against `--features fpfh`.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _register_common import BYOC, source_env


def _sample_pairs(folder: Path) -> list[tuple[Path, Path]]:
    """Every pair of the ``cloud_bin_*.ply`` fragments of ``folder``."""
    import itertools

    clouds = sorted(folder.glob("cloud_bin_*.ply"))
    pairs = list(itertools.combinations(clouds, 2))
    if not pairs:
        raise SystemExit(f"no cloud_bin_*.ply pairs in {folder} (set BYOC_SHARED_DATA)")
    return pairs


def _timed_batch(
    listing: Path, out: Path, extra: list[str], source: Path | None = None
) -> tuple[float, float]:
    """Wall and CPU seconds of one `byoc register-batch` process (``source``: of that tree)."""
    start = time.perf_counter()
    proc = subprocess.Popen(
        [*BYOC, "register-batch", str(listing), "--out-dir", str(out), *extra],
        env=source_env(source),
    )
    _, status, usage = os.wait4(proc.pid, 0)
    assert os.waitstatus_to_exitcode(status) in (0, 3), status
    return time.perf_counter() - start, usage.ru_utime + usage.ru_stime


def batch_vs_loop(
    folder: Path, repeats: int, loop: bool = True, baseline: Path | None = None
) -> dict:
    """Whole-process pairs per second: `register-batch` (default, --features fpfh and the
    ``baseline`` tree's default, interleaved, ``repeats`` each) and, once, one `byoc register`
    process per pair."""
    pairs = _sample_pairs(folder)
    variants = [("default", [], None), ("fpfh", ["--features", "fpfh"], None)]
    if baseline is not None:
        variants.append(("baseline", [], baseline))
    runs: dict[str, list[tuple[float, float]]] = {name: [] for name, _, _ in variants}
    same_as_baseline = None
    with tempfile.TemporaryDirectory() as tmp:
        listing = Path(tmp) / "pairs.txt"
        listing.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        for k in range(repeats):
            for name, extra, source in variants:
                out = Path(tmp) / f"{name}{k}"
                runs[name].append(_timed_batch(listing, out, extra, source))
        if baseline is not None:
            same_as_baseline = all(
                (Path(tmp) / "default0" / f"{a.stem}__{b.stem}.txt").read_bytes()
                == (Path(tmp) / "baseline0" / f"{a.stem}__{b.stem}.txt").read_bytes()
                for a, b in pairs
            )
        loop_s, same = None, None
        if loop:
            start = time.perf_counter()
            for k, (a, b) in enumerate(pairs):
                out = Path(tmp) / f"single_{k}.txt"
                _registered(subprocess.run([*BYOC, "register", str(a), str(b), "-o", str(out)]))
            loop_s = time.perf_counter() - start
            same = all(
                (Path(tmp) / f"single_{k}.txt").read_bytes()
                == (Path(tmp) / "default0" / f"{a.stem}__{b.stem}.txt").read_bytes()
                for k, (a, b) in enumerate(pairs)
            )
    return {
        "pairs": len(pairs),
        "runs": runs,
        "loop_s": loop_s,
        "same": same,
        "same_as_baseline": same_as_baseline,
    }


def print_batch(
    folder: Path, repeats: int = 1, loop: bool = True, baseline: Path | None = None
) -> None:
    load_before = os.getloadavg()[0]
    b = batch_vs_loop(folder, repeats, loop, baseline)
    n = b["pairs"]
    print(
        f"\nwhole process, {n} pairs ({folder.name}), median of {repeats} "
        f"(load average {load_before:.2f} -> {os.getloadavg()[0]:.2f}):"
    )
    med = {}
    for name, rs in b["runs"].items():
        wall, cpu = statistics.median(r[0] for r in rs), statistics.median(r[1] for r in rs)
        med[name] = wall
        label = "`byoc register-batch`" + {
            "fpfh": " --features fpfh",
            "baseline": " (baseline)",
        }.get(name, "")
        print(f"  {label:<40} {wall:6.1f} s, CPU {cpu:6.1f} s, {n / wall:.2f} pairs/s")
    print(f"  default / fpfh wall: {med['default'] / med['fpfh']:.2f}; bar: >= 2 pairs/s")
    if b["same_as_baseline"] is not None:
        print(
            f"  default / baseline wall: {med['default'] / med['baseline']:.2f}; T files "
            f"byte-identical to the baseline's: {b['same_as_baseline']}"
        )
    if b["loop_s"] is not None:
        loop_rate = n / b["loop_s"]
        print(
            f"  loop of `byoc register`: {b['loop_s']:.1f} s, {loop_rate:.2f} pairs/s; "
            f"batch / loop {n / med['default'] / loop_rate:.2f}x; "
            f"transforms byte-identical: {b['same']}"
        )


def _registered(run: subprocess.CompletedProcess) -> None:
    """Raise unless ``byoc register`` wrote its T file: exit 0, or 3 (below the gate)."""
    if run.returncode not in (0, 3):
        raise subprocess.CalledProcessError(run.returncode, run.args)


def whole_process(src: Path, tgt: Path, repeats: int) -> None:
    """Median wall time of whole `byoc register` processes: default against --features fpfh."""
    byoc = [sys.executable, "-m", "byoc_cli.cli.main", "-q", "register", str(src), str(tgt)]
    times: dict[str, list[float]] = {"default": [], "fpfh": []}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):  # interleaved, so that load changes hit both alike
            for name, extra in (("default", []), ("fpfh", ["--features", "fpfh"])):
                start = time.perf_counter()
                _registered(subprocess.run([*byoc, *extra, "-o", str(Path(tmp) / "T.txt")]))
                times[name].append(time.perf_counter() - start)
    d, f = statistics.median(times["default"]), statistics.median(times["fpfh"])
    print(
        f"\nwhole `byoc register` process, {src.name} -> {tgt.name}, median of {repeats}:\n"
        f"  default (shipped weights): {d:.2f} s\n  --features fpfh: {f:.2f} s\n"
        f"  ratio default / fpfh: {d / f:.2f} (bar: <= 1)"
    )

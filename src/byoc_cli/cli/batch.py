"""``byoc register-batch PAIRS``: many pairs in one process (the encoder loaded once).

Each pair's T file is written atomically when the pair finishes and its line is appended to
the JSON Lines summary (flushed), so a killed run loses at most the pair in flight and a rerun
skips the pairs whose T file exists. One pair's failure is recorded and the others go on.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.batch_runner import FeatureCache, PairRunner
from byoc_cli.cli.batch_summary import (
    FAILED,
    LOW_CONFIDENCE,
    OK,
    SKIPPED,
    Summary,
    below_gate_lines,
    init_reason,
    output_key,
    pair_record,
    recorded_below,
    recorded_results,
)
from byoc_cli.cli.display import is_quiet
from byoc_cli.cli.errors import EXIT_ERROR, EXIT_LOW_CONFIDENCE, EXIT_OK, handle_errors
from byoc_cli.cli.options import (
    device_option,
    int_option,
    path_option,
    resolve_device,
    verbosity_options,
)
from byoc_cli.cli.pair_files import BatchQc, batch_qc_option, check_qc_dir
from byoc_cli.cli.pairwise import (
    check_depth_inputs,
    cloud_factors,
    init_options,
    input_options,
    registrar,
)
from byoc_cli.cli.recipe_options import PAIRWISE, build_recipe, recipe_options


class ShardType(click.ParamType):
    """``I/N`` with 1 <= I <= N: the I-th of N shards."""

    name = "I/N"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None):
        if isinstance(value, tuple):
            return value
        try:
            index, count = (int(part) for part in str(value).split("/"))
        except ValueError:
            self.fail(f"{value!r} is not I/N (for example 2/8).", param, ctx)
        if not 1 <= index <= count:
            self.fail(f"{value!r}: I must be between 1 and N.", param, ctx)
        return index, count


def _plan(pairs, out_dir: Path) -> list[tuple[Any, Path]]:
    """Each pair with its T file; two pairs writing one file is bad input."""
    from byoc_cli.errors import InputError
    from byoc_cli.io.pairlist import default_output_name

    planned, seen = [], {}
    for entry in pairs:
        output = entry.output or out_dir / default_output_name(entry.source, entry.target)
        key = output.resolve()
        if key in seen:
            raise InputError(
                output, f"is the T file of line {seen[key]} and of line {entry.line} of the list"
            )
        seen[key] = entry.line
        planned.append((entry, output))
    return planned


@click.command(
    "register-batch",
    epilog="Exit codes: 0 every pair registered (or skipped); 1 bad input, or a pair failed "
    "(the others are still registered); 2 usage error; 3 a pair registered below "
    "--min-confidence, ambiguous, inconsistent with what the scans saw, or, from an initial "
    "pose, beyond --max-correction (its T file is still written), or skipped whose recorded "
    "result did not pass; such pairs are "
    "named on stderr (the first 10, then a count).",
)
@click.argument("pairs", type=click.Path(path_type=Path, dir_okay=False))
@path_option(
    "--out-dir",
    file=False,
    default=None,
    help="Folder of the T files of lines without an output column, named "
    "<source-stem>__<target-stem>.txt [default: the list's folder]; created if missing.",
)
@path_option(
    "--summary",
    default=None,
    help="JSON Lines summary, one object per pair, appended as pairs finish "
    "[default: OUT_DIR/summary.jsonl; summary.shard-I-of-N.jsonl with --shard].",
)
@click.option(
    "--shard",
    type=ShardType(),
    default=None,
    help="Only the pairs I, I+N, I+2N, ... of the list (1 <= I <= N), for job arrays.",
)
@click.option("--overwrite", is_flag=True, help="Register pairs whose T file exists again.")
@int_option(
    "--cache-size",
    min=1,
    default=32,
    help="Clouds whose features are kept in memory for later pairs (least recently used "
    "dropped first).",
)
@init_options
@batch_qc_option
@recipe_options(*PAIRWISE)
@input_options
@device_option
@verbosity_options
@handle_errors
def register_batch(
    pairs: Path,
    out_dir: Path | None,
    summary: Path | None,
    shard: tuple[int, int] | None,
    overwrite: bool,
    cache_size: int,
    qc_dir: Path | None,
    **options: Any,
) -> None:
    """Register every pair of PAIRS, a text file of 'source target [output [init]]' lines
    ('#' comments and blank lines allowed; paths relative to the file), writing one T file
    per pair and a JSON Lines summary; every option of `byoc register` applies to each pair.

    A fourth column names a file holding the pair's initial pose (4x4, as `byoc register
    --init` takes it; the output column is then required): that pair is registered from it
    (--init-mode, --max-correction), the others without.

    A rerun skips the pairs whose T file exists (--overwrite to redo them); their results as
    the summary recorded them count towards the exit code.
    """
    from byoc_cli.errors import InputError
    from byoc_cli.io.folders import new_folders
    from byoc_cli.io.outputs import OutputSet
    from byoc_cli.io.pairlist import read_pair_list
    from byoc_cli.io.pairlist import shard as take_shard

    device = resolve_device(options["device"])
    recipe_file = options.get("recipe_path")
    recipe = build_recipe(options)
    intrinsics = options["intrinsics"]
    weights = None if recipe.features.weights is None else Path(recipe.features.weights)
    entries = read_pair_list(pairs)
    out_dir = pairs.parent if out_dir is None else out_dir
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(out_dir, "is not a folder (--out-dir)")
    # The whole list's inputs and outputs are checked whatever the shard: an output of this
    # shard may be an input of another one (or name the same file as another shard's output).
    whole = _plan(entries, out_dir)
    inputs = [
        pairs,
        intrinsics,
        weights,
        recipe_file,
        *(p for e, _ in whole for p in (e.source, e.target)),
        *(e.init for e, _ in whole if e.init is not None),
    ]
    planned = whole
    if shard is not None:
        planned = [whole[e.index] for e in take_shard(entries, shard[0] - 1, shard[1])]
    check_depth_inputs(
        [p for entry, _ in planned for p in (entry.source, entry.target)], intrinsics
    )
    check_qc_dir(qc_dir)
    if summary is None:
        name = "summary.jsonl" if shard is None else f"summary.shard-{shard[0]}-of-{shard[1]}.jsonl"
        summary = out_dir / name
    mine = {entry.index for entry, _ in planned}
    todo, skipped = [], []
    recorded = recorded_results(summary) if not overwrite else {}
    with new_folders(out_dir):  # bad input leaves no folder behind (nor a parent made here)
        policy = OutputSet(inputs)
        policy.claim(summary)
        for entry, output in whole:
            policy.claim(output)  # every output is checked before the first pair runs
            if entry.index not in mine:
                continue
            if output.exists() and not overwrite:
                skipped.append((entry, output))
            else:
                todo.append((entry, output))
        # the weights are loaded before the summary is opened: unusable weights leave nothing
        made = registrar(recipe, device) if todo else None

    counts = {OK: 0, LOW_CONFIDENCE: 0, FAILED: 0, SKIPPED: len(skipped)}
    gate = recipe.gate.min_confidence
    below: list[tuple] = []  # (entry, confidence, skipped, reason or None)
    started = time.perf_counter()
    with Summary(summary) as lines:
        for entry, output in skipped:
            earlier = recorded.get(output_key(output))
            lines.write(pair_record(entry, output, SKIPPED, recorded=earlier))
            if earlier is not None and recorded_below(earlier, gate):
                below.append((entry, earlier.get("confidence"), True, None))
        if made is not None:
            run = PairRunner(
                made,
                FeatureCache(2 * cache_size),  # clouds and their features
                {
                    "scale": options["scale"],
                    "factors": cloud_factors(options),
                    "intrinsics": intrinsics,
                    "depth_scale": options["depth_scale"],
                },
                {
                    "min_confidence": recipe.gate.min_confidence,
                    "device": device,
                    "max_correction": options.get("max_correction"),
                    "init_mode": options.get("init_mode"),
                },
                inputs,
            )
            load = {"intrinsics": intrinsics, "depth_scale": options["depth_scale"]}
            qc = None if qc_dir is None else BatchQc(qc_dir, inputs, load)
            with _Progress(len(todo)) as progress:
                for (entry, output), done in zip(todo, run.in_order(todo), strict=True):
                    record = run.finish(entry, output, done)
                    if qc is not None and record["status"] == LOW_CONFIDENCE:
                        record["qc"] = qc.write(entry.line, output, record)
                    counts[record["status"]] += 1
                    lines.write(record)
                    if record["status"] == LOW_CONFIDENCE:
                        below.append((entry, record["confidence"], False, init_reason(record)))
                    progress.advance(f"{counts[FAILED]} failed")
                    if record["status"] == FAILED:
                        click.echo(f"byoc: error: line {entry.line}: {record['error']}", err=True)
    seconds = time.perf_counter() - started
    skipped_below = sum(1 for _, _, was_skipped, _ in below if was_skipped)
    if not is_quiet(False):  # -q: the failures' lines (errors), the summary file and the code
        for line in below_gate_lines(below, gate, summary):
            click.echo(line, err=True)
        skipped_note = ""
        if skipped_below:
            skipped_note = f"; {skipped_below} of them below --min-confidence as recorded"
        click.echo(
            f"byoc: {counts[OK]} registered, {counts[LOW_CONFIDENCE]} below --min-confidence, "
            f"{counts[FAILED]} failed, {counts[SKIPPED]} skipped (T file exists{skipped_note}); "
            f"summary {summary}; {len(todo)} pairs in {seconds:.1f} s "
            f"({len(todo) / max(seconds, 1e-9):.2f} pairs/s)",
            err=True,
        )
    if counts[FAILED]:
        raise SystemExit(EXIT_ERROR)
    raise SystemExit(EXIT_LOW_CONFIDENCE if below else EXIT_OK)


class _Progress:
    """A progress bar with ETA on stderr (none with -q)."""

    def __init__(self, total: int) -> None:
        from byoc_cli.cli.display import is_quiet

        self.total, self.bar, self.task = total, None, None
        self.quiet = is_quiet(False)

    def __enter__(self) -> _Progress:
        if not self.quiet:
            from byoc_cli.cli.display import progress_bar

            self.bar = progress_bar("{task.fields[note]}")
            self.task = self.bar.add_task("pairs", total=self.total, note="")
        return self

    def advance(self, note: str) -> None:
        if self.bar is not None:
            self.bar.update(self.task, advance=1, note=note)

    def __exit__(self, *exc: Any) -> None:
        if self.bar is not None:
            self.bar.__exit__(None, None, None)

"""``byoc register-batch PAIRS``: many pairs in one process (the encoder loaded once).

Each pair's T file is written atomically when the pair finishes and its line is appended to
the JSON Lines summary (flushed), so a killed run loses at most the pair in flight and a rerun
skips the pairs whose T file exists. One pair's failure is recorded and the others go on.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import click

from byoc_cli.cli.display import is_quiet
from byoc_cli.cli.errors import EXIT_ERROR, EXIT_LOW_CONFIDENCE, EXIT_OK, handle_errors
from byoc_cli.cli.options import (
    device_option,
    int_option,
    path_option,
    resolve_device,
    verbosity_options,
)
from byoc_cli.cli.pairwise import (
    check_depth_inputs,
    cloud_factors,
    input_options,
    registrar,
    registration_report,
)
from byoc_cli.cli.recipe_options import PAIRWISE, build_recipe, recipe_options

log = logging.getLogger("byoc")

#: a pair's status in the summary
OK, LOW_CONFIDENCE, FAILED, SKIPPED = "ok", "low_confidence", "failed", "skipped"
#: pairs below the gate named on stderr at the end of a run (the others are counted)
NAMED_BELOW_GATE = 10


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


class FeatureCache:
    """The features of the last ``size`` clouds used (least recently used goes first).

    Shared by the worker threads: a cloud asked for while another thread computes it is
    waited for, not computed twice; a failed computation is not kept (each pair that asks
    again gets the error again).
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict[Any, Future] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Any, compute) -> tuple[Any, bool]:
        """``(features, was_cached)``; ``compute()`` makes them on a miss."""
        with self._lock:
            future = self._items.get(key)
            if future is not None:
                self._items.move_to_end(key)
            else:
                self._items[key] = mine = Future()
                if len(self._items) > self.size:
                    self._items.popitem(last=False)
        if future is not None:
            return future.result(), True
        try:
            value = compute()
        except BaseException as exc:
            mine.set_exception(exc)
            with self._lock:
                if self._items.get(key) is mine:
                    del self._items[key]
            raise
        mine.set_result(value)
        return value, False


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
    "--min-confidence (its T file is still written), or skipped whose recorded confidence "
    "is below it; such pairs are named on stderr (the first 10, then a count).",
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
    **options: Any,
) -> None:
    """Register every pair of PAIRS, a text file of 'source target [output]' lines
    ('#' comments and blank lines allowed; paths relative to the file), writing one T file
    per pair and a JSON Lines summary; every option of `byoc register` applies to each pair.

    A rerun skips the pairs whose T file exists (--overwrite to redo them); their results as
    the summary recorded them count towards the exit code.
    """
    from byoc_cli.errors import InputError
    from byoc_cli.io.outputs import OutputSet, new_folders
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
    ]
    planned = whole
    if shard is not None:
        planned = [whole[e.index] for e in take_shard(entries, shard[0] - 1, shard[1])]
    check_depth_inputs(
        [p for entry, _ in planned for p in (entry.source, entry.target)], intrinsics
    )
    if summary is None:
        name = "summary.jsonl" if shard is None else f"summary.shard-{shard[0]}-of-{shard[1]}.jsonl"
        summary = out_dir / name
    mine = {entry.index for entry, _ in planned}
    todo, skipped = [], []
    recorded = _recorded_results(summary) if not overwrite else {}
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
    below: list[tuple[Any, float | None, bool]] = []  # (entry, confidence, skipped)
    started = time.perf_counter()
    with _Summary(summary) as lines:
        for entry, output in skipped:
            earlier = recorded.get(_output_key(output))
            lines.write(_record(entry, output, SKIPPED, recorded=earlier))
            if earlier is not None and _below(earlier, gate):
                below.append((entry, earlier.get("confidence"), True))
        if made is not None:
            run = _PairRunner(
                made,
                FeatureCache(2 * cache_size),  # clouds and their features
                {
                    "scale": options["scale"],
                    "factors": cloud_factors(options),
                    "intrinsics": intrinsics,
                    "depth_scale": options["depth_scale"],
                },
                {"min_confidence": recipe.gate.min_confidence, "device": device},
                inputs,
            )
            with _Progress(len(todo)) as progress:
                for (entry, output), done in zip(todo, run.in_order(todo), strict=True):
                    record = run.finish(entry, output, done)
                    counts[record["status"]] += 1
                    lines.write(record)
                    if record["status"] == LOW_CONFIDENCE:
                        below.append((entry, record["confidence"], False))
                    progress.advance(f"{counts[FAILED]} failed")
                    if record["status"] == FAILED:
                        click.echo(f"byoc: error: line {entry.line}: {record['error']}", err=True)
    seconds = time.perf_counter() - started
    skipped_below = sum(1 for *_, was_skipped in below if was_skipped)
    if not is_quiet(False):  # -q: the failures' lines (errors), the summary file and the code
        for line in _below_gate_lines(below, gate, summary):
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


def _output_key(output: Path) -> str:
    """How a T file is matched with the records of earlier runs (its absolute path)."""
    return str(output.absolute())


def _recorded_results(summary: Path) -> dict[str, dict]:
    """The last registered result (status ``ok`` or ``low_confidence``) an earlier run
    recorded in ``summary`` for each T file: ``{output key: {"status", "confidence",
    "min_confidence"}}``; empty when there is no summary or it cannot be read (a line cut by
    a kill is passed over)."""
    import json

    from byoc_cli.errors import InputError
    from byoc_cli.io.inputs import open_input

    if not summary.exists():
        return {}
    found: dict[str, dict] = {}
    try:
        with open_input(summary, "report") as file:
            for raw in file:
                try:
                    record = json.loads(raw)
                except ValueError:
                    continue
                if not isinstance(record, dict) or record.get("status") not in (OK, LOW_CONFIDENCE):
                    continue
                output = record.get("output")
                if isinstance(output, str):
                    keep = ("status", "confidence", "min_confidence")
                    found[_output_key(Path(output))] = {k: record.get(k) for k in keep}
    except InputError as exc:
        log.warning("the statuses of pairs done earlier are not known: %s", exc)
    return found


def _below(recorded: dict, gate: float) -> bool:
    """Whether a recorded result is below this run's gate (its confidence against ``gate``;
    without a confidence, its recorded status)."""
    confidence = recorded.get("confidence")
    if isinstance(confidence, int | float) and not isinstance(confidence, bool):
        return confidence < gate
    return recorded.get("status") == LOW_CONFIDENCE


def _below_gate_lines(below: list, gate: float, summary: Path) -> list[str]:
    """The pairs below the gate, one line each up to :data:`NAMED_BELOW_GATE`, then a count."""
    lines = []
    for entry, confidence, was_skipped in below[:NAMED_BELOW_GATE]:
        shown = "unknown" if confidence is None else f"{confidence:.3f}"
        when = " (recorded by an earlier run; T file kept)" if was_skipped else ""
        lines.append(
            f"byoc: line {entry.line}: {entry.source} -> {entry.target}: confidence {shown} "
            f"is below --min-confidence {gate:g}{when}"
        )
    if len(below) > NAMED_BELOW_GATE:
        lines.append(
            f"byoc: and {len(below) - NAMED_BELOW_GATE} more pairs below --min-confidence "
            f"(the summary {summary} has every one)"
        )
    return lines


def _record(
    entry, output: Path, status: str, error: str | None = None, recorded: dict | None = None
) -> dict:
    """The fields every summary line has; ``recorded``: a skipped pair's result as an earlier
    run recorded it (``status``, ``confidence``, ``min_confidence``)."""
    return {
        "index": entry.index,
        "line": entry.line,
        "source": str(entry.source),
        "target": str(entry.target),
        "output": str(output),
        "status": status,
        "error": error,
        "recorded": recorded,
    }


class _PairRunner:
    """Registers pairs with the shared registrar and feature cache, on the registrar's worker
    threads (:meth:`in_order`), and writes each pair's T file (:meth:`finish`, in the
    calling thread, in list order); never raises for a bad pair (its record says why)."""

    #: pairs submitted ahead of the one being written, per worker thread
    AHEAD = 2

    def __init__(self, registrar, cache, load: dict, gate: dict, inputs) -> None:
        self.registrar, self.cache, self.load, self.inputs = registrar, cache, load, inputs
        self.min_confidence, self.device = gate["min_confidence"], gate["device"]

    def in_order(self, todo) -> Iterator[tuple[Any, float]]:
        """:meth:`compute` of every ``(entry, output)`` of ``todo``, run side by side on the
        registrar's workers (at most ``AHEAD`` per worker in flight, so a killed run loses
        only those), yielded in list order."""
        pool = self.registrar.executor()
        window = self.AHEAD * self.registrar.threads
        pending: deque[Future] = deque()
        try:
            for entry, _ in todo:
                pending.append(pool.submit(self.compute, entry))
                if len(pending) >= window:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:  # interrupted: the pairs not started yet are dropped
            for future in pending:
                future.cancel()

    def compute(self, entry) -> tuple[Any, float]:
        """``(registration or the exception, seconds)`` of one pair."""
        started = time.perf_counter()
        timings: dict[str, float] = {}
        try:
            (factor_src, factor_tgt), _ = self.load["factors"]
            cloud_src = self._cloud(entry.source, "source", factor_src, timings)
            cloud_tgt = self._cloud(entry.target, "target", factor_tgt, timings)
            choice, voxels = None, [(None, None, 1.0)] * 2
            if self.registrar.auto_voxel:
                choice = self.registrar.voxel_for(cloud_src[2], cloud_tgt[2])
                voxels = [
                    (choice.voxel_size, choice.refine_voxel, choice.keep_of(k)) for k in (0, 1)
                ]
            src = self._features(cloud_src, voxels[0], timings, "features_src")
            tgt = self._features(cloud_tgt, voxels[1], timings, "features_tgt")
            result = self.registrar.match(src, tgt)
            result = result._replace(
                timings={**timings, **result.timings},
                voxel_choice=None if choice is None else choice.as_dict(),
            )
        except Exception as exc:  # one bad pair must not stop the others
            result = exc
        return result, time.perf_counter() - started

    def _cloud(self, path: Path, label: str, factor: float | None, timings: dict):
        """``(points, name, CloudScale | None, key)`` of a file times its ``factor`` to metres,
        read (and measured for an auto voxel) once while it stays in the cache."""
        start = time.perf_counter()
        key = ("cloud", path.resolve(), factor)

        def read():
            load = {k: self.load[k] for k in ("intrinsics", "depth_scale")}
            points, name = self.registrar.load(path, label, factor, **load)
            auto = self.registrar.auto_voxel
            size = self.registrar.cloud_scale(points, name) if auto else None
            return points, name, size, key

        cloud, cached = self.cache.get(key, read)
        timings["load"] = timings.get("load", 0.0) + (
            0.0 if cached else time.perf_counter() - start
        )
        return cloud

    def _features(self, cloud, voxel: tuple, timings: dict, stage: str):
        """Features at ``voxel``, ``(voxel_size, refine_voxel, keep)`` (None, None, 1.0:
        the registrar's); their ``scale`` is the target's factor (T in the target's units)."""
        start = time.perf_counter()
        points, name, _, key = cloud
        units = self.load["factors"][0][1]
        feats, cached = self.cache.get(
            ("features", key, voxel),
            lambda: self.registrar.extract_points(points, units, name, *voxel),
        )
        timings[stage] = 0.0 if cached else time.perf_counter() - start
        return feats

    def finish(self, entry, output: Path, computed: tuple[Any, float]) -> dict:
        """Write the T file of a :meth:`compute` result; the pair's summary record."""
        from byoc_cli.io import atomic_write_text, format_transform
        from byoc_cli.io.outputs import OutputSet

        result, seconds = computed
        try:
            if isinstance(result, Exception):
                raise result
            policy = OutputSet(self.inputs)
            policy.claim(output)
            with policy:  # the T file appears complete, or not at all
                atomic_write_text(output, format_transform(result.T_tgt_src))
        except Exception as exc:  # one bad pair must not stop the others
            log.debug("pair on line %d failed", entry.line, exc_info=True)
            message = " ".join(str(exc).split()) or type(exc).__name__
            return _record(entry, output, FAILED, message)
        factors, factors_given = self.load["factors"]
        run = {
            "min_confidence": self.min_confidence,
            "scale": self.load["scale"],
            "factors": factors,
            "factors_given": factors_given,
            "depth_scale": self.load["depth_scale"],
            "device": self.device,
            "started": time.perf_counter(),
        }
        report = registration_report(result, self.registrar, (entry.source, entry.target), run)
        del report["timings_s"]["command"]
        report["timings_s"]["pair"] = seconds
        return {**_record(entry, output, OK if result.passed else LOW_CONFIDENCE), **report}


class _Summary:
    """The JSON Lines summary, appended one flushed line at a time; a summary this run created
    and left empty (it failed before a pair was done) is removed."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> _Summary:
        self.created = not self.path.exists()
        self.file = open(self.path, "a", encoding="utf-8")
        return self

    def write(self, record: dict) -> None:
        from byoc_cli.io.jsonout import strict_dumps

        self.file.write(strict_dumps(record) + "\n")
        self.file.flush()

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        empty = self.file.tell() == 0
        self.file.close()
        if exc_type is not None and self.created and empty:
            with contextlib.suppress(OSError):
                self.path.unlink()


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

"""The thread policy: wait policy before torch, thread count from affinity, cgroup quota,
OMP_NUM_THREADS and --threads, worker pools with one torch thread per worker."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from byoc_cli import threads
from byoc_cli.cli.main import cli

SRC = Path(__file__).resolve().parents[1] / "src"


def _python(code: str, **env: str) -> str:
    """Run ``code`` in a fresh interpreter with this source tree and ``env`` (a value of
    ``""`` removes the variable); its stdout."""
    environ = {**os.environ, "PYTHONPATH": str(SRC)}
    for name, value in env.items():
        if value == "":
            environ.pop(name, None)
        else:
            environ[name] = value
    done = subprocess.run(
        [sys.executable, "-c", code], env=environ, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


# ------------------------------------------------------------------ the wait policy


def test_the_entry_point_sets_a_passive_wait_policy_before_torch_is_imported():
    out = _python(
        "import os, sys; import byoc_cli.cli.main; e = os.environ; "
        "print(e['OMP_WAIT_POLICY'], e['GOMP_SPINCOUNT'], 'torch' in sys.modules)",
        OMP_WAIT_POLICY="",
        GOMP_SPINCOUNT="",
    )
    assert out == "PASSIVE 1000 False"


def test_a_wait_policy_the_user_set_wins():
    out = _python(
        "import os; import byoc_cli.cli.main; "
        "print(os.environ['OMP_WAIT_POLICY'], os.environ.get('GOMP_SPINCOUNT'))",
        OMP_WAIT_POLICY="ACTIVE",
        GOMP_SPINCOUNT="",
    )
    assert out == "ACTIVE None"  # no spin count: it would override the user's policy


def test_a_spin_count_the_user_set_wins():
    env = {"GOMP_SPINCOUNT": "0"}
    assert threads.set_wait_policy(env) == "PASSIVE"
    assert env == {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "0"}


def test_freed_memory_is_kept_unless_the_user_tuned_the_allocator():
    import ctypes

    glibc = True
    try:
        ctypes.CDLL("libc.so.6").mallopt  # noqa: B018
    except (OSError, AttributeError):
        glibc = False
    assert threads.keep_freed_memory({}) is (glibc and sys.platform == "linux")
    assert threads.keep_freed_memory({"MALLOC_MMAP_THRESHOLD_": "65536"}) is False
    assert threads.keep_freed_memory({"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=1"}) is False


def test_the_api_applies_the_policy_when_it_imports_torch_first():
    out = _python(
        "import os; from byoc_cli import api; import torch; "
        "print(os.environ['OMP_WAIT_POLICY'], os.environ['OMP_NUM_THREADS'], "
        "torch.get_num_threads())",
        OMP_WAIT_POLICY="",
        OMP_NUM_THREADS="",
    )
    count = threads.available_cpus()
    assert out == f"PASSIVE {count} {count}"


def test_the_api_leaves_a_process_that_imported_torch_alone():
    out = _python(
        "import os, torch; from byoc_cli import api; "
        "print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('OMP_NUM_THREADS'))",
        OMP_WAIT_POLICY="",
        OMP_NUM_THREADS="",
    )
    assert out == "None None"


# ------------------------------------------------------------------ cgroup quotas


@pytest.mark.parametrize(
    ("text", "cpus"),
    [("max 100000\n", None), ("150000 100000\n", 1.5), ("200000 100000", 2.0), ("50000", 0.5)],
)
def test_cpu_max_is_parsed(text, cpus):
    assert threads.parse_cpu_max(text) == cpus


@pytest.mark.parametrize("text", ["", "a b", "1 2 3"])
def test_a_malformed_cpu_max_is_refused(text):
    with pytest.raises(ValueError):
        threads.parse_cpu_max(text)


def test_cfs_quota_is_parsed():
    assert threads.parse_cfs_quota("-1\n", "100000\n") is None
    assert threads.parse_cfs_quota("250000\n", "100000\n") == 2.5


def _fake_v2(tmp_path: Path, limits: dict[str, str], own: str) -> tuple[Path, Path]:
    """A cgroup v2 tree under ``tmp_path`` with ``cpu.max`` files at ``limits`` (folder ->
    content) and a ``/proc/self/cgroup`` naming ``own``."""
    root = tmp_path / "cgroup"
    for folder, text in limits.items():
        (root / folder).mkdir(parents=True, exist_ok=True)
        (root / folder / "cpu.max").write_text(text)
    (root / own).mkdir(parents=True, exist_ok=True)
    listing = tmp_path / "proc_cgroup"
    listing.write_text(f"0::/{own}\n")
    return listing, root


def test_the_tightest_cgroup_v2_quota_of_the_cgroup_and_its_parents_counts(tmp_path):
    listing, root = _fake_v2(
        tmp_path,
        {"": "max 100000\n", "ci": "150000 100000\n", "ci/job": "max 100000\n"},
        "ci/job",
    )
    assert threads.cgroup_cpu_limit(listing, root) == 1.5
    assert threads.available_cpus(affinity=8, quota=threads.cgroup_cpu_limit(listing, root)) == 1


def test_no_quota_and_unreadable_files_mean_no_limit(tmp_path):
    listing, root = _fake_v2(tmp_path, {"": "max 100000\n"}, "job")
    assert threads.cgroup_cpu_limit(listing, root) is None
    assert threads.cgroup_cpu_limit(tmp_path / "missing", root) is None
    (root / "cpu.max").write_text("garbage")
    assert threads.cgroup_cpu_limit(listing, root) is None


def test_a_cgroup_v1_cfs_quota_counts(tmp_path):
    root = tmp_path / "cgroup"
    folder = root / "cpu,cpuacct" / "docker" / "abc"
    folder.mkdir(parents=True)
    (folder / "cpu.cfs_quota_us").write_text("300000\n")
    (folder / "cpu.cfs_period_us").write_text("100000\n")
    listing = tmp_path / "proc_cgroup"
    listing.write_text("12:memory:/docker/abc\n4:cpu,cpuacct:/docker/abc\n")
    assert threads.cgroup_cpu_limit(listing, root) == 3.0
    assert threads.available_cpus(affinity=16, quota=3.0) == 3


def test_available_cpus_are_the_affinity_capped_by_the_quota_and_at_least_one():
    assert threads.available_cpus(affinity=4, quota=8.0) == 4
    assert threads.available_cpus(affinity=4, quota=0.3) == 1


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity here")
def test_the_thread_count_follows_taskset():
    out = _python(
        "import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); "
        "from byoc_cli import api; import torch; print(torch.get_num_threads())",
        OMP_NUM_THREADS="",
    )
    assert out == "1"


# ------------------------------------------------------------------ the thread count


def test_an_explicit_count_beats_omp_num_threads_which_beats_detection():
    env = {"OMP_NUM_THREADS": "3"}
    assert threads.thread_count(5, env) == 5
    assert threads.thread_count(None, env) == 3
    assert threads.thread_count(None, {"OMP_NUM_THREADS": "x"}) == threads.available_cpus()


def test_the_policy_goes_into_the_environment_and_into_a_loaded_torch():
    env: dict[str, str] = {"OMP_WAIT_POLICY": "ACTIVE"}
    before = torch.get_num_threads()
    try:
        assert threads.apply_thread_policy(1, env) == 1
        assert env == {"OMP_WAIT_POLICY": "ACTIVE", "OMP_NUM_THREADS": "1"}
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    with pytest.raises(ValueError):
        threads.apply_thread_policy(0, env)


def test_threads_option_is_applied_in_process(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    before = torch.get_num_threads()
    try:
        done = CliRunner().invoke(cli, ["--threads", "1", "weights", "--help"])
        assert done.exit_code == 0, done.output
        assert torch.get_num_threads() == 1
        assert os.environ["OMP_NUM_THREADS"] == "1"
    finally:
        torch.set_num_threads(before)


def test_threads_option_reaches_torch_imported_by_the_command():
    out = _python(
        "import sys; from byoc_cli.cli.main import cli\n"
        "try:\n    cli(['--threads', '1', 'weights', 'info'], standalone_mode=False)\n"
        "except SystemExit:\n    pass\n"
        "loaded = 'torch' in sys.modules; import torch; "
        "print('torch loaded by the command:', loaded, 'threads:', torch.get_num_threads())",
        OMP_NUM_THREADS="2",
    )
    assert out.splitlines()[-1] == "torch loaded by the command: True threads: 1"


def test_threads_option_refuses_zero():
    done = CliRunner().invoke(cli, ["--threads", "0", "weights", "--help"])
    assert done.exit_code == 2
    assert "--threads" in done.output


# ------------------------------------------------------------------ worker pools


def test_workers_run_torch_on_one_thread_and_leave_other_threads_alone():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        pool = threads.worker_pool(2)
        counts = {pool.submit(torch.get_num_threads).result() for _ in range(6)}
        flags = {pool.submit(threads.in_worker).result() for _ in range(6)}
        pool.shutdown()
        later: list[int] = []
        thread = threading.Thread(target=lambda: later.append(torch.get_num_threads()))
        thread.start()
        thread.join()
        assert counts == {1}
        assert flags == {True}
        assert not threads.in_worker()
        assert torch.get_num_threads() == 2
        assert later == [2]
    finally:
        torch.set_num_threads(before)


def test_a_pool_needs_a_worker():
    with pytest.raises(ValueError):
        threads.worker_pool(0)


# ------------------------------------------------------------------ side by side


def test_side_by_side_returns_the_results_in_order_whoever_ran_them():
    pool = threads.worker_pool(2)
    try:
        run = threads.side_by_side(pool)
        names = run([lambda: threading.current_thread().name for _ in range(4)])
        assert names[0] == threading.current_thread().name  # the first: the caller
        assert run([lambda k=k: k * k for k in range(5)]) == [0, 1, 4, 9, 16]
        assert run([]) == []
    finally:
        pool.shutdown()


def test_side_by_side_takes_back_work_a_busy_pool_has_not_started():
    pool = threads.worker_pool(1)
    release = threading.Event()
    blocker = pool.submit(release.wait)  # the only worker is busy until released
    try:
        # from a thread that is not a worker as from one: nothing waits on the blocked queue
        out = threads.side_by_side(pool)([lambda: "a", lambda: "b", lambda: "c"])
        assert out == ["a", "b", "c"]
        assert not blocker.done()
    finally:
        release.set()
        pool.shutdown()


def test_side_by_side_raises_what_a_call_raised():
    pool = threads.worker_pool(2)

    def fail():
        raise ValueError("bad half")

    try:
        with pytest.raises(ValueError, match="bad half"):
            threads.side_by_side(pool)([lambda: 1, fail])
    finally:
        pool.shutdown()

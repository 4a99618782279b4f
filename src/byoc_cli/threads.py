"""The thread policy of the tool: how many threads it runs and how idle threads wait.

torch (and open3d) parallelise with OpenMP (libgomp). By default an OpenMP thread that
finishes its share of a parallel region spins for a few milliseconds waiting for the next
one. The encoder and the refinement issue thousands of small parallel regions, so on a
machine whose cores are busy with other processes those spinning threads take the cores
from the thread that still has work (and from every other process): three copies of
``byoc register`` at once ran 2.5 times slower than with passive waiting (issue 25).

The policy, applied by the ``byoc`` entry point before torch is imported (and by
:mod:`byoc_cli.api` when it is the first to import torch):

* ``OMP_WAIT_POLICY=PASSIVE`` with ``GOMP_SPINCOUNT=1000``: a waiting thread spins about
  10 microseconds, then sleeps. Without the spin every parallel region wakes its threads
  from sleep, which made training steps 6 times slower on an idle machine. libgomp reads the
  variables once, when it is loaded, so they must be in the environment before ``import
  torch``. A value the user set wins.
* threads: the cores this process may actually use: its CPU affinity
  (``os.sched_getaffinity``, e.g. ``taskset``, ``docker --cpuset-cpus``) and its cgroup CPU
  quota (cgroup v2 ``cpu.max``, v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``; e.g.
  ``docker --cpus 1.5``, Kubernetes CPU limits), rounded down, at least 1. An explicit
  count (``byoc --threads N``) wins over ``OMP_NUM_THREADS``, which wins over the
  detected count. The count is passed to torch through ``OMP_NUM_THREADS`` (read at its
  import, also by MKL and open3d) and with ``torch.set_num_threads`` when torch is
  already loaded.

The entry point also keeps freed memory for reuse (:func:`keep_freed_memory`): glibc
returns every freed block of more than a few megabytes to the system at once and faults the
pages of the next one in anew, which cost a 1-2 M point registration a tenth of its CPU time
in the kernel (issue 25).

Nothing here imports torch at module level: ``byoc --help`` stays instant.
"""

from __future__ import annotations

import math
import os
import sys
import threading
from collections.abc import Callable, Mapping, MutableMapping, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from pathlib import Path

#: OpenMP's wait policy for the tool's processes
WAIT_POLICY = "PASSIVE"
WAIT_POLICY_VAR = "OMP_WAIT_POLICY"
#: libgomp's spins before a waiting thread sleeps, with the passive policy (it wins over the
#: policy's 0): about 10 microseconds. Back-to-back parallel regions hand over without a
#: sleep and a wake-up (training steps ran 6 times slower without it on an idle 2-core
#: machine: 2.0 s against 0.35 s), yet nothing spins long enough to take a busy core
SPIN_COUNT = "1000"
SPIN_COUNT_VAR = "GOMP_SPINCOUNT"
NUM_THREADS_VAR = "OMP_NUM_THREADS"
#: where the kernel tells a process its cgroups, and where cgroup file systems are mounted
PROC_CGROUP = Path("/proc/self/cgroup")
CGROUP_ROOT = Path("/sys/fs/cgroup")
#: cgroup v1 default scheduler period (microseconds) when the period file cannot be read
CFS_PERIOD_US = 100_000


def parse_cpu_max(text: str) -> float | None:
    """CPUs allowed by a cgroup v2 ``cpu.max`` file (``"QUOTA PERIOD"``, quota ``max`` for
    none): ``"150000 100000"`` -> 1.5, ``"max 100000"`` -> None.

    Raises:
        ValueError: text that is not ``QUOTA [PERIOD]``.
    """
    fields = text.split()
    if not 1 <= len(fields) <= 2:
        raise ValueError(f"cpu.max: expected 'QUOTA PERIOD', got {text!r}")
    if fields[0] == "max":
        return None
    period = int(fields[1]) if len(fields) == 2 else CFS_PERIOD_US
    return _ratio(int(fields[0]), period)


def parse_cfs_quota(quota_text: str, period_text: str) -> float | None:
    """CPUs allowed by cgroup v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``; a negative
    quota (``-1``) is no limit (None).

    Raises:
        ValueError: text that is not an integer.
    """
    return _ratio(int(quota_text), int(period_text))


def _ratio(quota: int, period: int) -> float | None:
    if quota <= 0 or period <= 0:
        return None
    return quota / period


def cgroup_cpu_limit(proc_cgroup: Path = PROC_CGROUP, root: Path = CGROUP_ROOT) -> float | None:
    """The CPU quota of this process's cgroups in CPUs (the tightest of its cgroup and
    every parent's), or None when there is none or it cannot be read.

    Args:
        proc_cgroup: the ``/proc/self/cgroup`` listing (``ID:CONTROLLERS:PATH`` lines).
        root: where the cgroup file systems are mounted.
    """
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None
    limits = []
    for line in lines:
        fields = line.split(":", 2)
        if len(fields) != 3:
            continue
        hierarchy, controllers, path = fields
        if hierarchy == "0" and controllers == "":  # cgroup v2: one unified tree
            limits += [_read_limit(d / "cpu.max", parse_cpu_max) for d in _walk_up(root, path)]
        elif "cpu" in controllers.split(","):  # cgroup v1: the cpu controller's tree
            for mount in (root / controllers, root / "cpu"):
                for folder in _walk_up(mount, path):
                    limits.append(_read_cfs(folder))
    found = [limit for limit in limits if limit is not None]
    return min(found) if found else None


def _walk_up(mount: Path, path: str) -> list[Path]:
    """``mount/path`` and its parents up to ``mount`` (inside a container the cgroup's own
    folder is often mounted at ``mount`` itself)."""
    folder, out = mount / path.strip("/"), []
    while True:
        out.append(folder)
        if folder == mount or mount not in folder.parents:
            return out
        folder = folder.parent


def _read_limit(file: Path, parse) -> float | None:
    try:
        return parse(file.read_text())
    except (OSError, ValueError):
        return None


def _read_cfs(folder: Path) -> float | None:
    try:
        quota = (folder / "cpu.cfs_quota_us").read_text()
    except OSError:
        return None
    try:
        period = (folder / "cpu.cfs_period_us").read_text()
    except OSError:
        period = str(CFS_PERIOD_US)
    try:
        return parse_cfs_quota(quota, period)
    except ValueError:
        return None


def affinity_cpus() -> int:
    """How many CPUs this process may be scheduled on (its affinity mask)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def available_cpus(affinity: int | None = None, quota: float | None = None) -> int:
    """The cores this process may actually use: the affinity count, capped by the cgroup
    CPU quota rounded down; at least 1.

    Args:
        affinity: CPUs in the affinity mask (default: :func:`affinity_cpus`).
        quota: CPUs of the cgroup quota (default: :func:`cgroup_cpu_limit`; None: no quota).
    """
    count = affinity_cpus() if affinity is None else affinity
    limit = cgroup_cpu_limit() if quota is None else quota
    if limit is not None:
        count = min(count, math.floor(limit))
    return max(1, count)


#: glibc's ``mallopt`` parameters and the values :func:`keep_freed_memory` sets: blocks up to
#: 256 MB come from the heap instead of a fresh ``mmap`` each (the default switches at 128 KB
#: and adapts up to 32 MB), and up to 512 MB of free heap top is kept (default: 128 KB)
MALLOPT = {
    "M_TRIM_THRESHOLD": (-1, 512 << 20),
    "M_TOP_PAD": (-2, 64 << 20),
    "M_MMAP_THRESHOLD": (-3, 256 << 20),
}


def keep_freed_memory(environ: Mapping[str, str] = os.environ) -> bool:
    """Make glibc's allocator keep freed memory for the next allocations (:data:`MALLOPT`),
    unless the user tuned it (``MALLOC_*_`` variables of the same names, ``GLIBC_TUNABLES``); the
    results do not change, the peak memory may grow by a few of the largest blocks.

    Returns:
        Whether the settings were applied (False: not glibc, or tuned by the user).
    """
    tuned = any(f"MALLOC_{name[2:]}_" in environ for name in MALLOPT)
    if tuned or "malloc" in environ.get("GLIBC_TUNABLES", "") or sys.platform != "linux":
        return False
    import ctypes

    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # another C library (musl)
        return False
    return all(mallopt(param, value) == 1 for param, value in MALLOPT.values())


def set_wait_policy(environ: MutableMapping[str, str] = os.environ) -> str:
    """Put ``OMP_WAIT_POLICY=PASSIVE`` in ``environ`` unless it holds a value already, and
    then a short spin, ``GOMP_SPINCOUNT=1000`` (unless set; a policy the user chose is left
    as it is); the policy in effect is returned. Has an effect on OpenMP only before it is
    loaded (before ``import torch``)."""
    if WAIT_POLICY_VAR not in environ:
        environ[WAIT_POLICY_VAR] = WAIT_POLICY
        environ.setdefault(SPIN_COUNT_VAR, SPIN_COUNT)
    return environ[WAIT_POLICY_VAR]


def thread_count(requested: int | None, environ: MutableMapping[str, str] = os.environ) -> int:
    """The number of threads: ``requested`` if given, else a valid ``OMP_NUM_THREADS``,
    else :func:`available_cpus`."""
    if requested is not None:
        return requested
    try:
        from_env = int(environ.get(NUM_THREADS_VAR, ""))
    except ValueError:
        from_env = 0
    return from_env if from_env > 0 else available_cpus()


def apply_thread_policy(
    requested: int | None = None, environ: MutableMapping[str, str] = os.environ
) -> int:
    """Set the wait policy and the thread count for this process and its children.

    Writes ``OMP_WAIT_POLICY`` (unless set) and ``OMP_NUM_THREADS`` into ``environ``, so
    torch, MKL and open3d start with them when they are imported later; if torch is
    already imported, also calls ``torch.set_num_threads``.

    Args:
        requested: an explicit thread count (``--threads``), >= 1; None: see
            :func:`thread_count`.

    Returns:
        The thread count in effect.

    Raises:
        ValueError: ``requested`` below 1.
    """
    if requested is not None and requested < 1:
        raise ValueError(f"threads must be at least 1, got {requested}")
    set_wait_policy(environ)
    count = thread_count(requested, environ)
    environ[NUM_THREADS_VAR] = str(count)
    torch = sys.modules.get("torch")
    if torch is not None and torch.get_num_threads() != count:
        torch.set_num_threads(count)
    return count


def worker_pool(workers: int) -> ThreadPoolExecutor:
    """A pool of ``workers`` threads whose torch operations run single-threaded: independent
    pieces of work (the two clouds of a pair, the pairs of a batch) run side by side, one
    per core, instead of each splitting its thousands of small operations across the cores
    (OpenMP parallel regions whose threads then wait on each other).

    Every worker is started here; the calling thread, and threads started later, keep the
    caller's torch thread count.

    Raises:
        ValueError: ``workers`` below 1.
    """
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    import torch

    # torch.set_num_threads sets the calling thread's count and the default of threads
    # that have not run a parallel operation yet: set the workers', then restore the default
    count = torch.get_num_threads()
    started = threading.Barrier(workers + 1)
    pool = ThreadPoolExecutor(workers, "byoc-worker")
    for _ in range(workers):
        pool.submit(_one_torch_thread, started)
    started.wait()
    torch.set_num_threads(count)
    return pool


#: marks the threads of worker pools (:func:`in_worker`)
_WORKER = threading.local()


def in_worker() -> bool:
    """Whether the calling thread is a :func:`worker_pool` worker (work it submits to a
    pool and waits for could wait for itself: run it in place)."""
    return getattr(_WORKER, "active", False)


def _one_torch_thread(started: threading.Barrier) -> None:
    import torch

    torch.get_num_threads()  # torch's lazy per-thread set-up first: it would undo ours
    torch.set_num_threads(1)
    _WORKER.active = True
    started.wait()  # every worker is busy until all are set: each runs this once


#: runs independent calls, possibly side by side, and returns their results in order
Parallel = Callable[[Sequence[Callable[[], object]]], list]


def side_by_side(pool: Executor) -> Parallel:
    """A :data:`Parallel` on ``pool`` for a thread that may be one of its workers: the first
    call runs in the calling thread while the others are offered to the pool; a call no
    worker has started by then is taken back and run in the calling thread too, so the
    caller never waits on work queued behind its own (a busy pool only costs the offer).
    The results are what the calls return, whichever thread ran them."""

    def run(calls: Sequence[Callable[[], object]]) -> list:
        offered = [pool.submit(call) for call in calls[1:]]
        results = [calls[0]()] if calls else []
        for call, future in zip(calls[1:], offered, strict=True):
            results.append(call() if future.cancel() else future.result())
        return results

    return run

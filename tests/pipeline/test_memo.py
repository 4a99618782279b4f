"""What the engine keeps per cloud array (pipeline/memo.py)."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from byoc_cli.pipeline.memo import InPlace, Memo, RefineClouds, all_done


def test_a_value_is_computed_once_per_array_and_key():
    memo, calls = Memo(4), []
    a, b = np.zeros((3, 3)), np.zeros((3, 3))  # equal arrays, two identities
    assert memo.get(a, "k", lambda: calls.append("a") or 1) == 1
    assert memo.get(a, "k", lambda: calls.append("again") or 2) == 1
    assert memo.get(b, "k", lambda: calls.append("b") or 3) == 3
    assert memo.get(a, "other", lambda: calls.append("other") or 4) == 4
    assert calls == ["a", "b", "other"]


def test_the_least_recently_used_is_dropped_first():
    memo, arrays = Memo(2), [np.zeros(1) for _ in range(3)]
    memo.get(arrays[0], None, lambda: 0)
    memo.get(arrays[1], None, lambda: 1)
    memo.get(arrays[0], None, lambda: -1)  # used again: 1 is now the oldest
    memo.get(arrays[2], None, lambda: 2)
    assert memo.get(arrays[0], None, lambda: "recomputed") == 0
    assert memo.get(arrays[1], None, lambda: "recomputed") == "recomputed"


def test_a_failure_is_not_kept():
    memo, a = Memo(2), np.zeros(1)

    def fail():
        raise ValueError("no")

    with pytest.raises(ValueError):
        memo.get(a, None, fail)
    assert memo.get(a, None, lambda: 5) == 5


def test_a_thread_waits_for_the_value_another_computes():
    memo, a, calls = Memo(2), np.zeros(1), []
    started = threading.Event()

    def slow():
        calls.append(1)
        started.set()
        time.sleep(0.2)
        return "v"

    with ThreadPoolExecutor(2) as pool:
        first = pool.submit(memo.get, a, None, slow)
        started.wait()
        second = pool.submit(memo.get, a, None, lambda: calls.append(2) or "other")
        assert first.result() == second.result() == "v"
    assert calls == [1]


def test_refinement_clouds_are_kept_per_array_and_voxel():
    clouds, made = RefineClouds(2), []
    a = np.random.default_rng(0).uniform(size=(500, 3))

    def local():
        made.append(1)
        return a

    first = clouds.get(a, 0.05, local)
    assert clouds.get(a, 0.05, local) is first and len(made) == 1
    assert clouds.get(a, 0.1, local) is not first and len(made) == 2  # another voxel
    assert first.voxel_size == 0.05


def test_all_done_waits_for_every_job_even_after_one_failed():
    ended = []

    def fails():
        raise RuntimeError("load failed")

    def slow():
        time.sleep(0.2)
        ended.append("slow")

    with ThreadPoolExecutor(2) as pool:
        jobs = all_done([pool.submit(fails), pool.submit(slow)])
        assert ended == ["slow"]
        with pytest.raises(RuntimeError):
            jobs[0].result()


def test_in_place_runs_the_call_at_once():
    assert InPlace().submit(lambda x, y=0: x + y, 2, y=3).result() == 5

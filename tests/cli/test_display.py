"""What commands show on stderr: the ETA of a progress bar counts down between items."""

from __future__ import annotations

import pytest

from byoc_cli.cli.display import countdown


def test_the_eta_is_the_mean_time_per_item_times_the_items_left_less_the_time_since():
    assert countdown(0, 10, 5.0, 0.0) is None  # nothing done: no estimate
    assert countdown(2, 10, 8.0, 0.0) == pytest.approx(32.0)  # 4 s a pair, 8 pairs left
    assert countdown(2, 10, 8.0, 3.0) == pytest.approx(29.0)  # counts down until the next
    assert countdown(2, 10, 8.0, 100.0) == 0.0  # never below zero
    assert countdown(10, 10, 40.0, 1.0) == 0.0
    assert countdown(3, None, 8.0, 0.0) is None  # no total

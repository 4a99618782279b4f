"""The sequence of one pair (pipeline/sequence.py): both clouds read and featured side by
side, the pair's voxel, the timings of every stage."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from byoc_cli.errors import InputError
from byoc_cli.pipeline.registrar import Registrar
from byoc_cli.pipeline.sequence import register_pair
from tests.pipeline._clouds import cube, moved


def test_a_pair_gets_one_voxel_and_the_timings_of_each_stage():
    made = Registrar("fpfh", threads=2)
    src, (tgt, T) = cube(2), moved(cube(3))
    got = register_pair(made, (src, tgt), None, {}, {"seed": 0})
    for stage in ("load", "scale", "features_src", "features_tgt", "prepare_src", "total"):
        assert got.timings[stage] >= 0, stage
    assert got.voxel_choice is not None and got.voxel_choice["voxel_size"] == got.voxel_size
    assert np.abs(got.T_tgt_src - T).max() < 0.02
    same = made.register(src, tgt, seed=0)  # the method is this sequence
    assert same.T_tgt_src.tobytes() == got.T_tgt_src.tobytes()


def test_a_failed_read_waits_for_the_other_cloud_before_it_raises(tmp_path, monkeypatch):
    made = Registrar("fpfh", threads=2)
    busy, real = threading.Event(), made.load

    def load(cloud, label, scale, **kw):
        if label == "target":
            time.sleep(0.3)
            busy.set()
        return real(cloud, label, scale, **kw)

    monkeypatch.setattr(made, "load", load)
    with pytest.raises(InputError):
        register_pair(made, (tmp_path / "missing.ply", cube(1)), None, {}, {})
    assert busy.is_set()  # the target's read had ended when the error came

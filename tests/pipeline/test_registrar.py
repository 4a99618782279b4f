"""The register engine (pipeline/registrar.py): refinement levels kept per cloud, a featured
pair matched, the scan-line flag of auto-voxel pairs."""

from __future__ import annotations

import numpy as np
import pytest

from byoc_cli.pipeline.recipe import preset
from byoc_cli.pipeline.registrar import Registrar
from tests.pipeline._clouds import cube, moved


def test_multiscale_refinement_runs_on_the_full_cloud_and_with_kept_points_alone():
    src = cube(2)
    tgt, T = moved(cube(3))
    registrar = Registrar("fpfh", voxel_size=None)  # features kept in files: one voxel
    f_src, f_tgt = registrar.extract(src), registrar.extract(tgt)
    assert np.array_equal(f_src.cloud, src) and np.array_equal(f_tgt.cloud, tgt)
    full = registrar.match(f_src, f_tgt, refine="multiscale")
    assert full.refine == "multiscale" and "refine" in full.timings
    assert np.abs(full.T_tgt_src - T).max() < 0.01
    # features read back from a file carry no cloud: the kept points are refined instead
    kept = registrar.match(
        f_src._replace(cloud=None), f_tgt._replace(cloud=None), refine="multiscale"
    )
    assert np.abs(kept.T_tgt_src - T).max() < 0.05
    assert not np.array_equal(kept.T_tgt_src, full.T_tgt_src)


def test_a_cloud_refined_in_several_pairs_is_prepared_once(monkeypatch):
    import byoc_cli.pipeline.refine as refine

    built = []
    original = refine.RefineCloud.target

    def counting(self, level):
        if level not in self._targets:
            built.append((id(self), level))
        return original(self, level)

    monkeypatch.setattr(refine.RefineCloud, "target", counting)
    registrar = Registrar("fpfh")
    a, (b, _), (c, _) = cube(2), moved(cube(3)), moved(cube(4))
    fa, fb, fc = registrar.extract(a), registrar.extract(b), registrar.extract(c)
    first = registrar.match(fa, fb, refine="multiscale")
    levels = len(built)
    assert levels == len(refine.LEVELS)  # b's levels as a target
    again = registrar.match(fa, fb, refine="multiscale")
    assert len(built) == levels  # nothing rebuilt
    assert np.array_equal(first.T_tgt_src, again.T_tgt_src)
    registrar.match(fc, fb, refine="multiscale")
    assert len(built) == levels  # b is the target again: reused
    registrar.match(fb, fc, refine="multiscale")
    assert len(built) == 2 * levels  # c as a target: built once


def test_only_clouds_sampled_along_lines_ask_the_fit_for_a_second_try(monkeypatch):
    import byoc_cli.pipeline.register as register_module
    from tests._rings import camera_scan, ring_scan

    seen = []
    real = register_module.estimate_transform

    def spy(*args, **kwargs):
        seen.append(kwargs.get("scan_lines"))
        return real(*args, **kwargs)

    monkeypatch.setattr(register_module, "estimate_transform", spy)
    rings, camera = ring_scan(), camera_scan()
    once = preset("byoc").changed(gate__retries=0)  # one fit a pair, whatever its confidence
    registrar = Registrar(fallback=None, recipe=once)
    for cloud in (rings, camera):
        registrar.register(cloud, moved(cloud)[0])
    with pytest.warns(UserWarning, match="differs from the 0.025 m"):
        explicit = Registrar(fallback=None, voxel_size=0.5, recipe=once)
    explicit.register(rings, moved(rings)[0])
    assert seen == [True, False, False]  # an explicit voxel: no auto measure, no flag

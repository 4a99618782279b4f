"""The gate's visibility check (pipeline/visibility.py): the rule with stand-ins, its place in
the registrar, and real depth frames under their ground truth and slid."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from byoc_cli.pipeline import visibility
from byoc_cli.pipeline.recipe import preset
from byoc_cli.pipeline.registrar import Registrar
from byoc_cli.pipeline.results import Registration
from byoc_cli.pipeline.visibility import (
    MAX_FREE_SPACE,
    free_space,
    near_origin,
    needs_visibility,
    with_visibility,
)
from tests._rings import wall as _wall

VOXEL = 0.025


def _registration(tx: float = 0.0, passed: bool = True, path: str = "global") -> Registration:
    T = np.eye(4)
    T[0, 3] = tx
    return Registration(
        T, 0.9 if passed else 0.1, passed, 10, 20, 0.5, 0.3, 100, 100, 0.05, VOXEL, "byoc",
        "ransac", "multiscale", 1000, 100, 0, None, {"fit": 0.1}, path=path,
    )  # fmt: skip


def _features(points: np.ndarray, voxel_size: float = VOXEL, origin=None, scale: float = 1.0):
    return SimpleNamespace(
        points=points * scale, voxel_size=voxel_size * scale, scale=scale, origin=origin,
        cloud=None,
    )  # fmt: skip


def test_only_passing_global_results_are_checked():
    ok = _registration()
    assert needs_visibility(ok, True) and not needs_visibility(ok, False)
    assert not needs_visibility(_registration(passed=False), True)
    assert not needs_visibility(_registration(path="local"), True)


def test_a_georeferenced_cloud_has_no_sensor_at_its_origin():
    assert near_origin(_features(_wall()))
    assert near_origin(_features(_wall(), origin=np.zeros(3)))
    assert not near_origin(_features(_wall(), origin=np.array([4.5e5, 5.2e6, 0.0])))


def test_a_right_pose_passes_and_a_slide_through_the_wall_does_not():
    # a wall seen from two sensors 0.4 m apart: the target's frame is the source's moved
    wall = _wall(3.0)
    T = np.eye(4)
    T[0, 3] = 0.4
    src, tgt = wall - T[:3, 3], wall  # the source's sensor stands 0.4 m to the side
    right = with_visibility(_registration()._replace(T_tgt_src=T), _features(src), _features(tgt))
    assert right.passed and right.visibility["consistent"]
    assert right.visibility["free_space"] == 0.0
    slid = T.copy()
    slid[2, 3] = -1.0  # a metre towards the target's sensor
    wrong = with_visibility(
        _registration()._replace(T_tgt_src=slid), _features(src), _features(tgt)
    )
    note = wrong.visibility
    assert not wrong.passed and not note["consistent"]
    assert note["source_in_target"] == 1.0 and note["free_space"] == 1.0
    assert note["max_free_space"] == MAX_FREE_SPACE and note["seen"][0] > 0
    assert wrong.timings["visibility"] == note["seconds"] >= 0 and wrong.timings["fit"] == 0.1
    assert np.array_equal(wrong.T_tgt_src, slid) and wrong.confidence == 0.9  # T as it was


def test_shares_are_taken_in_the_inputs_units():
    wall = _wall(3.0)
    T = np.eye(4)
    T[2, 3] = -1.0
    metres = with_visibility(
        _registration()._replace(T_tgt_src=T), _features(wall), _features(wall)
    )
    mm = np.eye(4)
    mm[2, 3] = -1000.0
    millimetres = with_visibility(
        _registration()._replace(T_tgt_src=mm),
        _features(wall * 1000, VOXEL * 1000, scale=0.001),
        _features(wall * 1000, VOXEL * 1000, scale=0.001),
    )
    assert millimetres.visibility["free_space"] == metres.visibility["free_space"] == 1.0


def test_a_side_with_few_points_seen_says_nothing():
    few = _wall(3.0, half=0.05, step=0.02)  # 36 points
    T = np.eye(4)
    T[2, 3] = -1.0
    note = free_space(few, few, T, VOXEL)
    assert note["source_in_target"] == 1.0 and note["seen"][0] < visibility.MIN_SEEN
    assert note["free_space"] == 0.0


def _match_alone(registrar, src, tgt, **kw) -> Registration:
    """``match_alone`` of a stand-in registrar: a passing result at the identity."""
    return _registration()._replace(overlap=0.9)  # no check with another seed


def test_the_registrar_checks_its_result_where_the_features_see_their_own_voxel(monkeypatch):
    monkeypatch.setattr(Registrar, "match_alone", _match_alone)
    wall = _wall(3.0)
    near = _features(
        wall + np.array([0.0, 0.0, -1.0])
    )  # the source sits a metre in front of the wall
    far = _features(wall)
    registrar = Registrar(fallback="none")
    own = registrar.voxel_size
    got = registrar.match(_features(near.points, own), _features(far.points, own), seed=0)
    assert not got.passed and got.visibility["source_in_target"] == 1.0
    off = Registrar(fallback="none", recipe=preset("byoc").changed(gate__visibility=False))
    got = off.match(_features(near.points, own), _features(far.points, own), seed=0)
    assert got.passed and got.visibility is None
    small = _features(near.points, 0.5 * own), _features(far.points, 0.5 * own)
    assert registrar.match(*small, seed=0).visibility is None  # brought up to scale: objects
    moved = _features(near.points, own, origin=np.array([1e6, 0.0, 0.0]))
    assert registrar.match(moved, _features(far.points, own), seed=0).visibility is None


def test_at_a_coarser_voxel_only_clouds_seen_from_their_origin_are_checked(monkeypatch):
    """Scans larger than the features' own (rooms, LiDAR): checked when each cloud hides at
    most MAX_HIDDEN of itself seen from its origin, as a scan from there does."""
    monkeypatch.setattr(Registrar, "match_alone", _match_alone)
    registrar = Registrar(fallback="none")
    coarse = 2.1 * registrar.voxel_size
    wall = _wall(3.0)
    near = _features(wall + np.array([0.0, 0.0, -1.0]), coarse)
    got = registrar.match(near, _features(wall, coarse), seed=0)
    assert not got.passed and got.visibility["source_in_target"] == 1.0
    assert got.visibility["hidden"] == [0.0, 0.0]
    assert got.visibility["max_hidden"] == visibility.MAX_HIDDEN
    # a target whose far wall lies behind its near one: not scanned from its origin
    layered = _features(np.concatenate([wall, _wall(5.0)]), coarse)
    assert registrar.match(near, layered, seed=0).visibility is None


def test_the_presets_check_the_learned_features_only():
    assert preset("byoc").gate.visibility and not preset("fpfh").gate.visibility


def _frames(shared_data: Path, spacing: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from byoc_cli.evaluation.pairs import rgbd_pairs
    from byoc_cli.geometry import voxelize

    pairs, _ = rgbd_pairs([shared_data / "rgbd" / "tum_fr1_desk_full"], spacing=spacing)
    pair = pairs[k]
    clouds = []
    for ref in (pair.source, pair.target):
        points = np.asarray(ref.load(), dtype=np.float64)
        clouds.append(points[voxelize(torch.from_numpy(points), VOXEL).point_index.numpy()])
    return clouds[0], clouds[1], pair.T_gt


@pytest.mark.parametrize(("k", "slide"), [(0, (0.5, 0.0, 0.0)), (1, (0.0, 0.0, -0.5))])
def test_real_depth_frames_see_nothing_through_each_other_under_the_truth(shared_data, k, slide):
    """Two Kinect frames 20 apart (tum_fr1_desk_full, each in its camera's frame): under the
    ground truth almost nothing of either lies in the other's free space; slid half a metre,
    a third of one of them does."""
    src, tgt, T_gt = _frames(shared_data, 20, k)
    assert free_space(src, tgt, T_gt, VOXEL)["free_space"] < 0.01
    slid = T_gt.copy()
    slid[:3, 3] += slide
    assert free_space(src, tgt, slid, VOXEL)["free_space"] > 3 * MAX_FREE_SPACE

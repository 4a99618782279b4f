"""The local registration from an initial pose: the correction and the trust region by hand,
the guess's checks, recovery of known transforms (synthetic rooms, georeferenced and in
millimetres; real TUM pairs), results outside the trust region, and guesses 40 deg off."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from byoc_cli.pipeline.local import (
    COARSE_BASE,
    Correction,
    InitialPose,
    TrustRegion,
    align_coarse,
    correction,
)
from byoc_cli.pipeline.refine_levels import RefineCloud
from tests.pipeline._rooms import ROOM, sample_boxes


def _boxes(n: int, boxes, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` points spread over the faces of axis-aligned ``boxes``."""
    return sample_boxes(boxes, n // len(boxes), rng)


def _rotation(axis, degrees: float) -> np.ndarray:
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = math.radians(degrees)
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def _transform(axis, degrees: float, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rotation(axis, degrees), t
    return T


def _about(T_gt: np.ndarray, centroid_src: np.ndarray, degrees: float, shift) -> np.ndarray:
    """``T_gt`` turned ``degrees`` about the source's centroid and moved by ``shift``."""
    c = T_gt[:3, :3] @ centroid_src + T_gt[:3, 3]
    P = _transform([0.4, -0.7, 0.3], degrees, np.zeros(3))
    P[:3, 3] = c - P[:3, :3] @ c + np.asarray(shift)
    return P @ T_gt


def _errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    D = np.linalg.inv(T) @ T_gt
    cos = np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)
    return math.degrees(math.acos(cos)), float(np.linalg.norm(D[:3, 3]))


@pytest.fixture(scope="module")
def registrar():
    from byoc_cli.api import Registrar

    return Registrar(device="cpu", threads=1)


@pytest.fixture(scope="module")
def room():
    """``(src, tgt, T_gt)``: two samplings of a room, the source moved by ``T_gt``'s inverse."""
    rng = np.random.default_rng(3)
    T_gt = _transform([0.2, 1.0, -0.3], 25.0, [0.6, -0.4, 0.1])
    tgt = _boxes(60_000, ROOM, rng)
    src = _boxes(60_000, ROOM, rng)
    src = (src - T_gt[:3, 3]) @ T_gt[:3, :3]  # x_src = R^T (x_tgt - t)
    return src, tgt, T_gt


# ------------------------------------------------------------------ by hand


def test_the_correction_of_a_turn_about_the_centroid_moves_the_centroid_nowhere():
    centroid = np.array([1.0, 2.0, 3.0])
    T_init = _transform([0, 0, 1], 30.0, [0.5, 0.0, 0.0])
    turn = _transform([1, 0, 0], 12.0, np.zeros(3))
    c = T_init[:3, :3] @ centroid + T_init[:3, 3]
    turn[:3, 3] = c - turn[:3, :3] @ c  # about where T_init puts the centroid
    moved = correction(turn @ T_init, T_init, centroid)
    assert moved.rotation_deg == pytest.approx(12.0)
    assert moved.translation == pytest.approx(0.0, abs=1e-12)
    shifted = _transform([1, 0, 0], 0.0, [0.3, 0.4, 0.0]) @ T_init
    assert correction(shifted, T_init, centroid) == pytest.approx(Correction(0.0, 0.5))


def test_the_trust_region_defaults_to_voxels_in_the_input_units():
    region = TrustRegion().resolved(voxel=0.025, scale=1.0)
    assert region == TrustRegion(20.0, pytest.approx(0.5))
    assert TrustRegion().resolved(voxel=25.0, scale=1000.0).translation == pytest.approx(0.5)
    assert TrustRegion(10.0, 0.2).resolved(0.025, 1.0) == TrustRegion(10.0, 0.2)
    assert region.holds(Correction(19.9, 0.49)) and not region.holds(Correction(20.1, 0.1))
    assert not region.holds(Correction(1.0, 0.51))


@pytest.mark.parametrize(
    ("init", "options", "message"),
    [
        (np.eye(3), {}, "finite"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), {}, "not a rotation"),
        (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1.0]]), {}, "last row"),
        (np.full((4, 4), np.nan), {}, "finite"),
        (np.eye(4), {"mode": "nearby"}, "init_mode"),
        (np.eye(4), {"max_correction": (-5.0, 0.3)}, "positive"),
        (np.eye(4), {"max_correction": (10.0, float("inf"))}, "positive"),
    ],
)
def test_a_bad_guess_or_bound_is_refused(init, options, message):
    with pytest.raises(ValueError, match=message):
        InitialPose.of(init, options.get("max_correction"), options.get("mode", "local"))


def test_a_guess_of_the_api_is_checked_and_kept(registrar, room):
    src, tgt, _ = room
    guess = InitialPose.of(np.eye(4), (15.0, None), "global")
    assert guess.trust == TrustRegion(15.0, None) and guess.mode == "global"
    with pytest.raises(ValueError, match="go with an init"):
        registrar.register(src, tgt, max_correction=(10.0, 0.2))


# ------------------------------------------------------------------ recovery


def test_the_coarse_pass_brings_a_far_guess_into_the_refinement_basin(room):
    src, tgt, T_gt = room
    start = _about(T_gt, src.mean(0), 10.0, [0.25, -0.1, 0.1])
    clouds = [RefineCloud(p, COARSE_BASE * 0.025) for p in (src, tgt)]
    T, fitness = align_coarse(*clouds, torch.from_numpy(start))
    rot, trans = _errors(T.numpy(), T_gt)
    assert _errors(start, T_gt)[0] == pytest.approx(10.0)
    assert rot < 1.0 and trans < 0.03 and fitness > 0.5


def test_recovers_a_known_transform_from_a_guess_10_deg_and_30_cm_off(registrar, room):
    src, tgt, T_gt = room
    guess = _about(T_gt, src.mean(0), 10.0, [0.2, -0.2, 0.1])
    result = registrar.register(src, tgt, init=guess)
    rot, trans = _errors(result.T_tgt_src, T_gt)
    assert rot < 0.3 and trans < 0.01
    assert result.path == "local" and result.features == "none" and result.passed
    assert result.init["correction"]["rotation_deg"] == pytest.approx(10.0, abs=0.3)
    assert result.init["correction"]["translation"] == pytest.approx(0.3, abs=0.01)
    assert result.init["inside_trust_region"]
    assert result.init["trust_region"] == {"rotation_deg": 20.0, "translation": pytest.approx(0.5)}
    assert set(result.timings) >= {"load", "scale", "coarse", "refine", "verify", "total"}


def test_georeferenced_and_millimetre_coordinates_give_the_same_transform(registrar, room):
    src, tgt, T_gt = room
    guess = _about(T_gt, src.mean(0), 8.0, [0.1, 0.2, -0.1])
    near = registrar.register(src, tgt, init=guess).T_tgt_src
    # UTM-like: both clouds 500 km away, the transforms conjugated by the shift
    offset = np.array([512_345.0, 4_123_456.0, 310.0])
    shift = _transform([1, 0, 0], 0.0, offset)
    far = registrar.register(src + offset, tgt + offset, init=shift @ guess @ np.linalg.inv(shift))
    rot, trans = _errors(np.linalg.inv(shift) @ far.T_tgt_src @ shift, near)
    assert rot < 0.05 and trans < 0.002
    mm = np.diag([1000.0, 1000.0, 1000.0, 1.0])
    result = registrar.register(src * 1000, tgt * 1000, init=mm @ guess @ np.linalg.inv(mm))
    rot, trans = _errors(np.linalg.inv(mm) @ result.T_tgt_src @ mm, T_gt)
    assert rot < 0.3 and trans < 0.01  # T in millimetres, the trust region too
    # the voxel follows the size (26.7 mm here, not 25: the room's radius is 1.07 m)
    assert result.init["trust_region"]["translation"] == pytest.approx(20 * result.voxel_size)


def test_a_result_beyond_the_trust_region_does_not_pass(registrar, room):
    src, tgt, T_gt = room
    guess = _about(T_gt, src.mean(0), 10.0, [0.2, -0.2, 0.1])
    result = registrar.register(src, tgt, init=guess, max_correction=(5.0, None))
    assert _errors(result.T_tgt_src, T_gt)[0] < 0.3  # right, but 10 deg from the guess
    assert not result.passed and not result.init["inside_trust_region"]
    tight = registrar.register(src, tgt, init=guess, max_correction=(45.0, 0.1))
    assert not tight.passed and tight.init["trust_region"]["translation"] == 0.1


def test_the_global_mode_keeps_the_global_result_that_agrees_with_the_guess(registrar, room):
    src, tgt, T_gt = room
    guess = _about(T_gt, src.mean(0), 5.0, [0.05, 0.0, 0.05])
    result = registrar.register(src, tgt, init=guess, init_mode="global")
    assert result.init["mode"] == "global"
    assert result.init["check"] in ("agrees", "local")
    assert _errors(result.T_tgt_src, T_gt)[0] < 1.0
    if result.init["check"] == "agrees":
        assert result.path == "global" and result.features == "byoc"


# ------------------------------------------------------------------ real data


def _tum_pairs(shared_data: Path, which):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from _init_pairs import rgbd_pairs

    found = list(rgbd_pairs((("tum_fr1_desk_full", 25),)))
    return [found[k] for k in which]


@pytest.mark.realdata
def test_recovers_real_tum_pairs_50_frames_apart_from_perturbed_guesses(registrar, shared_data):
    rng = np.random.default_rng(0)
    for pair in _tum_pairs(shared_data, (1, 4)):
        src, tgt = pair.load_source(), pair.load_target()
        guess = _about(pair.T_gt, src.mean(0), 10.0, 0.3 * _unit(rng))
        result = registrar.register(src, tgt, init=guess)
        rot, trans = _errors(result.T_tgt_src, pair.T_gt)
        assert rot < 5.0 and trans < 0.10, pair.name
        assert result.passed, pair.name


@pytest.mark.realdata
def test_guesses_40_deg_off_are_never_wrong_with_a_pass(registrar, shared_data):
    rng = np.random.default_rng(1)
    for pair in _tum_pairs(shared_data, (1, 2, 4, 9)):
        src, tgt = pair.load_source(), pair.load_target()
        guess = _about(pair.T_gt, src.mean(0), 40.0, 0.3 * _unit(rng))
        result = registrar.register(src, tgt, init=guess)
        rot, trans = _errors(result.T_tgt_src, pair.T_gt)
        assert not result.passed or (rot < 5.0 and trans < 0.10), pair.name


def _unit(rng) -> np.ndarray:
    d = rng.normal(size=3)
    return d / np.linalg.norm(d)


def test_a_stray_point_far_away_moves_neither_the_result_nor_its_correction(registrar, room):
    src, tgt, T_gt = room
    guess = _about(T_gt, src.mean(0), 8.0, [0.1, 0.2, -0.1])
    clean = registrar.register(src, tgt, init=guess)
    stray = registrar.register(np.vstack([src, [[1e6, 1e6, 1e6]]]), tgt, init=guess)
    assert clean.passed and stray.passed  # the stray dragged the mean 60 m: exit 3
    np.testing.assert_allclose(stray.T_tgt_src, clean.T_tgt_src, atol=1e-9)
    for key in ("rotation_deg", "translation"):
        assert stray.init["correction"][key] == pytest.approx(clean.init["correction"][key])

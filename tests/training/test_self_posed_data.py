"""Views, augmentation and correspondences of the self-posed variant."""

from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.geometry.voxel import voxelize
from byoc_cli.training.self_posed_data import (
    AugmentConfig,
    CachedFrame,
    cache_frame,
    crop_pair,
    first_point_per_voxel,
    make_pair_views,
    match_views,
    random_rotation,
)


def _cloud(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, size=(n, 3)).astype(np.float32)


def test_first_point_per_voxel_matches_voxelize():
    points = _cloud(5000, 0)
    ours = first_point_per_voxel(points, 0.1)
    grid = voxelize(torch.from_numpy(points), 0.1)
    assert np.array_equal(np.sort(ours), np.sort(grid.point_index.numpy()))


def test_first_point_per_voxel_hand_case():
    points = np.array([[0.01, 0, 0], [0.02, 0, 0], [0.15, 0, 0], [-0.05, 0, 0]], np.float32)
    assert first_point_per_voxel(points, 0.1).tolist() == [0, 2, 3]
    assert first_point_per_voxel(np.zeros((0, 3), np.float32), 0.1).shape == (0,)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.0, 180.0))
def test_random_rotation_is_a_rotation_within_range(seed, max_angle):
    R = random_rotation(max_angle, torch.Generator().manual_seed(seed))
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=R.dtype), atol=1e-10)
    assert abs(torch.linalg.det(R).item() - 1.0) < 1e-10
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (R.trace().item() - 1) / 2))))
    assert angle <= max_angle + 1e-6


def _rigid(angle_deg: float, t: list[float]) -> torch.Tensor:
    a = math.radians(angle_deg)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor(
        [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    )
    T[:3, 3] = torch.tensor(t)
    return T


def test_match_views_recovers_known_pairs():
    points_i = torch.from_numpy(_cloud(3000, 1))
    T_i_j = _rigid(30.0, [0.2, -0.1, 0.05])
    # view j sees the same points in its own frame: p_j = inv(T_i_j) p_i
    T_j_i = torch.linalg.inv(T_i_j).float()
    points_j = points_i @ T_j_i[:3, :3].T + T_j_i[:3, 3]
    matches = match_views(points_i, points_j, T_i_j, 0.05)
    assert len(matches) > 0.9 * len(voxelize(points_i, 0.05).coords) * 0.5
    moved = points_j[matches[:, 1]] @ T_i_j[:3, :3].float().T + T_i_j[:3, 3].float()
    dist = (moved - points_i[matches[:, 0]]).norm(dim=1)
    assert float(dist.max()) < 0.05 * math.sqrt(3) + 1e-5
    # each point is used at most once on each side
    assert len(set(matches[:, 0].tolist())) == len(matches)
    assert len(set(matches[:, 1].tolist())) == len(matches)


def test_match_views_disjoint_and_empty():
    points = torch.from_numpy(_cloud(100, 2))
    far = points + 10.0
    assert match_views(points, far, torch.eye(4, dtype=torch.float64), 0.05).shape == (0, 2)
    empty = torch.zeros(0, 3)
    assert match_views(empty, points, torch.eye(4, dtype=torch.float64), 0.05).shape == (0, 2)


def test_make_pair_views_correspondences_hold_under_augmentation():
    base = _cloud(20000, 3)
    T_i_j = _rigid(20.0, [0.1, 0.0, 0.0])
    T_j_i = np.linalg.inv(T_i_j.numpy())
    frame_i = cache_frame(base, 0.0125)
    frame_j = cache_frame((base @ T_j_i[:3, :3].T + T_j_i[:3, 3]).astype(np.float32), 0.0125)
    gen = torch.Generator().manual_seed(0)
    pair = make_pair_views(frame_i, frame_j, T_i_j, 0.025, AugmentConfig(90.0, 0.05, 0.7), gen)
    assert pair.view_i.coords.dtype == torch.int64 and pair.view_i.coords.shape[1] == 3
    assert len(pair.view_i.coords) == len(pair.view_i.points)
    assert len(pair.matches) > 100
    p_i = pair.view_i.points[pair.matches[:, 0]]
    p_j = pair.view_j.points[pair.matches[:, 1]]
    moved = p_j @ T_i_j[:3, :3].float().T + T_i_j[:3, 3].float()
    assert float((moved - p_i).norm(dim=1).max()) < 0.025 * math.sqrt(3) + 1e-5
    # the same seed gives the same views
    again = make_pair_views(
        frame_i,
        frame_j,
        T_i_j,
        0.025,
        AugmentConfig(90.0, 0.05, 0.7),
        torch.Generator().manual_seed(0),
    )
    assert torch.equal(again.matches, pair.matches)


def _known_pair(seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Frame i: a 2 m x 2 m wall (x in [0, 2]); frame j: the wall's part x in [1.8, 4] seen
    from a pose ``T_i_j`` (only 20 cm of overlap). Returns points_i, points_j, T_i_j."""
    rng = np.random.default_rng(seed)
    wall = np.stack([rng.uniform(0, 4, 40000), rng.uniform(0, 2, 40000), np.zeros(40000)], 1)
    wall[:, 2] = 0.05 * np.sin(3 * wall[:, 0])
    gen = torch.Generator().manual_seed(seed)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = random_rotation(90.0, gen)
    T[:3, 3] = torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)
    in_i = torch.from_numpy(wall[wall[:, 0] <= 2.0]).float()
    j_in_i = torch.from_numpy(wall[wall[:, 0] >= 1.8])
    inv = torch.linalg.inv(T)
    in_j = (j_in_i @ inv[:3, :3].T + inv[:3, 3]).float()
    return in_i, in_j, T


def _to_i(points_j: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    T = T.to(torch.float32)
    return points_j @ T[:3, :3].T + T[:3, 3]


def test_crop_pair_keeps_the_same_ball_in_both_frames_inside_the_overlap():
    for seed in range(12):
        points_i, points_j, T = _known_pair(seed)
        gen = torch.Generator().manual_seed(seed)
        ci, cj = crop_pair(CachedFrame(points_i), CachedFrame(points_j), T, 0.1, gen)
        # the centre is a point of i within 2 cm of j, so it lies at x >= 1.78 and both
        # crops are non-empty
        assert len(ci.points) > 0 and len(cj.points) > 0
        assert float(ci.points[:, 0].min()) > 1.78 - 0.1 - 1e-4
        # both crops are balls of the same place: the j crop, in frame i, lies within 0.2 m
        # of the i crop's mean (both within 0.1 m of the centre)
        j_in_i = _to_i(cj.points, T)
        assert float((j_in_i - ci.points.mean(dim=0)).norm(dim=1).max()) < 0.2 + 1e-4


def test_crop_pair_is_exactly_a_ball_around_one_point_of_i():
    points_i, points_j, T = _known_pair(3)
    gen = torch.Generator().manual_seed(0)
    ci, cj = crop_pair(CachedFrame(points_i), CachedFrame(points_j), T, 0.25, gen)
    j_in_i = _to_i(points_j, T)
    # find the centre: the point of i whose 0.25 m ball gives exactly the kept set
    kept = {tuple(p) for p in ci.points.tolist()}
    found = False
    for c in ci.points:
        ball_i = (points_i - c).norm(dim=1) < 0.25
        if {tuple(p) for p in points_i[ball_i].tolist()} != kept:
            continue
        ball_j = (j_in_i - c).norm(dim=1) < 0.25
        # points on the ball's surface may fall either way through float rounding
        assert abs(int(ball_j.sum()) - len(cj.points)) <= 2
        assert float((j_in_i[ball_j] - c).norm(dim=1).min()) < 0.02
        found = True
        break
    assert found


def test_crop_pair_without_overlap_or_points_in_j_still_crops_i():
    points_i, _, T = _known_pair(1)
    far = points_i + 10.0
    gen = torch.Generator().manual_seed(0)
    ci, cj = crop_pair(CachedFrame(points_i), CachedFrame(far), torch.eye(4), 0.2, gen)
    assert len(ci.points) > 0 and len(cj.points) == 0
    empty = CachedFrame(torch.zeros(0, 3))
    ci, cj = crop_pair(CachedFrame(points_i), empty, T, 0.2, gen)
    assert len(ci.points) > 0 and len(cj.points) == 0


def test_hole_augmentation_drops_voxels_and_is_off_by_default():
    """hole_prob 1: each view keeps a share of its voxels in [hole_min_keep, 1], the kept
    points still correspond; hole_prob 0 draws no random number (old runs resume the same)."""
    frame = CachedFrame(torch.from_numpy(_cloud(20000, 3)))
    T = torch.eye(4)
    base = AugmentConfig(max_rotation_deg=0.0, scale=0.0, min_keep=1.0)
    full = make_pair_views(frame, frame, T, 0.1, base, torch.Generator().manual_seed(0))
    holes = base._replace(hole_prob=1.0, hole_min_keep=0.3)
    thin = make_pair_views(frame, frame, T, 0.1, holes, torch.Generator().manual_seed(0))
    for a, b in ((full.view_i, thin.view_i), (full.view_j, thin.view_j)):
        assert 0.25 * len(a.coords) < len(b.coords) < len(a.coords)
        assert len(b.coords) == len(b.points)
    assert len(thin.matches) < len(full.matches)
    off = base._replace(hole_prob=0.0, hole_min_keep=0.3)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    make_pair_views(frame, frame, T, 0.1, off, g1)
    make_pair_views(frame, frame, T, 0.1, base, g2)
    assert torch.equal(g1.get_state(), g2.get_state())

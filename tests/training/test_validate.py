import math

import pytest
import torch
from torch import nn

from byoc_cli.geometry import voxelize
from byoc_cli.training.data import PairSample, View
from byoc_cli.training.validate import (
    PairErrors,
    inlier_ratio,
    pose_accuracy,
    register_pair_geometric,
    validate,
)

VOXEL = 0.025
K = torch.eye(3)


class _RelativeCoordEncoder(nn.Module):
    """Features from voxel coordinates relative to each cloud's minimum.

    Two clouds that differ by a whole-voxel translation get identical features at
    corresponding points, so the test-time pipeline must recover the translation exactly.
    ``scramble`` permutes the features of every cloud instead (useless features).
    """

    def __init__(self, scramble: bool = False) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.proj = nn.Parameter(torch.randn(3, 32, generator=g))
        self.scramble = scramble

    def forward(self, coords4: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        out = torch.empty(coords4.shape[0], 32)
        g = torch.Generator().manual_seed(1)
        for b in coords4[:, 0].unique():
            mask = coords4[:, 0] == b
            rel = (coords4[mask, 1:] - coords4[mask, 1:].min(0).values).float()
            f = torch.sin(rel @ self.proj + 0.3)
            if self.scramble:
                f = f[torch.randperm(f.shape[0], generator=g)]
            out[mask] = f
        return nn.functional.normalize(out, dim=1)


def _view(points: torch.Tensor) -> View:
    grid = voxelize(points, VOXEL)
    return View(points, grid.point_index, grid.coords, None, K)


def _pair(shift_voxels=(4, -2, 6), n=400, seed=0) -> PairSample:
    """View 1 = view 0 moved by whole voxels; ``T_gt`` maps view 1 back onto view 0."""
    g = torch.Generator().manual_seed(seed)
    sites = torch.unique(torch.randint(0, 40, (n, 3), generator=g), dim=0)
    points0 = ((sites.double() + 0.5) * VOXEL + torch.tensor([0.0, 0.0, 1.0])).float()
    shift = torch.tensor(shift_voxels, dtype=torch.float64) * VOXEL
    points1 = (points0.double() - shift).float()
    T_gt = torch.eye(4, dtype=torch.float64)
    T_gt[:3, 3] = shift
    return PairSample(_view(points0), _view(points1), T_gt, 0, (0, 1))


def test_pose_accuracy_counts_thresholds_and_inliers():
    errors = PairErrors(
        torch.tensor([1.0, 6.0, 50.0], dtype=torch.float64),
        torch.tensor([4.0, 20.0, 30.0], dtype=torch.float64),
        torch.tensor([0.5, 0.01, 0.1], dtype=torch.float64),
    )
    m = pose_accuracy(errors)
    assert m["rot_acc_5"] == pytest.approx(100 / 3)
    assert m["rot_acc_10"] == pytest.approx(200 / 3)
    assert m["rot_acc_45"] == pytest.approx(200 / 3)
    assert m["rot_median_deg"] == 6.0
    assert m["trans_acc_5"] == pytest.approx(100 / 3)
    assert m["trans_acc_25"] == pytest.approx(200 / 3)
    assert m["trans_mean_cm"] == pytest.approx(18.0)
    assert m["inlier_pct_mean"] == pytest.approx(100 * 0.61 / 3)
    assert m["corr_fmr"] == pytest.approx(200 / 3)
    assert m["num_pairs"] == 3


def test_pose_accuracy_without_pairs_is_nan_not_an_error():
    empty = torch.zeros(0, dtype=torch.float64)
    m = pose_accuracy(PairErrors(empty, empty, empty))
    assert m["num_pairs"] == 0
    assert math.isnan(m["rot_acc_5"]) and math.isnan(m["inlier_pct_mean"])
    assert "inlier_pct_mean" not in pose_accuracy(PairErrors(empty, empty))


def test_inlier_ratio_uses_the_ground_truth_direction():
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([1.0, 0.0, 0.0])
    p = torch.zeros(4, 3, dtype=torch.float64)
    q = torch.tensor([[1.0, 0, 0], [1.05, 0, 0], [1.2, 0, 0], [-1.0, 0, 0]], dtype=torch.float64)
    assert inlier_ratio(T, p, q) == pytest.approx(0.5)
    assert inlier_ratio(T, p, q, threshold=0.3) == pytest.approx(0.75)
    assert inlier_ratio(T, p[:0], q[:0]) == 0.0


def test_register_pair_recovers_a_whole_voxel_shift():
    sample = _pair()
    v0, v1 = sample.view0, sample.view1
    reg = register_pair_geometric(
        _RelativeCoordEncoder(),
        v1.coords,
        v0.coords,
        v1.points[v1.point_index],
        v0.points[v0.point_index],
        generator=torch.Generator().manual_seed(0),
    )
    assert reg.points_src.shape == (400, 3) and reg.points_tgt.shape == (400, 3)
    assert torch.allclose(reg.T_tgt_src, sample.T_gt, atol=1e-5)
    assert inlier_ratio(sample.T_gt, reg.points_src, reg.points_tgt) == 1.0


@pytest.mark.parametrize("training", [True, False])
def test_validate_scores_good_and_useless_features_and_restores_the_mode(training):
    samples = [_pair(seed=s) for s in range(3)]
    samples.append(samples[0]._replace(T_gt=None))  # unposed pairs are skipped
    good = _RelativeCoordEncoder().train(training)
    metrics, errors = validate(good, samples)
    assert good.training is training
    assert metrics["num_pairs"] == 3
    assert metrics["rot_acc_5"] == 100.0 and metrics["trans_acc_5"] == 100.0
    assert metrics["inlier_pct_mean"] == 100.0 and metrics["corr_fmr"] == 100.0
    assert float(errors.rotation_deg.max()) < 1e-3

    bad = _RelativeCoordEncoder(scramble=True).train(training)
    metrics, _ = validate(bad, samples)
    assert bad.training is training
    assert metrics["inlier_pct_mean"] < 20.0
    assert metrics["trans_acc_5"] < 100.0


def test_validate_is_seeded():
    samples = [_pair(seed=s) for s in range(2)]
    enc = _RelativeCoordEncoder(scramble=True)
    a = validate(enc, samples, seed=3)[1]
    b = validate(enc, samples, seed=3)[1]
    assert torch.equal(a.rotation_deg, b.rotation_deg)
    assert torch.equal(a.inlier_ratio, b.inlier_ratio)

import pytest
import torch

from byoc_cli.errors import ShapeError
from byoc_cli.models.visual import VisualEncoder, project_points, sample_visual_features


def test_shape_unit_norm_and_size():
    torch.manual_seed(0)
    enc = VisualEncoder().eval()
    out = enc(torch.rand(2, 3, 32, 24) * 2 - 1)
    assert out.shape == (2, 32, 32, 24)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(2, 32, 24))
    n = sum(p.numel() for p in enc.parameters())
    assert 0.28e6 < n < 0.32e6  # the paper's visual encoder: about 0.30 M (docs/training.md)


def test_bad_input_shape():
    with pytest.raises(ShapeError):
        VisualEncoder()(torch.zeros(1, 1, 8, 8))


def test_pixel_centre_points_read_their_own_pixel():
    g = torch.Generator().manual_seed(0)
    h, w = 12, 16
    K = torch.tensor([[20.0, 0.0, 7.3], [0.0, 21.0, 5.9], [0.0, 0.0, 1.0]])
    fmap = torch.nn.functional.normalize(torch.randn(8, h, w, generator=g), dim=0)
    v, u = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    z = torch.rand(h, w, generator=g) + 0.5
    x = (u + 0.5 - K[0, 2]) * z / K[0, 0]
    y = (v + 0.5 - K[1, 2]) * z / K[1, 1]
    points = torch.stack([x, y, z], dim=-1).reshape(-1, 3)
    uv = project_points(points, K)
    torch.testing.assert_close(uv[:, 0], (u.flatten() + 0.5).float(), atol=1e-4, rtol=0)
    sampled = sample_visual_features(fmap, points, K)
    torch.testing.assert_close(sampled, fmap.reshape(8, -1).T, atol=1e-4, rtol=0)


def test_sampling_is_differentiable():
    fmap = torch.randn(4, 6, 6, requires_grad=True)
    K = torch.tensor([[5.0, 0, 3], [0, 5.0, 3], [0, 0, 1]])
    feats = sample_visual_features(fmap, torch.tensor([[0.1, 0.05, 1.0]]), K)
    feats.sum().backward()
    assert fmap.grad is not None and fmap.grad.abs().sum() > 0

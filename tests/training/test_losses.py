import pytest
import torch
from torch import nn

from byoc_cli.errors import ShapeError
from byoc_cli.geometry import make_transform
from byoc_cli.training.losses import (
    Predictor,
    geometric_registration_loss,
    residuals,
    transfer_loss,
    visual_registration_loss,
)


def _shift_x():
    return make_transform(torch.eye(3, dtype=torch.float64), torch.tensor([1.0, 0.0, 0.0]).double())


def test_residuals_hand_computed():
    p = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    q = torch.tensor([[1.0, 0.0, 0.0], [2.0, 1.0, 5.0]])
    r = residuals(_shift_x(), p, q)
    assert r.dtype == torch.float64
    torch.testing.assert_close(r, torch.tensor([0.0, 4.0], dtype=torch.float64), atol=1e-10, rtol=0)


def test_visual_and_geometric_losses_hand_computed():
    p = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    q = torch.tensor([[1.0, 0.0, 0.0], [2.0, 1.0, 4.0], [1.0, 2.0, 0.0]])  # r = 0, 3, 2
    w = torch.tensor([1.0, 3.0, 4.0])
    # sum (w / sum w) r = (0 + 9 + 8) / 8
    assert visual_registration_loss(_shift_x(), p, q, w).item() == pytest.approx(17 / 8)
    # mean r, weights play no part
    assert geometric_registration_loss(_shift_x(), p, q).item() == pytest.approx(5 / 3)


def test_visual_loss_all_zero_weights_is_finite():
    p = torch.zeros(4, 3)
    loss = visual_registration_loss(_shift_x(), p, p + 1, torch.zeros(4))
    assert torch.isfinite(loss) and loss.item() == 0.0


def test_visual_loss_gradcheck_float64():
    g = torch.Generator().manual_seed(0)
    p = torch.randn(6, 3, generator=g, dtype=torch.float64)
    q = torch.randn(6, 3, generator=g, dtype=torch.float64)
    w = torch.rand(6, generator=g, dtype=torch.float64).requires_grad_()
    T = _shift_x()
    assert torch.autograd.gradcheck(lambda w_: visual_registration_loss(T, p, q, w_), (w,))
    pp = p.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda p_: geometric_registration_loss(T, p_, q), (pp,))


def test_residual_shape_errors():
    with pytest.raises(ShapeError):
        residuals(_shift_x(), torch.zeros(3, 3), torch.zeros(4, 3))


class _Double(nn.Module):
    def forward(self, x):
        return 2.0 * x


def test_transfer_loss_hand_computed():
    g0 = torch.tensor([[1.0, 0.0], [1.0, 0.0]])
    g1 = torch.tensor([[0.0, 1.0], [1.0, 0.0]])
    # cos = [0, 1] both ways: 2 - 0.5 - 0.5
    loss = transfer_loss(g0, g1, nn.Identity())
    assert loss.item() == pytest.approx(1.0)
    assert transfer_loss(g0, g0, nn.Identity()).item() == pytest.approx(0.0, abs=1e-6)


def test_transfer_loss_stop_gradient():
    g = torch.Generator().manual_seed(1)
    g0 = torch.randn(5, 4, generator=g, requires_grad=True)
    g1 = torch.randn(5, 4, generator=g, requires_grad=True)
    transfer_loss(g0, g1, _Double()).backward()
    # reference: the gradient reaching g1 flows only through h(g1) against a fixed g0
    a = g0.detach()
    b = g1.detach().clone().requires_grad_()
    (-torch.nn.functional.cosine_similarity(a, 2 * b, dim=-1).mean()).backward()
    torch.testing.assert_close(g1.grad, b.grad)


def test_predictor_architecture():
    h = Predictor(32)
    kinds = [type(m) for m in h.net]
    assert kinds == [nn.Linear, nn.LayerNorm, nn.ReLU, nn.Linear]
    assert h.net[0].in_features == 32 and h.net[3].out_features == 32
    assert h(torch.randn(7, 32)).shape == (7, 32)

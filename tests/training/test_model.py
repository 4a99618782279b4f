import pytest
import torch

from byoc_cli.geometry import voxelize
from byoc_cli.training.data import PairSample, View
from byoc_cli.training.model import ByocModel

SIZE = 24
K = torch.tensor([[20.0, 0.0, 12.0], [0.0, 20.0, 12.0], [0.0, 0.0, 1.0]])


def _view(g: torch.Generator) -> View:
    v, u = torch.meshgrid(torch.arange(SIZE), torch.arange(SIZE), indexing="ij")
    z = 1.0 + 0.3 * torch.sin(u / 3.0 + torch.rand((), generator=g) * 6) + 0.2 * torch.cos(v / 4.0)
    x = (u + 0.5 - K[0, 2]) * z / K[0, 0]
    y = (v + 0.5 - K[1, 2]) * z / K[1, 1]
    points = torch.stack([x, y, z], -1).reshape(-1, 3).float()
    grid = voxelize(points, 0.05)
    color = torch.rand(3, SIZE, SIZE, generator=g) * 2 - 1
    return View(points, grid.point_index, grid.coords, color, K.clone())


def _batch(n=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [PairSample(_view(g), _view(g), None, 0, (0, 1)) for _ in range(n)]


def _model(variant):
    torch.manual_seed(0)
    return ByocModel(variant=variant, voxel_size=0.05, num_correspondences=20, augment_seed=3)


def _modes(model):
    return [m.training for m in model.modules()]


@pytest.mark.parametrize("variant", ["byoc", "byoc-geo", "byoc-vis", "byoc-rot"])
@pytest.mark.parametrize("training", [True, False])
def test_forward_never_changes_mode(variant, training):
    model = _model(variant).train(training)
    before = _modes(model)
    terms = model(_batch())
    assert _modes(model) == before  # research-code bug 10.1
    assert torch.isfinite(terms.total) and terms.num_samples == 2
    used = {"byoc": "vis geo v2g", "byoc-rot": "vis geo v2g", "byoc-geo": "geo", "byoc-vis": "vis"}
    for name in ("vis", "geo", "v2g"):
        value = getattr(terms, name).item()
        assert (value != 0.0) == (name in used[variant].split()), name
    torch.testing.assert_close(terms.total, terms.vis + terms.geo + terms.v2g)


def test_augmentation_only_in_training_mode():
    model = _model("byoc-rot")
    batch = _batch()
    state = model.aug_generator.get_state()
    model.eval()
    with torch.no_grad():
        eval_terms = model(batch)
    assert torch.equal(model.aug_generator.get_state(), state)  # no draw in eval mode
    # in eval mode byoc-rot is exactly byoc with the same weights
    plain = _model("byoc")
    plain.load_state_dict(model.state_dict())
    with torch.no_grad():
        torch.testing.assert_close(plain.eval()(batch).total, eval_terms.total)
    model.train()
    with torch.no_grad():
        model(batch)
    assert not torch.equal(model.aug_generator.get_state(), state)  # drawn while training


def test_transfer_loss_sends_no_gradient_to_the_visual_encoder():
    model = _model("byoc").train()
    terms = model(_batch())
    terms.v2g.backward()
    assert all(p.grad is None or not p.grad.any() for p in model.visual.parameters())
    assert any(p.grad is not None and p.grad.any() for p in model.geometric.parameters())
    assert all(p.grad is not None for p in model.predictor.parameters())
    # while the visual loss does reach it
    model.zero_grad(set_to_none=True)
    model(_batch()).vis.backward()
    assert any(p.grad is not None and p.grad.any() for p in model.visual.parameters())


def test_degenerate_sample_is_left_out():
    batch = _batch(2)
    tiny = batch[1].view1._replace(point_index=torch.arange(2), coords=batch[1].view1.coords[:2])
    batch[1] = batch[1]._replace(view1=tiny)
    terms = _model("byoc-geo")(batch)
    assert terms.num_samples == 1 and torch.isfinite(terms.total)


@pytest.mark.slow
def test_loss_falls_when_overfitting_one_pair(shared_data):
    from byoc_cli.io.rgbd import discover_sequences
    from byoc_cli.training.data import PairDataset

    seqs = discover_sequences(shared_data / "rgbd" / "tum_fr1_desk")
    pair = PairDataset(seqs, 2, "train", use_color=False)[0]
    torch.manual_seed(0)
    model = ByocModel(variant="byoc-geo").train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, eps=1e-4)
    losses = []
    for _ in range(30):
        terms = model([pair])
        opt.zero_grad()
        terms.total.backward()
        opt.step()
        losses.append(terms.total.item())
    first, last = sum(losses[:3]) / 3, sum(losses[-3:]) / 3
    assert last < 0.7 * first, losses

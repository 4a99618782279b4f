"""Geometric encoders: registry, configuration round trip, output contract, gradients."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from byoc_cli.errors import ShapeError
from byoc_cli.models.encoder import (
    ENCODER_CONFIGS,
    EncoderConfig,
    GeometricEncoder,
    build_encoder,
    encode_voxels,
)


@pytest.fixture(autouse=True)
def _one_thread():
    """One intra-op thread: these tensors are tiny, so parallel regions only add overhead,
    and on a busy machine every one of them can stall for a scheduler time slice."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


#: Parameter count of MinkUNet34C (in 3, out 32), the paper's encoder (docs/training.md).
MINKUNET34C_PARAMETERS = 37.9e6

TINY = EncoderConfig(
    name="tiny",
    stem_channels=4,
    stem_kernel=3,
    encoder_channels=(6, 8),
    encoder_blocks=(1, 1),
    decoder_channels=(6, 4),
    decoder_blocks=(1, 0),
    out_dim=5,
)


def cloud(generator, n=300, extent=12, batch=0):
    """Distinct voxels of a random blob: ``(M, 4)`` int64 with batch column ``batch``."""
    xyz = torch.unique(torch.randint(0, extent, (n, 3), generator=generator), dim=0)
    return torch.cat([torch.full((xyz.shape[0], 1), batch), xyz], dim=1)


def ones(coords, channels=3):
    return torch.ones(coords.shape[0], channels)


def num_parameters(module):
    return sum(p.numel() for p in module.parameters())


def test_minkunet34c_parameter_count():
    count = num_parameters(build_encoder("minkunet34c"))
    assert abs(count - MINKUNET34C_PARAMETERS) / MINKUNET34C_PARAMETERS < 0.01


def test_minkunet34c_is_the_method_configuration():
    config = ENCODER_CONFIGS["minkunet34c"]
    assert (config.stem_kernel, config.stem_channels, config.block_kernel) == (5, 32, 3)
    assert config.encoder_channels == (32, 64, 128, 256)
    assert config.encoder_blocks == (2, 3, 4, 6)
    assert config.decoder_channels == (256, 128, 96, 96)
    assert config.decoder_blocks == (2, 2, 2, 2)
    assert (config.in_channels, config.out_dim) == (3, 32)
    final = build_encoder("minkunet34c").final
    assert final.weight.shape == (1, 96, 32) and final.bias is not None


@pytest.mark.parametrize("name", sorted(ENCODER_CONFIGS))
def test_config_round_trips_through_json(name):
    config = ENCODER_CONFIGS[name]
    assert config.name == name
    data = json.loads(json.dumps(dataclasses.asdict(config)))
    assert EncoderConfig(**data) == config
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.out_dim = 3  # type: ignore[misc]


def test_state_dict_names_are_stable():
    names = list(GeometricEncoder(TINY).state_dict())
    assert names[:2] == ["stem.conv.weight", "stem.bn.weight"]
    assert "down.0.conv.weight" in names and "enc.1.0.conv2.weight" in names
    assert "enc.0.0.shortcut.0.weight" in names and "enc.0.0.shortcut.1.running_var" in names
    assert "up.1.conv.weight" in names and "dec.0.0.bn1.bias" in names
    assert names[-2:] == ["final.weight", "final.bias"]


def test_build_encoder_errors_and_overrides():
    with pytest.raises(ValueError, match=r"compact.*minkunet34c"):
        build_encoder("resnet")
    assert build_encoder("compact", out_dim=16).config.out_dim == 16
    with pytest.raises(ValueError):
        build_encoder("compact", no_such_field=1)
    with pytest.raises(ValueError, match="one entry per stage"):
        EncoderConfig(name="x", encoder_blocks=(1, 1))
    with pytest.raises(ValueError, match="odd"):
        EncoderConfig(name="x", stem_kernel=4)


@pytest.mark.parametrize("config", [TINY, ENCODER_CONFIGS["compact"]], ids=["tiny", "compact"])
def test_output_contract_and_gradients(generator, config):
    torch.manual_seed(0)
    encoder = GeometricEncoder(config)
    coords = torch.cat([cloud(generator), cloud(generator, batch=1)])
    encoder.train()
    out = encoder(coords, ones(coords))
    assert out.shape == (coords.shape[0], config.out_dim) and out.dtype == torch.float32
    torch.testing.assert_close(out.norm(dim=1), torch.ones(coords.shape[0]))
    out[:, 0].sum().backward()
    grads = [p.grad for p in encoder.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0
    assert encoder.training  # forward never changes the mode
    encoder.eval()
    with torch.inference_mode():
        encoder(coords, ones(coords))
    assert not encoder.training


def test_eval_batch_independence_and_row_order(generator):
    torch.manual_seed(0)
    encoder = GeometricEncoder(TINY).eval()
    a, b = cloud(generator), cloud(generator, batch=1)
    b0 = b.clone()
    b0[:, 0] = 0
    with torch.no_grad():
        both = encoder(torch.cat([a, b]), ones(torch.cat([a, b])))
        alone = torch.cat([encoder(a, ones(a)), encoder(b0, ones(b0))])
        perm = torch.randperm(a.shape[0], generator=generator)
        permuted = encoder(a[perm], ones(a))
        reference = encoder(a, ones(a))
    torch.testing.assert_close(both, alone)
    torch.testing.assert_close(permuted, reference[perm])


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 60), shift=st.integers(-50, 50))
def test_translation_by_even_steps_is_invariant(seed, n, shift):
    """Shifting by a multiple of the coarsest stride keeps every level's cells: same output."""
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(0)
    encoder = GeometricEncoder(TINY).eval()
    coords = cloud(g, n=n, extent=6)
    moved = coords.clone()
    moved[:, 1:] += 4 * shift  # TINY has two stages: coarsest stride 4
    with torch.no_grad():
        out, out_moved = encoder(coords, ones(coords)), encoder(moved, ones(moved))
    torch.testing.assert_close(out, out_moved)
    assert torch.isfinite(out).all()


def test_encode_voxels_and_degenerate_sizes(generator):
    torch.manual_seed(0)
    encoder = GeometricEncoder(TINY).eval()
    xyz = cloud(generator)[:, 1:]
    with torch.no_grad():
        out = encode_voxels(encoder, xyz)
        full = encoder(
            torch.cat([torch.zeros(xyz.shape[0], 1, dtype=torch.int64), xyz], 1), ones(xyz)
        )
        single = encode_voxels(encoder, xyz[:1])
        empty = encode_voxels(encoder, xyz[:0])
    assert torch.equal(out, full)
    assert single.shape == (1, TINY.out_dim)
    torch.testing.assert_close(single.norm(dim=1), torch.ones(1))
    assert empty.shape == (0, TINY.out_dim)
    with pytest.raises(ShapeError):
        encode_voxels(encoder, xyz[:, :2])
    with pytest.raises(ShapeError, match="feats"):
        encoder(torch.zeros(2, 4, dtype=torch.int64), torch.ones(2, 2))


def test_deterministic(generator):
    torch.manual_seed(0)
    encoder = GeometricEncoder(TINY).eval()
    coords = cloud(generator, n=400)
    with torch.no_grad():
        assert torch.equal(encoder(coords, ones(coords)), encoder(coords, ones(coords)))


@pytest.mark.realdata
def test_compact_on_a_real_fragment(shared_data):
    from plyfile import PlyData

    from byoc_cli.geometry import voxelize

    path = (
        shared_data / "3dmatch" / "sample" / "3DMatch" / "7-scenes-redkitchen" / "cloud_bin_0.ply"
    )
    if not path.is_file():
        pytest.skip(f"{path} not found")
    vertex = PlyData.read(str(path))["vertex"]
    points = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    grid = voxelize(torch.from_numpy(points), 0.025)
    torch.manual_seed(0)
    encoder = build_encoder("compact").eval()
    with torch.inference_mode():
        feats = encode_voxels(encoder, grid.coords)
    assert feats.shape == (grid.coords.shape[0], 32)
    torch.testing.assert_close(feats.norm(dim=1), torch.ones(feats.shape[0]))


def test_runs_under_cpu_autocast(generator):
    torch.manual_seed(0)
    encoder = GeometricEncoder(TINY)
    coords = cloud(generator)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = encoder(coords, ones(coords))
    torch.testing.assert_close(
        out.float().norm(dim=1), torch.ones(coords.shape[0]), atol=0.02, rtol=0
    )
    out.float().sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in encoder.parameters())

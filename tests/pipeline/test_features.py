"""Feature extraction refuses clouds that cannot be registered, naming them."""

from __future__ import annotations

import pytest
import torch

from byoc_cli.errors import RegistrationError
from byoc_cli.pipeline.features import FpfhExtractor


def _line(n: int = 200, noise: float = 0.0) -> torch.Tensor:
    t = torch.linspace(0, 2, n, dtype=torch.float64)
    points = torch.stack([t, 2 * t, torch.ones_like(t)], dim=1)
    return points + noise * torch.randn(
        points.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )


def test_collinear_cloud_is_refused_with_its_label():
    with pytest.raises(RegistrationError, match=r"^scan\.ply: the points are collinear"):
        FpfhExtractor(0.05)(_line(), label="scan.ply")


def test_voxel_larger_than_the_cloud_is_refused():
    cube = torch.rand(500, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5
    with pytest.raises(RegistrationError, match="larger than the cloud"):
        FpfhExtractor(1e9)(cube, label="a.ply")
    assert FpfhExtractor(0.1)(cube, label="a.ply").feats.shape[1] == 33


def test_a_thick_line_is_not_collinear():
    # a 'line' 40 cm thick at a 5 cm voxel has structure across it
    assert FpfhExtractor(0.05)(_line(2000, noise=0.2)).points.shape[0] > 10


def test_an_encoder_given_as_a_function_is_built_once_on_first_use():
    from concurrent.futures import ThreadPoolExecutor

    from byoc_cli.models.encoder import build_encoder
    from byoc_cli.pipeline.features import ByocExtractor

    calls = []

    def build():
        calls.append(1)
        return build_encoder("compact")

    extractor = ByocExtractor(build, 0.05)
    assert not extractor.loaded and calls == []
    points = torch.rand(400, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda _: extractor(points).feats, range(4)))
    assert calls == [1] and extractor.loaded and not extractor.encoder.training
    for features in got[1:]:
        torch.testing.assert_close(features, got[0])

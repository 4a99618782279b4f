"""The engine's inputs (pipeline/inputs.py): clouds and depth images in metres."""

from __future__ import annotations

import numpy as np
import pytest


def test_a_loose_depth_image_reads_millimetres_and_refuses_an_implausible_depth(tmp_path):
    from PIL import Image

    from byoc_cli.errors import InputError
    from byoc_cli.pipeline.inputs import depth_scale_of, load_cloud

    K = tmp_path / "K.txt"
    K.write_text("50 0 32\n0 50 24\n0 0 1\n")
    near, far = tmp_path / "near.png", tmp_path / "far.png"
    Image.fromarray(np.full((48, 64), 1500, np.uint16)).save(near)
    Image.fromarray(np.full((48, 64), 40, np.uint16)).save(far)
    assert depth_scale_of(near) == (1000.0, "default")
    assert np.median(load_cloud(near, intrinsics=K)[:, 2]) == pytest.approx(1.5)
    with pytest.raises(InputError, match=r"median depth 0\.04 m .*--depth-scale"):
        load_cloud(far, intrinsics=K)
    assert np.median(load_cloud(far, intrinsics=K, depth_scale=40)[:, 2]) == pytest.approx(1.0)

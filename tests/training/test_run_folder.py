"""Run-folder helpers: how exported weights name their datasets."""

from __future__ import annotations

import pytest

from byoc_cli.training.run_folder import dataset_name


@pytest.mark.parametrize(
    ("given", "named"),
    [
        ("tum_fr1_xyz", "tum_fr1_xyz"),
        ("office/seq1", "office/seq1"),
        ("/work/shared/data/rgbd/tum_fr1_rpy", "tum_fr1_rpy"),
        ("/home/me/scans/office/", "office"),
        ("../shared/data/rgbd/tum_fr1_desk", "tum_fr1_desk"),
        ("~/scans/kitchen", "kitchen"),
    ],
)
def test_dataset_names_keep_sequence_names_and_drop_folders(given, named):
    assert dataset_name(given) == named

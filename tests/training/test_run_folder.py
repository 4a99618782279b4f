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


def test_a_failed_new_run_leaves_the_folder_as_it_found_it(tmp_path):
    from byoc_cli.training.run_folder import NewRunFolder

    absent = NewRunFolder(tmp_path / "a" / "b" / "run")
    (tmp_path / "a" / "b" / "run" / "pseudo_pairs").mkdir(parents=True)
    (tmp_path / "a" / "b" / "run" / "config.json").write_text("{}")
    absent.undo()
    assert list(tmp_path.iterdir()) == []  # the parents the run made go too

    kept = tmp_path / "restartable"
    kept.mkdir()
    (kept / "config.json").write_text("{}")
    (kept / "pseudo_pairs").mkdir()
    found = NewRunFolder(kept)
    (kept / "metrics.jsonl").write_text("")
    (kept / "new_cache").mkdir()
    (kept / "config.json").write_text('{"new": 1}')
    found.undo()
    assert sorted(p.name for p in kept.iterdir()) == ["config.json", "pseudo_pairs"]

    a_file = tmp_path / "file"
    a_file.write_text("x")
    NewRunFolder(a_file).undo()
    assert a_file.read_text() == "x"

from pathlib import Path

from byoc_cli.evaluation.method_features import weights_labels


def test_labels_are_stems_when_unique():
    assert weights_labels(["a/x.safetensors", "b/y.safetensors"]) == ["x", "y"]


def test_training_runs_are_told_apart_by_their_folder():
    paths = [Path("runs/geo/weights.safetensors"), Path("runs/full/weights.safetensors")]
    assert weights_labels([*paths, Path("random.safetensors")]) == [
        "geo/weights",
        "full/weights",
        "random",
    ]


def test_same_folder_and_stem_falls_back_to_position():
    paths = ["a/run/w.safetensors", "b/run/w.safetensors"]
    assert weights_labels(paths) == ["w#1", "w#2"]


def test_no_weights_no_labels():
    assert weights_labels([]) == []

import pytest

from byoc_cli.evaluation.methods import parse_method_names


def test_method_names_split_and_deduplicated():
    assert parse_method_names(["byoc,identity", "byoc fpfh-ransac"]) == [
        "byoc",
        "identity",
        "fpfh-ransac",
    ]
    with pytest.raises(ValueError, match="unknown method"):
        parse_method_names(["nope"])

"""The folders a command creates or fills (byoc_cli.io.folders)."""

from __future__ import annotations

import pytest

from byoc_cli.errors import InputError
from byoc_cli.io.folders import check_run_folder


def test_run_folder_policy(tmp_path):
    check_run_folder(tmp_path / "new", lambda p: False)
    (tmp_path / "empty").mkdir()
    check_run_folder(tmp_path / "empty", lambda p: False)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "weights.safetensors").write_bytes(b"user")
    with pytest.raises(InputError, match="not empty and not a byoc run folder"):
        check_run_folder(mine, lambda p: False)
    check_run_folder(mine, lambda p: True)
    with pytest.raises(InputError, match="not a folder"):
        check_run_folder(mine / "weights.safetensors", lambda p: False)

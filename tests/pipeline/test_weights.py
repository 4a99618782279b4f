"""Weights files: round trip, validation, refusal of anything that does not match the spec."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
import torch

from byoc_cli.errors import WeightsError
from byoc_cli.pipeline.weights import (
    init_weights,
    load_weights,
    save_weights,
    tensors_sha256,
    validate_metadata,
)


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> tuple[Path, torch.nn.Module, dict]:
    path = tmp_path_factory.mktemp("w") / "enc.safetensors"
    encoder, meta = init_weights("compact", seed=3)
    save_weights(path, encoder, meta)
    return path, encoder, meta


def _rewrite(path: Path, out: Path, edit_meta=None, edit_tensors=None) -> Path:
    from safetensors.torch import load, save

    blob = path.read_bytes()
    (n,) = struct.unpack("<Q", blob[:8])
    meta = json.loads(json.loads(blob[8 : 8 + n])["__metadata__"]["byoc"])
    tensors = load(blob)
    if edit_meta:
        edit_meta(meta)
    if edit_tensors:
        edit_tensors(tensors)
    out.write_bytes(save(tensors, metadata={"byoc": json.dumps(meta)}))
    return out


def test_round_trip_is_exact(saved):
    path, encoder, _meta = saved
    loaded = load_weights(path)
    for name, value in encoder.state_dict().items():
        assert torch.equal(value, loaded.encoder.state_dict()[name]), name
    assert loaded.metadata["architecture"] == "compact"
    assert loaded.metadata["training"]["variant"] == "random-init"
    assert len(loaded.file_sha256) == 64
    assert not loaded.encoder.training
    # built on the meta device (no random init) and given the file's tensors: none left behind
    tensors = [*loaded.encoder.parameters(), *loaded.encoder.buffers()]
    assert tensors and not any(t.is_meta for t in tensors)
    assert all(p.requires_grad for p in loaded.encoder.parameters())


def test_init_is_seeded_and_leaves_global_rng_alone(saved):
    _, encoder, _ = saved
    state = torch.get_rng_state()
    again, _ = init_weights("compact", seed=3)
    assert torch.equal(torch.get_rng_state(), state)
    for name, value in encoder.state_dict().items():
        assert torch.equal(value, again.state_dict()[name])


def test_checksum_is_order_independent():
    a = {"x": torch.ones(2), "y": torch.zeros(3, dtype=torch.int64)}
    b = {"y": torch.zeros(3, dtype=torch.int64), "x": torch.ones(2)}
    assert tensors_sha256(a) == tensors_sha256(b)
    assert tensors_sha256(a) != tensors_sha256(
        {"x": torch.ones(2), "y": torch.ones(3, dtype=torch.int64)}
    )


@pytest.mark.parametrize(
    ("edit_meta", "edit_tensors", "phrase"),
    [
        (lambda m: m.update(format_version=2), None, "newer than this byoc-cli"),
        (lambda m: m.update(format="other"), None, "not a byoc weights file"),
        (lambda m: m.pop("voxel_size"), None, "lacks 'voxel_size'"),
        (lambda m: m.update(architecture="resnet9000"), None, "unknown architecture"),
        (lambda m: m["training"].update(variant="supervised"), None, "unknown training variant"),
        (lambda m: m.update(feature_dim=16), None, "feature_dim"),
        (None, lambda t: t.update({k: t[k] + 1 for k in list(t)[:1]}), "checksum"),
    ],
)
def test_refuses_mismatching_files(saved, tmp_path, edit_meta, edit_tensors, phrase):
    bad = _rewrite(saved[0], tmp_path / "bad.safetensors", edit_meta, edit_tensors)
    with pytest.raises(WeightsError, match=phrase) as info:
        load_weights(bad)
    assert "bad.safetensors" in str(info.value)


def test_refuses_wrong_tensor_set_even_with_valid_checksum(saved, tmp_path):
    def drop_one(tensors):
        tensors.pop(sorted(tensors)[0])

    bad = _rewrite(saved[0], tmp_path / "bad.safetensors", edit_tensors=drop_one)
    # recompute the checksum so that only the tensor set is wrong
    from safetensors.torch import load, save

    blob = bad.read_bytes()
    (n,) = struct.unpack("<Q", blob[:8])
    meta = json.loads(json.loads(blob[8 : 8 + n])["__metadata__"]["byoc"])
    tensors = load(blob)
    meta["tensors_sha256"] = tensors_sha256(tensors)
    bad.write_bytes(save(tensors, metadata={"byoc": json.dumps(meta)}))
    with pytest.raises(WeightsError, match="missing tensor"):
        load_weights(bad)


@pytest.mark.parametrize(
    ("content", "phrase"),
    [
        (b"", "too short"),
        (b"\xff" * 64, "bad header length"),
        (b"\x04\0\0\0\0\0\0\0abcd", "not JSON"),
    ],
)
def test_refuses_non_safetensors(tmp_path, content, phrase):
    path = tmp_path / "x.safetensors"
    path.write_bytes(content)
    with pytest.raises(WeightsError, match=phrase):
        load_weights(path)


def test_missing_file_and_plain_safetensors(tmp_path):
    from safetensors.torch import save

    with pytest.raises(WeightsError, match="no such file"):
        load_weights(tmp_path / "none.safetensors")
    plain = tmp_path / "plain.safetensors"
    plain.write_bytes(save({"w": torch.zeros(2)}))
    with pytest.raises(WeightsError, match="no byoc metadata"):
        load_weights(plain)


def test_validate_metadata_rejects_non_object():
    with pytest.raises(WeightsError, match="not a JSON object"):
        validate_metadata("m.json", [1, 2])

"""Reading and writing weights files (see ``weights-spec/README.md``).

A weights file is safetensors (tensors) plus one JSON metadata object under the
header key ``byoc``. Nothing is ever unpickled.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import struct
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import torch

from byoc_cli import limits
from byoc_cli.errors import WeightsError
from byoc_cli.io.atomic import atomic_write_bytes
from byoc_cli.io.inputs import SIZE_CAPS, open_input
from byoc_cli.io.jsonout import strict_dumps
from byoc_cli.models.encoder import ENCODER_CONFIGS, EncoderConfig, GeometricEncoder

FORMAT = "byoc-weights"
FORMAT_VERSION = 1
METADATA_KEY = "byoc"
VARIANTS = ("byoc", "byoc-geo", "byoc-vis", "byoc-rot", "self-posed", "random-init")
_REQUIRED = {
    "format": str,
    "format_version": int,
    "architecture": str,
    "architecture_config": dict,
    "feature_dim": int,
    "voxel_size": (int, float),
    "training": dict,
    "code_version": str,
    "created": str,
    "tensors_sha256": str,
}
_TRAINING_REQUIRED = {"variant": str, "steps": int, "seed": int, "metrics": dict}
#: Largest safetensors header (JSON) read: names, shapes and offsets of the tensors and the
#: metadata take kilobytes; a JSON document is parsed into objects many times its size.
_MAX_HEADER_BYTES = 8 * 1024 * 1024
#: Hard limits checked before anything is built from the metadata.
MAX_VOXEL_SIZE = limits.MAX_VOXEL_SIZE
MAX_METRICS = 1000
_CONFIG_FIELDS = {f.name for f in dataclasses.fields(EncoderConfig)}


class LoadedWeights(NamedTuple):
    """A validated weights file.

    Attributes:
        encoder: the geometric encoder in eval mode, on CPU.
        metadata: the metadata object (see the spec).
        file_sha256: SHA-256 of the whole file (hex).
        path: where it was read from.
    """

    encoder: GeometricEncoder
    metadata: dict[str, Any]
    file_sha256: str
    path: str


def tensors_sha256(tensors: dict[str, torch.Tensor]) -> str:
    """Hash a tensor payload as the spec defines (name order; name, dtype, shape, bytes)."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        tensor = tensors[name].detach().cpu().contiguous()
        digest.update(name.encode("utf-8"))
        digest.update(str(tensor.dtype).removeprefix("torch.").encode("ascii"))
        digest.update(",".join(str(s) for s in tensor.shape).encode("ascii"))
        digest.update(tensor.numpy().astype(tensor.numpy().dtype.newbyteorder("<")).tobytes())
    return digest.hexdigest()


#: storage types of floating-point tensors (float16 halves the file; loaded as float32)
STORAGE_DTYPES = (torch.float32, torch.float16)


def _state_tensors(encoder: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().contiguous().clone() for k, v in encoder.state_dict().items()}


def build_metadata(
    encoder: GeometricEncoder,
    *,
    voxel_size: float,
    variant: str,
    data: Any = None,
    steps: int = 0,
    seed: int = 0,
    metrics: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Metadata for ``encoder`` (without ``tensors_sha256``, added by :func:`save_weights`)."""
    from byoc_cli import __version__

    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    config: EncoderConfig = encoder.config
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "architecture": config.name,
        "architecture_config": dataclasses.asdict(config),
        "feature_dim": int(config.out_dim),
        "voxel_size": float(voxel_size),
        "training": {
            "variant": variant,
            "data": data if data is not None else [],
            "steps": int(steps),
            "seed": int(seed),
            "metrics": {k: float(v) for k, v in (metrics or {}).items()},
        },
        "code_version": __version__,
        "created": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def save_weights(
    path: str | Path,
    encoder: GeometricEncoder,
    metadata: dict[str, Any],
    *,
    dtype: torch.dtype = torch.float32,
) -> str:
    """Write ``encoder`` with ``metadata`` atomically; returns the file's SHA-256.

    See :func:`weights_bytes` (what raises).
    """
    blob = weights_bytes(path, encoder, metadata, dtype=dtype)
    atomic_write_bytes(path, blob)
    return hashlib.sha256(blob).hexdigest()


def weights_bytes(
    path: str | Path,
    encoder: GeometricEncoder,
    metadata: dict[str, Any],
    *,
    dtype: torch.dtype = torch.float32,
) -> bytes:
    """The weights file of ``encoder`` with ``metadata`` (``path``: its name, for messages).

    ``dtype`` (float32 or float16) is the storage type of the floating-point tensors; the
    loader always builds a float32 encoder.

    Raises:
        WeightsError: naming ``path``, when the metadata breaks the spec or a tensor holds NaN
            or Inf (a diverged run): nothing is written that :func:`load_weights` refuses.
        ValueError: ``dtype`` is not float32 or float16.
    """
    from safetensors.torch import save

    if dtype not in STORAGE_DTYPES:
        raise ValueError(f"dtype must be float32 or float16, got {dtype}")
    tensors = {
        k: v.to(dtype) if v.is_floating_point() else v for k, v in _state_tensors(encoder).items()
    }
    # never write a file that load_weights refuses
    validate_metadata(path, {**metadata, "tensors_sha256": ""})
    _check_finite(path, tensors)
    meta = dict(metadata)
    meta["tensors_sha256"] = tensors_sha256(tensors)
    return save(tensors, metadata={METADATA_KEY: strict_dumps(meta, sort_keys=True)})


def _read_header(path: Path, f: BinaryIO) -> dict[str, Any]:
    """The safetensors header of the weights file open as ``f`` (read from its start; the
    tensor data is not read)."""
    size = os.fstat(f.fileno()).st_size
    head = f.read(8)
    if len(head) < 8:
        raise WeightsError(path, "not a safetensors file (too short)")
    (header_len,) = struct.unpack("<Q", head)
    if header_len > min(_MAX_HEADER_BYTES, size - 8):
        raise WeightsError(path, "not a safetensors file (bad header length)")
    try:
        header = json.loads(f.read(header_len))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise WeightsError(path, "not a safetensors file (header is not JSON)") from exc
    if not isinstance(header, dict):
        raise WeightsError(path, "not a safetensors file (header is not an object)")
    return header


def _metadata(path: Path, header: dict[str, Any]) -> Any:
    """The byoc metadata object of a safetensors header (not yet validated)."""
    raw_meta = header.get("__metadata__")
    raw_meta = raw_meta.get(METADATA_KEY) if isinstance(raw_meta, dict) else None
    if raw_meta is None:
        raise WeightsError(path, "safetensors file has no byoc metadata (not a byoc weights file)")
    try:
        return json.loads(raw_meta)
    except (TypeError, json.JSONDecodeError, RecursionError) as exc:
        raise WeightsError(path, "byoc metadata is not valid JSON") from exc


def _check_finite(path: str | Path, tensors: dict[str, torch.Tensor]) -> None:
    """Refuse tensors holding NaN or Inf (a diverged training run): they give NaN features.

    Raises:
        WeightsError: naming the first such tensor.
    """
    for name in sorted(tensors):
        tensor = tensors[name]
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise WeightsError(path, f"tensor {name!r} holds NaN or Inf values")


def validate_metadata(path: str | Path, meta: Any) -> EncoderConfig:
    """Check a metadata object against the spec; return the encoder configuration.

    Raises:
        WeightsError: naming the first problem found.
    """
    if not isinstance(meta, dict):
        raise WeightsError(path, "metadata is not a JSON object")
    if meta.get("format") != FORMAT:
        raise WeightsError(path, f"not a byoc weights file (format is {meta.get('format')!r})")
    version = meta.get("format_version")
    if isinstance(version, int) and version > FORMAT_VERSION:
        raise WeightsError(
            path,
            f"format version {version} is newer than this byoc-cli supports "
            f"({FORMAT_VERSION}); upgrade byoc-cli",
        )
    for key, kind in _REQUIRED.items():
        if key not in meta:
            raise WeightsError(path, f"metadata lacks '{key}'")
        if not isinstance(meta[key], kind) or isinstance(meta[key], bool):
            raise WeightsError(path, f"metadata '{key}' has the wrong type")
    if version != FORMAT_VERSION:
        raise WeightsError(path, f"unsupported format version {version!r}")
    for key, kind in _TRAINING_REQUIRED.items():
        value = meta["training"].get(key)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise WeightsError(path, f"metadata 'training.{key}' is missing or has the wrong type")
    if meta["training"]["variant"] not in VARIANTS:
        raise WeightsError(path, f"unknown training variant {meta['training']['variant']!r}")
    arch = meta["architecture"]
    if arch not in ENCODER_CONFIGS:
        raise WeightsError(
            path, f"unknown architecture {arch!r} (known: {', '.join(sorted(ENCODER_CONFIGS))})"
        )
    voxel = meta["voxel_size"]
    if not (math.isfinite(voxel) and 0 < voxel <= MAX_VOXEL_SIZE):
        raise WeightsError(
            path, f"metadata 'voxel_size' must be in (0, {MAX_VOXEL_SIZE:g}] m, got {voxel!r}"
        )
    _check_training(path, meta["training"])
    config = _named_config(path, arch, meta["architecture_config"])
    if config.out_dim != meta["feature_dim"]:
        raise WeightsError(path, "feature_dim does not match architecture_config")
    return config


def _check_training(path: str | Path, training: dict[str, Any]) -> None:
    """Steps and seed are non-negative, metrics a small object of numbers (or null)."""
    for key in ("steps", "seed"):
        if training[key] < 0:
            raise WeightsError(path, f"metadata 'training.{key}' must be >= 0")
    metrics = training["metrics"]
    if len(metrics) > MAX_METRICS:
        raise WeightsError(path, f"metadata 'training.metrics' has more than {MAX_METRICS} entries")
    for name, value in metrics.items():
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if value is not None and not number:
            raise WeightsError(
                path, f"metadata 'training.metrics.{name}' is not a number ({type(value).__name__})"
            )


def _named_config(path: str | Path, arch: str, raw: dict[str, Any]) -> EncoderConfig:
    """The configuration of ``arch``, after checking that ``raw`` describes exactly it.

    Nothing is built from ``raw``: an absurd width (say a million channels) is refused
    here instead of being allocated.
    """
    expected = dataclasses.asdict(ENCODER_CONFIGS[arch])
    unknown = sorted(set(raw) - _CONFIG_FIELDS)
    if unknown:
        raise WeightsError(path, f"architecture_config has an unknown key {unknown[0]!r}")
    for key, want in expected.items():
        got = raw.get(key)
        if (tuple(got) if isinstance(want, tuple) and isinstance(got, list) else got) != want:
            shown = repr(got) if len(repr(got)) <= 60 else f"{repr(got)[:57]}..."
            raise WeightsError(
                path,
                f"architecture_config does not fit {arch!r}: {key} is {shown}, "
                f"expected {list(want) if isinstance(want, tuple) else want!r}",
            )
    return ENCODER_CONFIGS[arch]


def read_metadata(path: str | Path) -> tuple[dict[str, Any], str]:
    """The validated metadata of a weights file and the SHA-256 of the whole file (hex),
    without decoding its tensors: what a report says of the weights before the encoder is
    built (:func:`load_weights` checks the tensors).

    Raises:
        WeightsError: the file is missing, not a regular file, larger than a weights file may
            be, not safetensors, or its metadata does not match the spec.
    """
    meta, _, blob = _read_checked(Path(path))
    return meta, hashlib.sha256(blob).hexdigest()


def _read_checked(path: Path) -> tuple[dict[str, Any], EncoderConfig, bytes]:
    """The validated metadata, the encoder configuration and the whole file's bytes of a
    weights file; the header and the metadata are checked before the tensor data is read.

    Raises:
        WeightsError: as :func:`read_metadata`.
    """
    with open_input(path, "weights", WeightsError) as f:
        meta = _metadata(path, _read_header(path, f))
        config = validate_metadata(path, meta)
        f.seek(0)
        blob = f.read(SIZE_CAPS["weights"][0] + 1)
    return meta, config, blob


def load_weights(path: str | Path) -> LoadedWeights:
    """Read, validate and build the encoder of a weights file.

    Raises:
        WeightsError: the file is missing, not a regular file, larger than a weights file may
            be, not safetensors, or does not match the spec (metadata, tensor names, shapes,
            dtypes or checksum), or a tensor holds NaN or Inf.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load

    path = Path(path)
    meta, config, blob = _read_checked(path)
    try:
        tensors = load(blob)
    except (SafetensorError, ValueError, RuntimeError) as exc:
        raise WeightsError(path, f"corrupt tensor data ({exc})") from exc
    if tensors_sha256(tensors) != meta["tensors_sha256"]:
        raise WeightsError(path, "tensor checksum mismatch (file corrupt or edited)")
    _check_finite(path, tensors)
    with torch.device("meta"):  # no memory and no random init: every tensor is the file's
        encoder = GeometricEncoder(config)
    expected = encoder.state_dict()
    missing = sorted(set(expected) - set(tensors))
    extra = sorted(set(tensors) - set(expected))
    if missing or extra:
        what = f"missing tensor {missing[0]!r}" if missing else f"unexpected tensor {extra[0]!r}"
        raise WeightsError(path, f"tensors do not match architecture {config.name!r}: {what}")
    for name, ref in expected.items():
        got = tensors[name]
        stored_ok = got.dtype == ref.dtype or (
            ref.dtype == torch.float32 and got.dtype in STORAGE_DTYPES
        )
        if got.shape != ref.shape or not stored_ok:
            raise WeightsError(
                path,
                f"tensor {name!r} is {got.dtype} {tuple(got.shape)}, "
                f"expected {ref.dtype} {tuple(ref.shape)}",
            )
    tensors = {k: v.float() if v.is_floating_point() else v for k, v in tensors.items()}
    encoder.load_state_dict(tensors, strict=True, assign=True)
    left = [n for n, t in (*encoder.named_parameters(), *encoder.named_buffers()) if t.is_meta]
    if left:  # a tensor the state dict does not hold (none today): never run on meta
        raise WeightsError(path, f"architecture {config.name!r} has no stored {left[0]!r}")
    encoder.eval()
    return LoadedWeights(encoder, meta, hashlib.sha256(blob).hexdigest(), str(path))


def init_weights(arch: str, seed: int, voxel_size: float = 0.025) -> tuple[GeometricEncoder, dict]:
    """A randomly initialised encoder (seeded) and its ``random-init`` metadata."""
    from byoc_cli.models.encoder import build_encoder

    fork_devices: list = []
    with torch.random.fork_rng(devices=fork_devices):
        torch.manual_seed(seed)
        encoder = build_encoder(arch)
    encoder.eval()
    meta = build_metadata(encoder, voxel_size=voxel_size, variant="random-init", seed=seed)
    return encoder, meta

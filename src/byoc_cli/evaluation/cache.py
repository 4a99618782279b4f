"""An on-disk cache of per-cloud features, so that re-running an evaluation is fast.

One ``.npz`` file per (input cloud, feature settings): the key is the SHA-256 of a JSON object
holding the feature identity (extractor, voxel size, weights hash, FPFH radii, ...) and the
input identity (resolved path, size and modification time of the file, plus whatever turns the
file into points, e.g. depth intrinsics). Files are written atomically; an unreadable or
mismatching file is recomputed (with a warning) and replaced.
"""

from __future__ import annotations

import hashlib
import io
import json
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from byoc_cli.errors import InputError
from byoc_cli.io.inputs import open_input
from byoc_cli.pipeline.features import CloudFeatures

__all__ = ["CACHE_VERSION", "FeatureCache", "file_identity"]

#: Bumped whenever the cached content or its meaning changes.
CACHE_VERSION = 1


def file_identity(path: str | Path, **extra: Any) -> dict[str, Any]:
    """Identity of an input file: resolved path, size, mtime (ns), plus ``extra`` settings.

    Raises:
        OSError: the file cannot be stat'ed (callers check existence first).
    """
    path = Path(path).resolve()
    st = path.stat()
    return {"path": str(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns, **extra}


class FeatureCache:
    """Features on disk under ``root`` (None: no disk cache, every call computes).

    Attributes:
        root: the cache folder, created on first write.
        hits, misses: lookups served from disk / computed.
    """

    def __init__(self, root: str | Path | None) -> None:
        self.root = Path(root) if root is not None else None
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(features: dict[str, Any], source: dict[str, Any]) -> str:
        """SHA-256 (hex) of the feature identity and the input identity."""
        blob = json.dumps(
            {"version": CACHE_VERSION, "features": features, "input": source},
            sort_keys=True,
            default=str,
        )
        return hashlib.sha256(blob.encode("utf-8")).hexdigest()

    def path(self, features: dict[str, Any], source: dict[str, Any]) -> Path | None:
        """Where the entry lives: ``root/<extractor>/<key[:40]>.npz`` (None without root)."""
        if self.root is None:
            return None
        folder = str(features.get("extractor", "features"))
        return self.root / folder / f"{self.key(features, source)[:40]}.npz"

    def get(
        self,
        features: dict[str, Any],
        source: dict[str, Any],
        compute: Callable[[], CloudFeatures],
    ) -> CloudFeatures:
        """The cached features of ``source`` under ``features``, computing them when absent.

        Args:
            features: JSON-able identity of the feature settings.
            source: JSON-able identity of the input (see :func:`file_identity`).
            compute: returns the features on a miss.

        Returns:
            :class:`CloudFeatures` (points float64, feats float32, indices int64).

        Raises:
            InputError: the cache file cannot be written (folder not writable, disk full).
        """
        path = self.path(features, source)
        key = self.key(features, source)
        if path is not None and path.is_file():
            loaded = self._load(path, key)
            if loaded is not None:
                self.hits += 1
                return loaded
        self.misses += 1
        result = compute()
        if path is not None:
            self._save(path, key, result)
        return result

    @staticmethod
    def _load(path: Path, key: str) -> CloudFeatures | None:
        try:
            with open_input(path, "cache") as f, np.load(f, allow_pickle=False) as data:
                if str(data["key"]) != key:
                    raise ValueError("key mismatch")
                points = torch.from_numpy(np.array(data["points"], dtype=np.float64))
                feats = torch.from_numpy(np.array(data["feats"], dtype=np.float32))
                index = torch.from_numpy(np.array(data["point_index"], dtype=np.int64))
                coords = torch.from_numpy(np.array(data["coords"], dtype=np.int64))
        except (OSError, KeyError, ValueError, zipfile.BadZipFile, InputError) as exc:
            warnings.warn(
                f"{path}: unusable feature cache entry ({exc}); recomputing", stacklevel=3
            )
            return None
        n = points.shape[0]
        if points.shape != (n, 3) or feats.shape[0] != n or index.shape != (n,):
            warnings.warn(f"{path}: feature cache entry has bad shapes; recomputing", stacklevel=3)
            return None
        return CloudFeatures(points, feats, index, coords)

    @staticmethod
    def _save(path: Path, key: str, cloud: CloudFeatures) -> None:
        from byoc_cli.errors import InputError
        from byoc_cli.io.atomic import atomic_write_bytes

        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(path.parent, f"cannot create the cache folder ({exc})") from exc
        buffer = io.BytesIO()
        np.savez(
            buffer,
            key=np.array(key),
            points=cloud.points.detach().cpu().numpy().astype(np.float64),
            feats=cloud.feats.detach().cpu().numpy().astype(np.float32),
            point_index=cloud.point_index.detach().cpu().numpy().astype(np.int64),
            coords=cloud.coords.detach().cpu().numpy().astype(np.int64),
        )
        atomic_write_bytes(path, buffer.getvalue())

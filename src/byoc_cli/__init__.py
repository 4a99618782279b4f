"""byoc-cli: point-cloud registration with self-supervised BYOC features.

The Python API (:mod:`byoc_cli.api`) is importable from here and loaded on first use, so that
``import byoc_cli`` (and ``byoc --help``) stays light::

    from byoc_cli import register
    result = register("source.ply", "target.ply")   # result.T_tgt_src, result.confidence
"""

from importlib.metadata import PackageNotFoundError, version
from typing import Any

try:
    __version__ = version("byoc-cli")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0+unknown"

#: names of the Python API, imported from :mod:`byoc_cli.api` when first used
_API = (
    "Features",
    "Registrar",
    "Registration",
    "extract_features",
    "load_cloud",
    "load_weights",
    "register",
)

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    if name in _API:
        from byoc_cli import api

        return getattr(api, name)
    raise AttributeError(f"module 'byoc_cli' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)

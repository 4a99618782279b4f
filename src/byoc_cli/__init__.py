"""byoc-cli: point-cloud registration with self-supervised BYOC features."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("byoc-cli")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0+unknown"

__all__ = ["__version__"]

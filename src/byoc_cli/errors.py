"""Typed errors raised by the core.

Every error the library raises on purpose derives from :class:`ByocError`. The
CLI turns these into a one-line message on stderr and exit code 1; library
code never prints or exits.
"""

from __future__ import annotations

import sys
import threading
import types


class ByocError(Exception):
    """Base class of every error raised on purpose by byoc-cli."""


class ShapeError(ByocError, ValueError):
    """A tensor or array has the wrong shape, dtype or size."""


class InputError(ByocError):
    """An input file is missing, unreadable, malformed or unusable.

    Args:
        path: the offending file (or folder).
        problem: what is wrong with it, as a short phrase.
    """

    def __init__(self, path: object, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class DatasetError(InputError):
    """A dataset folder (RGB-D video, 3DMatch benchmark) cannot be used."""


class WeightsError(InputError):
    """A weights file does not match the weights specification."""


class DependencyError(ByocError):
    """An optional dependency (open3d) is missing or fails to import."""


class RegistrationError(ByocError):
    """Registration could not produce a transform (e.g. no correspondences)."""


class TrainingError(ByocError):
    """Training cannot go on: the loss or the weights became NaN or Inf (diverged)."""


#: the first import of open3d, one thread at a time (:func:`require_open3d`)
_OPEN3D_IMPORT = threading.Lock()
#: the subpackage open3d imports on import and byoc never uses: its plotting helpers import
#: dash, plotly and IPython, about 0.6 CPU-seconds of open3d's 0.9 (``python -X importtime``)
_OPEN3D_VISUALIZATION = "open3d.visualization"


def require_open3d():
    """Import open3d lazily, with an install hint if that fails.

    The first import skips ``open3d.visualization`` (a placeholder stands in for it while
    open3d imports, and is taken away after): ``open3d.visualization`` is imported when it is
    first asked for (``import open3d.visualization``, or the attribute of the package, as
    the Python API's users may do after a registration). Where that fails (another open3d),
    open3d is imported as it is.

    Returns:
        The ``open3d`` module.

    Raises:
        DependencyError: open3d is not installed or its import fails (for
            instance when the system library libusb-1.0 is missing).
    """
    try:
        with _OPEN3D_IMPORT:
            o3d = sys.modules.get("open3d") or _import_open3d()
    except Exception as exc:  # ImportError, OSError from a missing shared library
        raise DependencyError(
            f"open3d is needed for this feature but could not be imported ({exc}); "
            "install it with `pip install open3d-cpu` (Linux x86-64) or `pip install open3d`, "
            "and on Debian/Ubuntu `apt-get install -y libusb-1.0-0`"
        ) from exc
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def _import_open3d():
    """``import open3d`` without its visualization subpackage (:func:`require_open3d`);
    as it is where that fails."""
    placeholder = types.ModuleType(_OPEN3D_VISUALIZATION)
    sys.modules.setdefault(_OPEN3D_VISUALIZATION, placeholder)
    try:
        import open3d
    except Exception:
        open3d = None
    finally:
        if sys.modules.get(_OPEN3D_VISUALIZATION) is placeholder:
            del sys.modules[_OPEN3D_VISUALIZATION]
        package = sys.modules.get("open3d")
        if getattr(package, "visualization", None) is placeholder:
            del package.visualization
    if open3d is None:
        import open3d
    elif "visualization" not in vars(open3d) and "__getattr__" not in vars(open3d):
        open3d.__getattr__ = _visualization_on_demand
    return open3d


def _visualization_on_demand(name: str):
    """The open3d package's attribute ``name`` that is not there yet (PEP 562): its
    ``visualization`` subpackage, imported now (:func:`_import_open3d` left it out)."""
    if name == "visualization":
        import importlib

        return importlib.import_module(_OPEN3D_VISUALIZATION)
    raise AttributeError(f"module 'open3d' has no attribute {name!r}")

"""The registered dataset layouts, in detection order.

Discovery asks the layouts in this order whether a folder is one of their sequences; the
first that says yes reads it. Adding a layout: write a module next to ``tum.py`` that defines
``LAYOUT = Layout(...)`` (see :class:`~byoc_cli.io.rgbd.layout.Layout`) and add it to
:data:`BUILTIN_LAYOUTS` before ``redwood`` (the catch-all "folder with a ``depth/``"), or
register it at run time with :func:`register_layout`.
"""

from __future__ import annotations

import os
from pathlib import Path

from byoc_cli.io.rgbd import redwood, scannet, threedmatch, tum
from byoc_cli.io.rgbd.layout import Layout

#: The layouts of this package, in detection order.
BUILTIN_LAYOUTS: tuple[Layout, ...] = (
    tum.LAYOUT,
    threedmatch.LAYOUT,
    scannet.LAYOUT,
    redwood.LAYOUT,
)

#: Names of the built-in layouts, as in :attr:`RGBDSequence.layout`.
LAYOUTS = tuple(layout.name for layout in BUILTIN_LAYOUTS)

#: Raw depth units per metre of each built-in layout (overridable with ``depth_scale``).
DEFAULT_DEPTH_SCALE = {layout.name: layout.depth_scale for layout in BUILTIN_LAYOUTS}

_REGISTRY: list[Layout] = list(BUILTIN_LAYOUTS)


def registered_layouts() -> tuple[Layout, ...]:
    """The registered layouts, in detection order."""
    return tuple(_REGISTRY)


def register_layout(layout: Layout, *, before: str | None = None) -> None:
    """Add a layout to discovery.

    Args:
        layout: the new layout.
        before: the name of a registered layout to detect after it (e.g. ``"redwood"``,
            whose "folder with a ``depth/``" test would otherwise claim many layouts);
            None: last.

    Raises:
        ValueError: a layout of that name is registered already, or ``before`` is not one.
    """
    names = [known.name for known in _REGISTRY]
    if layout.name in names:
        raise ValueError(f"an RGB-D layout named {layout.name!r} is registered already")
    if before is None:
        _REGISTRY.append(layout)
        return
    if before not in names:
        raise ValueError(f"no registered RGB-D layout named {before!r} (known: {names})")
    _REGISTRY.insert(names.index(before), layout)


def unregister_layout(name: str) -> None:
    """Remove a layout from discovery.

    Raises:
        ValueError: no layout of that name is registered.
    """
    for k, known in enumerate(_REGISTRY):
        if known.name == name:
            del _REGISTRY[k]
            return
    raise ValueError(f"no registered RGB-D layout named {name!r}")


def detect_layout(folder: Path, names: list[str]) -> Layout | None:
    """The first registered layout that recognises ``folder`` (sorted entry ``names``)."""
    for layout in _REGISTRY:
        if layout.detect(folder, names):
            return layout
    return None


def layout_of_depth_image(path: Path) -> tuple[Layout, Path] | None:
    """The layout of the sequence a single depth image belongs to, and its folder: the
    image's own folder (3DMatch ``seq-01/frame-N.depth.png``) or its parent (TUM
    ``SEQ/depth/T.png`` beside ``SEQ/depth.txt``, ScanNet and Redwood ``SEQ/depth/N.png``);
    None when neither is a sequence of a registered layout (or cannot be listed)."""
    folder = Path(path).absolute().parent
    for candidate in (folder, folder.parent):
        try:
            names = sorted(os.listdir(candidate))
        except OSError:
            continue
        layout = detect_layout(candidate, names)
        if layout is not None:
            return layout, candidate
    return None


def not_found_message() -> str:
    """The "no sequence found" message, naming what every registered layout looks for."""
    looked = ", ".join(layout.description for layout in _REGISTRY)
    return f"no RGB-D sequence found (looked for {looked})"

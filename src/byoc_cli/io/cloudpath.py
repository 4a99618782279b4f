"""A cloud's name on the command line: a file, or one scan of a multi-scan file.

An E57 file holds one or more scans. One scan of it is named by the file and the scan's index
after a colon, ``site.e57:2`` (0-based, in the order the file lists its scans, which is
pye57's and libE57Format's ``data3D`` index). A colon, not ``#``: ``#`` starts a comment in
``register-batch`` pair lists. The selector is read only when no file of that exact name
exists, so a file really named ``a.e57:2`` is still read as itself.

Nothing here reads a file or imports numpy: commands use it before their work starts
(output checks, names of pose files).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import NamedTuple

__all__ = ["CloudPath", "cloud_file", "cloud_stem", "parse_cloud_path", "scan_path"]

_SCAN = re.compile(r"^(?P<file>.+\.e57):(?P<scan>\d+)$", re.IGNORECASE)


class CloudPath(NamedTuple):
    """A cloud as named: its file and, for one scan of a multi-scan file, the scan's index.

    Attributes:
        file: the file to read.
        scan: 0-based scan index (``site.e57:2`` -> 2), or None for the whole file.
    """

    file: Path
    scan: int | None


def parse_cloud_path(path: str | os.PathLike[str]) -> CloudPath:
    """Split ``site.e57:2`` into ``(site.e57, 2)``; any other path (or an existing file of
    that exact name) is ``(path, None)``."""
    text = os.fspath(path)
    match = _SCAN.match(text)
    if match is None or os.path.lexists(text):
        return CloudPath(Path(text), None)
    return CloudPath(Path(match["file"]), int(match["scan"]))


def cloud_file(path: str | os.PathLike[str]) -> Path:
    """The file a cloud name reads (``site.e57:2`` -> ``site.e57``)."""
    return parse_cloud_path(path).file


def scan_path(path: str | os.PathLike[str], scan: int) -> Path:
    """The name of scan ``scan`` of the multi-scan file ``path`` (``site.e57:2``)."""
    return Path(f"{os.fspath(path)}:{scan}")


def cloud_stem(path: str | os.PathLike[str]) -> str:
    """A short name of a cloud for the files made from it: the file's stem, and for one scan
    of a multi-scan file ``<stem>_scan<k>`` (``site.e57:2`` -> ``site_scan2``)."""
    file, scan = parse_cloud_path(path)
    return file.stem if scan is None else f"{file.stem}_scan{scan}"

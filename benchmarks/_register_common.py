"""What the parts of benchmarks/register.py share: the data, the voxel, the `byoc` command line
and the environment of a command of another source tree.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("BYOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
SAMPLE = DATA / "3dmatch" / "sample" / "3DMatch" / "7-scenes-redkitchen"
VOXEL = 0.025
BYOC = [sys.executable, "-m", "byoc_cli.cli.main", "-q"]


def source_env(source: Path | None) -> dict[str, str] | None:
    """The environment of a command of another source tree (None: this one's)."""
    if source is None:
        return None
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": f"{source}{os.pathsep}{path}" if path else str(source)}

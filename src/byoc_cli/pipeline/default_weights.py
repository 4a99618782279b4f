"""The weights that ship with byoc-cli (installed with the package, checksummed).

``byoc_cli/data/weights/default.safetensors`` is the encoder ``byoc register`` uses when no
``--weights`` is given; ``default.sha256`` beside it holds the file's SHA-256, checked on
every load so that a damaged install is refused instead of registering badly.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from byoc_cli.errors import WeightsError
from byoc_cli.io.inputs import read_input

#: folder of the shipped weights inside the installed package
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "data" / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "default.safetensors"
DEFAULT_CHECKSUM = WEIGHTS_DIR / "default.sha256"


def default_weights_path() -> Path | None:
    """The shipped weights file, or None when this install ships none."""
    return DEFAULT_WEIGHTS if DEFAULT_WEIGHTS.is_file() else None  # read at call time


def verify_default_weights(path: Path | None = None, checksum: Path | None = None) -> str:
    """Check the shipped file against its recorded SHA-256; returns the digest.

    ``path`` and ``checksum`` default to :data:`DEFAULT_WEIGHTS` and :data:`DEFAULT_CHECKSUM`.

    Raises:
        WeightsError: the file or its checksum is missing, or they disagree.
    """
    path = DEFAULT_WEIGHTS if path is None else path
    if not path.is_file():
        raise WeightsError(path, "no weights ship with this install (pass --weights FILE)")
    digest = hashlib.sha256(read_input(path, "weights", WeightsError)).hexdigest()
    _check_digest(path, digest, DEFAULT_CHECKSUM if checksum is None else checksum)
    return digest


def _check_digest(path: Path, digest: str, checksum: Path) -> None:
    """Raise unless ``digest`` is the SHA-256 recorded in ``checksum``."""
    try:
        expected = checksum.read_text(encoding="ascii").split()[0].strip().lower()
    except (OSError, IndexError, UnicodeDecodeError) as exc:
        raise WeightsError(
            checksum, "the shipped weights' checksum file is missing or empty"
        ) from exc
    if digest != expected:
        raise WeightsError(
            path, "the shipped weights do not match their checksum (reinstall byoc-cli)"
        )


def load_default_weights():
    """Verify and load the shipped weights (a ``LoadedWeights``).

    Raises:
        WeightsError: nothing ships, the checksum disagrees, or the file is invalid.
    """
    from byoc_cli.pipeline.weights import load_weights

    if not DEFAULT_WEIGHTS.is_file():
        raise WeightsError(
            DEFAULT_WEIGHTS, "no weights ship with this install (pass --weights FILE)"
        )
    loaded = load_weights(DEFAULT_WEIGHTS)  # one read: it hashes the whole file too
    _check_digest(DEFAULT_WEIGHTS, loaded.file_sha256, DEFAULT_CHECKSUM)
    return loaded


def default_weights_metadata() -> tuple[dict, str]:
    """The metadata of the shipped weights and the file's SHA-256, the file checked against
    its recorded checksum, its tensors not read (:func:`load_default_weights` reads them).

    Raises:
        WeightsError: nothing ships, the checksum disagrees, or the metadata is invalid.
    """
    from byoc_cli.pipeline.weights import read_metadata

    if not DEFAULT_WEIGHTS.is_file():
        raise WeightsError(
            DEFAULT_WEIGHTS, "no weights ship with this install (pass --weights FILE)"
        )
    meta, digest = read_metadata(DEFAULT_WEIGHTS)
    _check_digest(DEFAULT_WEIGHTS, digest, DEFAULT_CHECKSUM)
    return meta, digest

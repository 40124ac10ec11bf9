"""The one checksum of data files: SHA-256 of a regular file, read in 1 MiB chunks.

Provenance files record it (:mod:`daror_runtime.data.provenance`), model files record their
training data's (:mod:`daror_runtime.models.files`), and a session compares a validation file's
with its model's training data (held-out data is another file, not the same bytes renamed).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from daror_runtime.errors import DataError
from hal.files import DATA_MAX_BYTES, regular_file

__all__ = ["file_sha256"]


def file_sha256(path: Path | str) -> str:
    """SHA-256 of a data file, as 64 hexadecimal digits (regular files only: a FIFO or device named here is refused, never read).

    Raises:
        DataError: not a readable regular file, or larger than the data files' bound.
    """
    digest = hashlib.sha256()
    with open(regular_file(path, DataError, DATA_MAX_BYTES, "data file"), "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()

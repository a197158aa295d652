"""SHA-256 of a file, read in 1 MiB blocks (frames, samples tables, data files can be large)."""

from __future__ import annotations

import hashlib
import os

from plumbing.inputs import open_input

__all__ = ["sha256_file"]


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of the file's bytes."""
    h = hashlib.sha256()
    with open_input(path, "file") as fh:  # a FIFO or device is refused, never waited on
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()

"""Atomic file writes, shared by every stage (this is the lowest layer, so all may import it).

A reader — or a crash — never sees a half-written file: the bytes go to a temp file in the same
directory, are fsync'd, then moved into place (rename, or link when overwriting is forbidden),
and the directory entry is fsync'd too.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

__all__ = ["atomic_write_bytes", "atomic_write_with", "fsync_dir"]


def fsync_dir(path: str | os.PathLike) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_with(
    path: str | os.PathLike, write: Callable[[BinaryIO], None], *, overwrite: bool = True
) -> Path:
    """Call `write(fh)` on a temp file beside `path`, fsync, then move it into place.

    With overwrite=False the move is `os.link`, which raises FileExistsError rather than
    replace an existing file (a captured frame is never overwritten).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        if overwrite:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    fsync_dir(path.parent)
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, overwrite: bool = True) -> Path:
    return atomic_write_with(path, lambda fh: fh.write(data), overwrite=overwrite)

"""Atomic file writes, shared by every layer.

A reader — or a crash — never sees a half-written file: the bytes go to a temp file in the same
directory, are fsync'd, then moved into place, and the directory entry is fsync'd too.

One default: **never overwrite** (the move is `os.link`, which raises FileExistsError rather
than replace a file — a captured frame or an earlier result is never lost by accident). A caller
that means to replace a file it owns says so with `overwrite=True` (then `os.replace`).

Never replaced, with or without `overwrite`: a symlink (the move would put a regular file in
place of the link) and anything that is not a regular file (a device, a FIFO, a directory,
a socket) — the write is refused before a byte is written (`NotARegularFile`).

A writer killed mid-write (kill -9, a power cut) leaves its temp file `.NAME.tmp-PID` behind; the
next write of NAME removes those whose process is gone, and says so on the log (stderr).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from plumbing.errors import UserError

__all__ = [
    "NotARegularFile",
    "atomic_write_bytes",
    "atomic_write_with",
    "fsync_dir",
    "check_writable_dir",
]


class NotARegularFile(UserError, OSError):
    """An output path that is a symlink, device, FIFO, socket or directory."""


def _refuse_special(path: Path) -> None:
    if path.is_symlink():
        raise NotARegularFile(
            f"{path}: is a symbolic link; gonio does not replace links — write to the file "
            "itself or choose another path"
        )
    if path.exists() and not path.is_file():
        kind = "a directory" if path.is_dir() else "not a regular file (a device, FIFO or socket)"
        raise NotARegularFile(f"{path}: is {kind}; choose a file path for the output")


def check_writable_dir(path: str | os.PathLike, hint: str) -> None:
    """Refuse, in one line ending in `hint`, a folder gonio could not write an output into
    (read-only medium, no permission, missing): said before minutes of work, not after."""
    folder = Path(path)
    if not folder.is_dir():
        raise UserError(f"{folder}: no such folder for the output; {hint}")
    if not os.access(folder, os.W_OK):
        # access() says EROFS for a read-only mount even to root, who is otherwise allowed.
        why = "read-only file system" if _read_only_mount(folder) else "no write permission"
        raise UserError(f"{folder}: cannot write the output there ({why}); {hint}")


def _read_only_mount(folder: Path) -> bool:
    try:
        return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def fsync_dir(path: str | os.PathLike) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove_stale_temps(path: Path) -> None:
    """Remove `.NAME.tmp-PID` files beside `path` whose writer PID no longer runs (a temp file of
    a live process, this one's included, is its writer's to finish or remove)."""
    prefix = f".{path.name}.tmp-"
    try:
        candidates = [p for p in path.parent.iterdir() if p.name.startswith(prefix)]
    except OSError:
        return
    for tmp in candidates:
        pid = tmp.name[len(prefix) :]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
            continue  # alive (or not ours to signal): its writer may still finish it
        except ProcessLookupError:
            pass
        except (PermissionError, OverflowError, ValueError):
            continue
        try:
            tmp.unlink()
        except OSError:
            continue
        logging.getLogger("gonio").warning(
            f"removed {tmp}: the temp file of a writer (pid {pid}) that was killed before it "
            "finished"
        )


def atomic_write_with(
    path: str | os.PathLike, write: Callable[[BinaryIO], None], *, overwrite: bool = False
) -> Path:
    """Call `write(fh)` on a temp file beside `path`, fsync, then move it into place: by
    `os.link` (FileExistsError if `path` exists), or with `overwrite=True` by `os.replace`."""
    path = Path(path)
    _refuse_special(path)
    _remove_stale_temps(path)
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
    except OSError as exc:
        if exc.filename is not None or exc.errno is None:
            raise
        # write(2) and fsync(2) name no file (a full disk says only "No space left on
        # device"): the user is told which file could not be written.
        raise OSError(exc.errno, exc.strerror, str(path)) from exc
    finally:
        if tmp.exists():
            tmp.unlink()
    fsync_dir(path.parent)
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, overwrite: bool = False) -> Path:
    """`data` into `path` atomically (see `atomic_write_with`)."""
    return atomic_write_with(path, lambda fh: fh.write(data), overwrite=overwrite)

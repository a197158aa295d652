"""Reading input files safely: regular files only, with a size cap, never blocking.

A path given to gonio — a config, a samples table, a frame in a run someone sent — may name a
FIFO (a read waits forever for a writer, and ignores SIGTERM while it waits in the kernel), a
device (`/dev/zero` never ends; opening a serial port resets the board on it), or a directory.
Every reader goes through here: the path is `stat`ed (which opens nothing), refused in one line
unless it is a regular file within the cap, then opened `O_NONBLOCK` (so even a FIFO swapped in
between cannot block the open) and checked again on the open descriptor.
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from typing import BinaryIO

from plumbing.errors import UserError

__all__ = [
    "NotAnInputFile",
    "open_input",
    "read_input_bytes",
    "read_input_text",
    "check_input",
    "check_nesting",
    "MAX_NESTING",
    "MiB",
    "GiB",
    "FRAME_MAX_BYTES",
    "DATA_MAX_BYTES",
]

MiB = 1 << 20
GiB = 1 << 30
# A frame: a 100-megapixel 16-bit RAW is 200 MB, a float32 RGBA EXR of it 1.6 GB.
FRAME_MAX_BYTES = 4 * GiB
# Measured data from elsewhere (RGL .bsdf, CSV tables): the largest RGL files are ~100 MB.
DATA_MAX_BYTES = 2 * GiB


#: The deepest nesting of brackets and braces a JSON or TOML input may have. gonio's own files
#: nest a few levels; Python's parsers recurse once per level and overflow the stack near 1000
#: (a RecursionError, not a one-line error), so a deeper file is refused before it is parsed.
MAX_NESTING = 100

_NOT_A_BRACKET = re.compile(r"[^\[\]{}]+")


class NotAnInputFile(UserError, OSError):
    """An input path that is not a regular file, or is larger than its cap."""


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _check(path: Path, st: os.stat_result, what: str, max_bytes: int | None) -> None:
    if not stat.S_ISREG(st.st_mode):
        raise NotAnInputFile(f"{path}: is {_kind(st.st_mode)}; {what} must be a regular file")
    if max_bytes is not None and st.st_size > max_bytes:
        raise NotAnInputFile(
            f"{path}: {st.st_size / MiB:.0f} MiB, larger than any {what} gonio reads "
            f"({max_bytes / MiB:.0f} MiB)"
        )


def open_input(path: str | os.PathLike, what: str, max_bytes: int | None = None) -> BinaryIO:
    """`path` opened for binary reading, or NotAnInputFile (FileNotFoundError if missing)."""
    path = Path(path)
    _check(path, path.stat(), what, max_bytes)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        _check(path, os.fstat(fd), what, max_bytes)  # the same file that was stat'ed
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_input_bytes(path: str | os.PathLike, what: str, max_bytes: int) -> bytes:
    """All of `path`, refusing a file that is not regular or grows past `max_bytes`."""
    with open_input(path, what, max_bytes) as fh:
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:  # it grew while we read it
        cap = f"{max_bytes / MiB:.0f} MiB"
        raise NotAnInputFile(f"{path}: larger than any {what} gonio reads ({cap})")
    return data


def read_input_text(path: str | os.PathLike, what: str, max_bytes: int) -> str:
    """`read_input_bytes` decoded as UTF-8, with a one-line error for any other encoding."""
    data = read_input_bytes(path, what, max_bytes)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise NotAnInputFile(
            f"{path}: not UTF-8 text (byte {exc.start}); {what} must be a UTF-8 text file"
        ) from None


def check_input(path: str | os.PathLike, what: str, max_bytes: int | None = None) -> Path:
    """Check `path` as `open_input` does, for a library that opens the file by name (pyarrow,
    rawpy, OpenEXR); returns it."""
    open_input(path, what, max_bytes).close()
    return Path(path)


def check_nesting(text: str, path: str | os.PathLike, what: str) -> None:
    """Refuse, in one line, a JSON or TOML `text` nested deeper than MAX_NESTING. Brackets in
    strings count too: the bound is far above any real file's depth either way."""
    depth = deepest = 0
    for ch in _NOT_A_BRACKET.sub("", text):
        depth = depth + 1 if ch in "[{" else max(depth - 1, 0)
        if depth > deepest:
            deepest = depth
            if deepest > MAX_NESTING:
                raise NotAnInputFile(
                    f"{path}: nested more than {MAX_NESTING} levels deep; not a {what} gonio "
                    "writes or reads — check that it is the right file"
                )

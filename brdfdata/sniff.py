"""Which BRDF file format a path holds, by its first bytes: the samples reader names the format
of a file that is not a samples table (and says how to import it); `gonio import` checks what
it is given. Below both :mod:`brdfdata.samples` and :mod:`brdfdata.formats`.
"""

from __future__ import annotations

import os

from plumbing.inputs import open_input

__all__ = ["sniff_format"]


def sniff_format(path) -> str | None:
    """ "rgl", "merl" or "csv" when the file looks like one (by its first bytes), else None."""
    try:
        with open_input(path, "data file") as fh:
            head = fh.read(4096)
        size = os.path.getsize(path)
    except OSError:
        return None
    if head.startswith(b"tensor_file\0"):
        return "rgl"
    if size == 12 + 3 * 90 * 90 * 180 * 8 and head[:12] == bytes.fromhex(
        "5a0000005a000000b4000000"
    ):
        return "merl"
    try:
        first = head.decode("utf-8").splitlines()[0]
    except (UnicodeDecodeError, IndexError):
        return None
    if any(d in first for d in ",;\t") and "theta" in first.lower():
        return "csv"
    return None

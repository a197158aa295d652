"""Readers and writers for the BRDF file formats the field uses, and the guards every source of
samples passes through (issue 16).

=================  =====================================================  ==========================
module             what it holds                                          reference
=================  =====================================================  ==========================
``common``         FormatError, σ assumptions, provenance metadata         DESIGN §4 (samples)
``guards``         unit and range checks, duplicate merging                DESIGN §3, §4
``tensor_file``    the RGL ``tensor_file`` container (read and write)      Dupuy & Jakob 2018
``rgl``            RGL adaptive-parameterization BRDF: evaluation,         Dupuy & Jakob 2018
                   measured directions, import to samples
``rgl_tabulate``   a fitted model tabulated as an RGL file (Mitsuba        Dupuy & Jakob 2018
                   ``measured`` loads it): the export fallback
``merl``           MERL ``.binary`` (read, lookup, write, import)          Matusik et al. 2003
``csv_table``      delimited text with named columns (read and write)      —
=================  =====================================================  ==========================

This package imports nothing of ours outside ``fitting`` (import-linter contract). The heavy
modules are not imported here: ``import fitting.formats.merl`` etc.
"""

from __future__ import annotations

__all__ = ["FORMATS", "sniff_format"]

#: Formats ``gonio import`` reads, and whether ``gonio export`` can write them from samples.
FORMATS = {"rgl": False, "merl": True, "csv": True}


def sniff_format(path) -> str | None:
    """ "rgl", "merl" or "csv" when the file looks like one (by its first bytes), else None."""
    import os

    from plumbing.inputs import open_input

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

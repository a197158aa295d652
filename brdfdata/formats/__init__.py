"""Readers and writers for the BRDF file formats the field uses (issue 16); every table they make
passes the samples contract's guards (:mod:`brdfdata.samples.guards`).

=================  =====================================================  ==========================
module             what it holds                                          reference
=================  =====================================================  ==========================
``common``         FormatError, σ assumptions, provenance metadata         docs/design.md §4
``convert``        one entry point per format for ``gonio import/export``  docs/formats.md
``tensor_file``    the RGL ``tensor_file`` container (read and write)      Dupuy & Jakob 2018
``rgl``            RGL adaptive-parameterization BRDF: evaluation,         Dupuy & Jakob 2018
                   measured directions, import to samples
``rgl_tabulate``   a fitted model tabulated as an RGL file (Mitsuba        Dupuy & Jakob 2018
                   ``measured`` loads it): the export fallback
``merl``           MERL ``.binary`` (read, lookup, write, import)          Matusik et al. 2003
``csv_table``      delimited text with named columns (read and write)      —
=================  =====================================================  ==========================

This package imports nothing of ours above ``brdfdata`` (import-linter contract). The heavy
modules are not imported here: ``import brdfdata.formats.merl`` etc.
"""

from __future__ import annotations

from brdfdata.sniff import sniff_format

__all__ = ["FORMATS", "sniff_format"]

#: Formats ``gonio import`` reads, and whether ``gonio export`` can write them from samples.
FORMATS = {"rgl": False, "merl": True, "csv": True}

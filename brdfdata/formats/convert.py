"""``gonio import`` / ``gonio export``: one entry point per direction over the format modules, so
the command line only parses options. Every imported table passes the guards
(:mod:`brdfdata.samples.guards`) before it is returned.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from brdfdata.formats.common import FormatError, parse_grid, parse_sigma
from brdfdata.samples import SampleTable
from brdfdata.samples.guards import check_samples
from brdfdata.samples.table import EXCLUDING
from plumbing.inputs import DATA_MAX_BYTES, check_input

__all__ = [
    "IMPORT_FORMATS",
    "EXPORT_FORMATS",
    "ImportOptions",
    "import_samples",
    "check_export",
    "export_file",
]

IMPORT_FORMATS = ("rgl", "merl", "csv")
EXPORT_FORMATS = ("merl", "csv")


@dataclass(frozen=True)
class ImportOptions:
    """Options of ``gonio import`` as given on the command line (text, parsed here).

    ``grid``: None = the file's own directions (rgl: measured nodes, merl: bin centres), else
    a :func:`~brdfdata.formats.common.parse_grid` spec in degrees; ``sigma``: None = the
    format's default (csv: a ``sigma`` column; rgl/merl: rel=0.02); csv only: ``angles``,
    ``columns`` (contract name → file column), ``values`` (channel → value column),
    ``channel_column``, ``default_channel``, ``delimiter``; rgl only: ``wavelengths_nm``;
    ``merge_duplicates``: merge repeated rows instead of refusing them."""

    grid: str | None = None
    sigma: str | None = None
    angles: str = "rad"
    columns: dict[str, str] = field(default_factory=dict)
    values: dict[str, str] = field(default_factory=dict)
    channel_column: str = "channel"
    default_channel: str = "Y"
    delimiter: str | None = None
    wavelengths_nm: tuple[float, ...] | None = None
    merge_duplicates: bool = False


def _not_for(fmt: str, options: ImportOptions) -> None:
    """Refuse options that mean nothing for ``fmt`` (a typo should not pass silently)."""
    csv_only = {
        "--angles": options.angles != "rad",
        "--column": bool(options.columns),
        "--value": bool(options.values),
        "--delimiter": options.delimiter is not None,
    }
    used = [k for k, v in csv_only.items() if v and fmt != "csv"]
    if options.grid is not None and fmt == "csv":
        used.append("--grid")
    if options.wavelengths_nm is not None and fmt != "rgl":
        used.append("--wavelengths")
    if used:
        raise FormatError(f"gonio import {fmt}: {', '.join(used)} does not apply to {fmt} files")


def import_samples(fmt: str, path: str | os.PathLike, options: ImportOptions) -> SampleTable:
    """Read ``path`` as ``fmt`` into the samples contract, guarded (module docstring)."""
    path = Path(path)
    if fmt not in IMPORT_FORMATS:
        raise FormatError(f"unknown import format {fmt!r}; use one of {', '.join(IMPORT_FORMATS)}")
    if not path.exists():
        raise FormatError(f"{path}: no such file")
    check_input(path, f"{fmt} file", DATA_MAX_BYTES)  # FIFO, device, directory: one line
    _not_for(fmt, options)
    grid = None if options.grid in (None, "measured") else parse_grid(options.grid)
    if fmt == "rgl":
        from brdfdata.formats.rgl import RglImportOptions, import_rgl

        sigma = parse_sigma(options.sigma or "rel=0.02", allow_column=False)
        table = import_rgl(path, RglImportOptions(grid, sigma, options.wavelengths_nm))
    elif fmt == "merl":
        from brdfdata.formats.merl import MerlImportOptions, import_merl

        sigma = parse_sigma(options.sigma or "rel=0.02", allow_column=False)
        table = import_merl(path, MerlImportOptions(grid, sigma))
    else:
        from brdfdata.formats.csv_table import CsvOptions, read_csv_table

        csv_opts = CsvOptions(
            angles=options.angles,
            sigma=parse_sigma(options.sigma or "sigma"),
            columns=dict(options.columns),
            values=dict(options.values),
            channel_column=options.channel_column,
            default_channel=options.default_channel,
            delimiter=options.delimiter,
        )
        table = read_csv_table(path, csv_opts)
    if not np.any((np.asarray(table.flags, np.int64) & EXCLUDING) == 0):
        # an RGL file whose VNDF is all zero became an empty table, and exit 0
        raise FormatError(
            f"{path}: no measured value in it ({len(table)} rows, every one excluded); not a "
            f"{fmt} file of a measurement — check that it is the right file"
        )
    return check_samples(table, str(path), merge_duplicates_rows=options.merge_duplicates)


def check_export(fmt: str, angles: str) -> None:
    """Refuse an export format or angle unit ``gonio export`` does not write (one line)."""
    if fmt not in EXPORT_FORMATS:
        hint = " (an RGL file needs the instrument's parameterization)" if fmt == "rgl" else ""
        raise FormatError(
            f"unknown export format {fmt!r}{hint}; use one of {', '.join(EXPORT_FORMATS)}"
        )
    if angles not in ("rad", "deg"):
        raise FormatError(f"--angles {angles!r}: use deg or rad")


def export_file(fmt: str, source: str | os.PathLike, out: str | os.PathLike, angles: str = "rad"):
    """Write ``out`` in ``fmt`` from the samples table ``source`` (csv; merl: mean f per bin).
    Returns (path, one line describing what was written). A fitted model is exported by
    :func:`fitting.export.export_fit`."""
    source, out = Path(source), Path(out)
    check_export(fmt, angles)
    from brdfdata.samples import read_samples

    if fmt == "csv":
        from brdfdata.formats.csv_table import write_csv_table

        table = read_samples(source)
        return write_csv_table(out, table, angles), f"{len(table)} samples, angles in {angles}"
    from brdfdata.formats import merl

    if angles != "rad":
        raise FormatError("--angles applies to csv only (MERL bins are angles by definition)")
    table, n_bins = merl.table_from_samples(read_samples(source))
    merl.write_merl(out, table)
    return out, f"{n_bins} bins with data (mean f per bin), the rest marked invalid"

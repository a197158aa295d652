"""Samples tables on disk (docs/design.md §4): `samples.parquet`, the contract between calibration
and fitting, written atomically (whole or streamed pose by pose) and read with every check of
:mod:`brdfdata.samples.guards`. A table with only the required columns is valid input, so samples
measured by other instruments can be fitted too.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from brdfdata.samples.guards import check_samples
from brdfdata.samples.table import (
    EXCLUDING,
    FORMAT_NAMES,
    OPTIONAL_COLUMNS,
    REQUIRED_COLUMNS,
    SCHEMA_VERSION,
    SamplesError,
    SampleTable,
)
from brdfdata.sniff import sniff_format
from plumbing.atomic import atomic_write_with
from plumbing.hashing import sha256_file
from plumbing.inputs import DATA_MAX_BYTES, check_input, read_input_bytes

__all__ = [
    "read_samples",
    "write_samples",
    "write_samples_streamed",
    "SampleStream",
    "open_samples_file",
    "check_columns",
    "table_from_arrow",
]


def _arrow_columns(cols: dict[str, np.ndarray]) -> dict[str, pa.Array]:
    """The Arrow columns of a samples table (required, then optional ones in `cols`' order)."""
    out = {
        "theta_i": pa.array(cols["theta_i"], pa.float64()),
        "phi_i": pa.array(cols["phi_i"], pa.float64()),
        "theta_o": pa.array(cols["theta_o"], pa.float64()),
        "phi_o": pa.array(cols["phi_o"], pa.float64()),
        "channel": pa.array(np.asarray(cols["channel"]).astype(str), pa.string()),
        "f": pa.array(cols["f"], pa.float64()),
        "sigma": pa.array(cols["sigma"], pa.float64()),
        "flags": pa.array(np.asarray(cols["flags"], dtype=np.int32), pa.int32()),
    }
    for name, values in cols.items():
        if name in out:
            continue
        dtype = OPTIONAL_COLUMNS.get(name)
        out[name] = pa.array(values, dtype) if dtype is not None else pa.array(values)
    return out


def _file_metadata(metadata: dict[str, str]) -> dict[str, str]:
    """The file's key-value metadata: schema version and units, then the table's own."""
    meta = {
        "gonio.schema_version": str(SCHEMA_VERSION),
        "gonio.units": json.dumps(
            {
                "theta_i": "rad",
                "phi_i": "rad",
                "theta_o": "rad",
                "phi_o": "rad",
                "f": "1/sr",
                "sigma": "1/sr",
            }
        ),
    }
    meta.update(metadata)
    return meta


def write_samples(path: str | os.PathLike, table: SampleTable) -> Path:
    """Write atomically (temp file, fsync, rename) with units and schema version in metadata."""
    path = Path(path)
    cols = {
        "theta_i": table.theta_i,
        "phi_i": table.phi_i,
        "theta_o": table.theta_o,
        "phi_o": table.phi_o,
        "channel": table.channel,
        "f": table.f,
        "sigma": table.sigma,
        "flags": table.flags,
        **table.extra,
    }
    meta = _file_metadata(table.metadata)
    arrow = pa.table(_arrow_columns(cols)).replace_schema_metadata(
        {k.encode(): v.encode() for k, v in meta.items()}
    )
    atomic_write_with(path, lambda fh: pq.write_table(arrow, fh), overwrite=True)
    return path


class SampleStream:
    """A samples table written piece by piece (a calibration writes each pose's samples as it
    goes, so its memory does not grow with the number of poses). Pieces are dicts of the
    table's columns (``channel``, ``f``, … and optional columns), buffered into row groups of
    about `ROW_GROUP_ROWS` rows; the metadata is given at the end, when it is known. Made by
    `write_samples_streamed`, which keeps the write atomic."""

    ROW_GROUP_ROWS = 1 << 20  # ≈ 76 MB of buffered columns: small next to a pose's images

    def __init__(self, fh) -> None:
        self._fh = fh
        self._writer: pq.ParquetWriter | None = None
        self._buffer: list[dict[str, pa.Array]] = []
        self._buffered = 0
        self.rows = 0

    def append(self, cols: dict[str, np.ndarray]) -> None:
        n = int(np.asarray(cols["f"]).shape[0])
        if n == 0:
            return
        self._buffer.append(_arrow_columns(cols))
        self._buffered += n
        self.rows += n
        if self._buffered >= self.ROW_GROUP_ROWS:
            self._flush()

    def _flush(self) -> None:
        if not self._buffer:
            return
        table = pa.concat_tables(pa.table(piece) for piece in self._buffer)
        self._buffer, self._buffered = [], 0
        if self._writer is None:
            # No stored Arrow schema: the file's key-value metadata, added at the end, is then
            # what a reader sees as the schema's metadata (every column is a plain Parquet type).
            self._writer = pq.ParquetWriter(self._fh, table.schema, store_schema=False)
        self._writer.write_table(table)

    def finish(self, metadata: dict[str, str]) -> None:
        self._flush()
        if self._writer is None:
            raise ValueError("no samples were written")
        self._writer.add_key_value_metadata(_file_metadata(metadata))
        self._writer.close()

    def abort(self) -> None:
        """Close the writer after a failure, while its (temp) file is still open: the file is
        thrown away, but a writer left to the garbage collector would write to a closed file."""
        if self._writer is not None:
            try:
                self._writer.close()
            except Exception:  # the original error is the one to report
                pass
            self._writer = None


def write_samples_streamed(
    path: str | os.PathLike, produce: Callable[[SampleStream], dict[str, str]]
) -> int:
    """Write a samples table atomically from pieces: ``produce(stream)`` appends them and
    returns the table's metadata; the file appears (temp file, fsync, rename, replacing an
    earlier one) only if it returns; an exception leaves no file. Returns the rows written."""
    rows = 0

    def write(fh) -> None:
        nonlocal rows
        stream = SampleStream(fh)
        try:
            stream.finish(produce(stream))
        except BaseException:
            stream.abort()
            raise
        rows = stream.rows

    atomic_write_with(Path(path), write, overwrite=True)
    return rows


def _flags_column(arrow, path) -> np.ndarray:
    """The flags as int32 bit sets, refusing what a cast would silently turn into 0 (= good):
    nulls, NaN, fractions, negatives and values beyond 31 bits (2³² became 0 before)."""
    column = arrow.column("flags")
    if column.null_count:
        first = int(np.flatnonzero(np.asarray(column.is_null()))[0])
        raise SamplesError(f"{path}: column 'flags': row {first} is null; flags are bit sets")
    try:
        values = np.asarray(column.to_numpy(zero_copy_only=False), dtype=np.float64)
    except (TypeError, ValueError, pa.ArrowInvalid):
        raise SamplesError(f"{path}: column 'flags' is not numeric") from None
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(values) | (values != np.round(values)) | (values < 0)
        bad |= values >= 2**31
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise SamplesError(
            f"{path}: column 'flags': row {first} holds {values[first]:g}; flags are bit sets, "
            "whole numbers from 0 (good) to 2^31 - 1"
        )
    return values.astype(np.int32)


def _channel_column(arrow, path) -> np.ndarray:
    """Channel names as str, refusing a null or empty name (before, a null became "None" and
    was fitted as a channel of that name) and a column that is not text."""
    column = arrow.column("channel")
    if pa.types.is_dictionary(column.type):
        column = column.cast(pa.string())
    if not (pa.types.is_string(column.type) or pa.types.is_large_string(column.type)):
        raise SamplesError(f"{path}: column 'channel' is {column.type}, not text (R, G, B, ...)")
    missing = np.asarray(pc.fill_null(pc.equal(pc.utf8_length(column), 0), True))
    if missing.any():
        raise SamplesError(
            f"{path}: column 'channel': row {int(np.flatnonzero(missing)[0])} has no channel "
            "name (null or empty); every row needs one (R, G, B, or a band name)"
        )
    return np.asarray(column.to_numpy(zero_copy_only=False), dtype=object).astype(str)


def open_samples_file(path: Path) -> pq.ParquetFile:
    """The Parquet file of a samples table, opened (its footer read) but no rows; a missing
    file, a directory, a FIFO or device (plumbing.inputs) or another format is one line."""
    if not path.exists():
        raise SamplesError(f"{path}: no such file")
    if path.is_dir():
        raise SamplesError(f"{path}: is a directory, expected a samples .parquet file")
    check_input(path, "samples table")  # a FIFO or device would block or never end
    try:
        return pq.ParquetFile(path)
    except Exception as exc:  # pyarrow raises several types for a non-Parquet file
        _not_parquet(path, exc)


def _not_parquet(path: Path, exc: Exception) -> NoReturn:
    fmt = sniff_format(path)
    if fmt is not None:  # a format gonio can import: say how
        raise SamplesError(
            f"{path}: looks like {FORMAT_NAMES[fmt]} file, not a Parquet samples table; "
            f"convert it with `gonio import {fmt} {path} --out SAMPLES.parquet` (samples of a "
            "run: `gonio calibrate RUN`)"
        ) from None
    raise SamplesError(
        f"{path}: not a Parquet samples table ({type(exc).__name__}: damaged or another "
        "format); re-create it with `gonio calibrate RUN`, convert it with `gonio import`, "
        "or write it with pyarrow"
    ) from None


def read_samples(path: str | os.PathLike, *, merge_duplicates: bool = False) -> SampleTable:
    """Read and validate a samples table. Raises SamplesError with a one-line reason.

    Every table passes the unit and range guards of :mod:`brdfdata.samples.guards` (degrees,
    below-horizon rows, σ ≤ 0, unflagged f < 0, duplicated rows — the latter merged instead
    when ``merge_duplicates``)."""
    path = Path(path)
    open_samples_file(path).close()  # missing, a directory, a FIFO, another format: one line
    # The bytes hashed are the bytes parsed (a fit records this hash, and a report compares
    # it): hashing the file again after reading it let a file changed in between pass.
    data = read_input_bytes(path, "samples table", DATA_MAX_BYTES)
    sha = hashlib.sha256(data).hexdigest()
    try:
        arrow = pq.ParquetFile(pa.BufferReader(data)).read()
    except Exception as exc:  # a damaged column chunk behind a readable footer
        _not_parquet(path, exc)
    del data
    table = table_from_arrow(arrow, path, merge_duplicates=merge_duplicates)
    del arrow
    # Arrow's allocator keeps the freed read buffers for reuse (≈ 60 B per row): hand them
    # back, since a fit's later peaks come from numpy, not Arrow.
    pa.default_memory_pool().release_unused()
    if sha256_file(path) != sha:
        raise SamplesError(
            f"{path}: changed while gonio read it (another program is writing it); run the "
            "command again when that has finished"
        )
    table.source_sha256 = sha
    return table


def check_columns(names: list[str], path: Path) -> None:
    """Refuse a table without every required column (one line)."""
    twice = sorted({c for c in names if names.count(c) > 1})
    if twice:
        raise SamplesError(
            f"{path}: column {twice[0]!r} appears more than once; a samples table names each "
            "column once — re-create it with `gonio calibrate RUN` or `gonio import`"
        )
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        raise SamplesError(
            f"{path}: not a samples table, missing column(s) {', '.join(missing)} "
            f"(required: {', '.join(REQUIRED_COLUMNS)})"
        )


def _checked_metadata(arrow: pa.Table, path: Path) -> dict[str, str]:
    """The table's own metadata as text, its schema version checked (one line otherwise)."""
    raw_meta = arrow.schema.metadata or {}
    try:
        meta = {k.decode(): v.decode() for k, v in raw_meta.items() if not k.startswith(b"ARROW")}
    except UnicodeDecodeError:
        raise SamplesError(
            f"{path}: its metadata is not UTF-8 text, so not a samples table gonio or pyarrow "
            "wrote — re-create it with `gonio calibrate RUN` or `gonio import`"
        ) from None
    version = meta.get("gonio.schema_version")
    if version is not None and not re.fullmatch(r"[0-9]{1,9}", version):
        # "²" passes str.isdigit and fails int(); "2.0" is no version this gonio writes
        raise SamplesError(
            f"{path}: samples schema version {version!r} is not a whole number as gonio writes "
            f"it (this one reads up to {SCHEMA_VERSION}); a newer gonio or another tool wrote "
            "it — upgrade gonio, or re-create the table with `gonio calibrate` or `gonio import`"
        )
    if version is not None and int(version) > SCHEMA_VERSION:
        raise SamplesError(
            f"{path}: samples schema version {version} was written by a newer gonio (this one "
            f"reads up to {SCHEMA_VERSION}); upgrade gonio"
        )
    return meta


def table_from_arrow(
    arrow: pa.Table, path: Path, *, merge_duplicates: bool = False, guards: bool = True
) -> SampleTable:
    """The validated SampleTable of an Arrow table read from ``path`` (whole, or one batch of a
    streamed read, fitting.binning): columns, schema version, finiteness, flags, channel names
    and — unless ``guards`` is False, for a rereading of rows already checked — the guards of
    brdfdata.samples.guards. Raises SamplesError."""
    check_columns(arrow.column_names, path)
    meta = _checked_metadata(arrow, path)
    if arrow.num_rows == 0:
        raise SamplesError(f"{path}: the samples table is empty")

    def col(name: str, dtype: type) -> np.ndarray:
        column = arrow.column(name)
        fix = "write it as numbers (pyarrow, or `gonio import csv` for a text table)"
        # Text that happens to parse ("0.4") was converted silently before: a table whose
        # numbers are strings was written by something that did not mean them as numbers.
        if pa.types.is_string(column.type) or pa.types.is_large_string(column.type):
            raise SamplesError(f"{path}: column {name!r} is not {dtype.__name__} but text; {fix}")
        if pa.types.is_boolean(column.type):  # True/False would be fitted as 1/0 sr⁻¹
            raise SamplesError(f"{path}: column {name!r} is boolean, not {dtype.__name__}; {fix}")
        try:
            return np.asarray(column.to_numpy(zero_copy_only=False), dtype=dtype)
        except (TypeError, ValueError, pa.ArrowInvalid):
            raise SamplesError(f"{path}: column {name!r} is not {dtype.__name__}; {fix}") from None

    f = col("f", np.float64)
    sigma = col("sigma", np.float64)
    angles = {c: col(c, np.float64) for c in ("theta_i", "phi_i", "theta_o", "phi_o")}
    finite = np.isfinite(f) & np.isfinite(sigma)
    for a in angles.values():
        finite &= np.isfinite(a)
    if not finite.any():
        raise SamplesError(f"{path}: no row has finite angles, f and sigma (all NaN or inf)")
    flags = (
        _flags_column(arrow, path)
        if "flags" in arrow.column_names
        else np.zeros(arrow.num_rows, np.int32)
    )
    # A NaN or inf in a row marked good is a damaged or mis-exported table, not a measurement:
    # refuse it rather than silently fit a subset. Rows flagged bad may hold anything.
    bad = (flags == 0) & ~finite
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        names = [
            name
            for name, v in (("f", f), ("sigma", sigma), *angles.items())
            if not np.isfinite(v[first])
        ]
        raise SamplesError(
            f"{path}: {int(bad.sum())} row(s) have NaN or inf in {', '.join(names)} "
            f"(first: row {first}) but flags = 0; drop those rows or set their flags column "
            "(e.g. 8 = masked)"
        )
    extra = {
        name: col(name, np.int64)
        for name in ("capture_id", "pixel_x", "pixel_y", "texel")
        if name in arrow.column_names
    }
    if "bend_level" in arrow.column_names:
        level = col("bend_level", np.float64)
        # A fit multiplies the model of every row it uses — measured, censored or kept despite
        # a flag (FLAG_ROLES: all but the excluded) — by 1 + b · level: one NaN there would
        # make every walker's likelihood NaN, a failed fit with no word of why.
        bad_level = ((flags & EXCLUDING) == 0) & ~(np.isfinite(level) & (level >= 0))
        if bad_level.any():
            first = int(np.flatnonzero(bad_level)[0])
            raise SamplesError(
                f"{path}: column 'bend_level' holds {level[first]:g} in row {first} "
                f"({int(bad_level.sum())} row(s) a fit uses without a finite level ≥ 0); it is the "
                "fraction of the camera's clip a sample was read at (docs/formats.md): drop the "
                "column or those rows"
            )
        extra["bend_level"] = level
    channel = _channel_column(arrow, path)
    table = SampleTable(
        channel=channel, f=f, sigma=sigma, flags=flags, extra=extra, metadata=meta, **angles
    )
    if not guards:
        return table
    return check_samples(table, str(path), merge_duplicates_rows=merge_duplicates)

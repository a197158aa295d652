"""Delimited text tables (CSV, TSV, semicolon or whitespace separated) with named columns: the
way other instruments and spreadsheets hand over BRDF samples.

Reading (:func:`read_csv_table`) maps the file's column names onto the samples contract
(docs/design.md §4; ``docs/formats.md``):

* angle columns ``theta_i``, ``phi_i``, ``theta_o``, ``phi_o`` (rename with
  ``columns={"theta_i": "THETA_IN", …}``), in radians or degrees (``angles="deg"``);
* values either long — one ``f`` column and a ``channel`` column (R, G, B, Y or any label) —
  or wide — one value column per channel (``values={"R": "f_red", …}``; columns named
  ``f_R``, ``f_G``, ``f_B`` or ``f_Y`` are found without being named), or a single ``f``
  column with no channel column (``default_channel``, "Y");
* σ from a column (``sigma`` or ``sigma_<channel>`` in the wide form), ``rel=FRACTION``,
  ``abs=VALUE`` (sr⁻¹), or ``repeats``: rows repeating the same (θ_i, φ_i, θ_o, φ_o, channel)
  become one sample with f = their mean and σ = their standard deviation/√n (n ≥ 2 each);
* an optional ``flags`` column (int bitmask, 0 = good) is kept.

Writing (:func:`write_csv_table`) gives the long form with every column of the contract, floats
in their shortest round-trip form (``repr``), so write → read returns the same float64 values.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from brdfdata.formats.common import FormatError, SigmaRule, provenance
from brdfdata.samples import SampleTable
from plumbing.atomic import atomic_write_bytes
from plumbing.inputs import DATA_MAX_BYTES, read_input_bytes

__all__ = ["CsvOptions", "read_csv_table", "write_csv_table", "csv_text"]

ANGLES = ("theta_i", "phi_i", "theta_o", "phi_o")


@dataclass(frozen=True)
class CsvOptions:
    """How to read a delimited table (module docstring). ``delimiter`` None = sniffed."""

    angles: str = "rad"
    sigma: SigmaRule = field(default_factory=lambda: SigmaRule("column", "sigma"))
    columns: dict[str, str] = field(default_factory=dict)
    values: dict[str, str] = field(default_factory=dict)
    channel_column: str = "channel"
    default_channel: str = "Y"
    delimiter: str | None = None


def _read_rows(path: Path, delimiter: str | None) -> tuple[list[str], list[list[str]]]:
    try:
        text = read_input_bytes(path, "table", DATA_MAX_BYTES).decode("utf-8-sig")
    except UnicodeDecodeError:
        raise FormatError(f"{path}: not a text table (not UTF-8); export it as CSV") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 2:
        raise FormatError(f"{path}: a table needs a header line and at least one row")
    if delimiter is None:
        try:
            delimiter = csv.Sniffer().sniff(lines[0], delimiters=",;\t ").delimiter
        except csv.Error:
            delimiter = ","
    if delimiter == " ":
        rows = [ln.split() for ln in lines]
    else:
        rows = list(csv.reader(lines, delimiter=delimiter))
    header = [h.strip() for h in rows[0]]
    body = [[c.strip() for c in r] for r in rows[1:]]
    bad = next((i for i, r in enumerate(body) if len(r) != len(header)), None)
    if bad is not None:
        raise FormatError(
            f"{path}: line {bad + 2} has {len(body[bad])} field(s), the header has "
            f"{len(header)}; fix that line or pass --delimiter"
        )
    return header, body


def _column(path: Path, header, body, name: str, what: str) -> np.ndarray:
    if name not in header:
        raise FormatError(
            f"{path}: no column {name!r} for {what} (columns: {', '.join(header)}); "
            f"name it with --column {what}=YOUR_COLUMN"
        )
    j = header.index(name)
    try:
        return np.array([float(r[j]) for r in body], dtype=np.float64)
    except ValueError:
        first = next(i for i, r in enumerate(body) if not _is_float(r[j]))
        raise FormatError(
            f"{path}: column {name!r} line {first + 2}: {body[first][j]!r} is not a number"
        ) from None


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _value_columns(header, options: CsvOptions) -> dict[str, str] | None:
    """Channel → value column for the wide form, or None for the long form."""
    if options.values:
        return dict(options.values)
    wide = {h[2:]: h for h in header if h.startswith("f_") and len(h) > 2}
    return wide or None


def read_csv_table(path: str | os.PathLike, options: CsvOptions | None = None) -> SampleTable:
    """A delimited text file as a samples table (angles converted to radians). FormatError,
    one line naming the file, column and line, for anything that does not fit."""
    options = options or CsvOptions()
    path = Path(path)
    if options.angles not in ("rad", "deg"):
        raise FormatError(f"--angles {options.angles!r}: use deg or rad")
    header, body = _read_rows(path, options.delimiter)
    names = {a: options.columns.get(a, a) for a in ANGLES}
    angles = {a: _column(path, header, body, names[a], a) for a in ANGLES}
    if options.angles == "deg":
        angles = {a: np.radians(v) for a, v in angles.items()}
    wide = _value_columns(header, options)
    n_rows = len(body)
    parts = []  # (channel labels, f, sigma or None) per block of rows
    if wide:
        for chan, col in wide.items():
            f = _column(path, header, body, col, f"the {chan} values")
            sig = None
            if options.sigma.kind == "column":
                sig_col = options.columns.get(f"sigma_{chan}", f"sigma_{chan}")
                if sig_col not in header and options.sigma.value in header:
                    sig_col = str(options.sigma.value)
                sig = _column(path, header, body, sig_col, f"sigma_{chan}")
            parts.append((np.full(n_rows, chan), f, sig))
    else:
        f = _column(path, header, body, options.columns.get("f", "f"), "f")
        chan_col = options.columns.get("channel", options.channel_column)
        if chan_col in header:
            j = header.index(chan_col)
            labels = np.array([r[j] for r in body])
        else:
            labels = np.full(n_rows, options.default_channel)
        sig = None
        if options.sigma.kind == "column":
            sig = _column(path, header, body, str(options.sigma.value), "sigma")
        parts.append((labels, f, sig))
    flags = None
    if "flags" in header:
        flags = _column(path, header, body, "flags", "flags").astype(np.int64)
    k = len(parts)
    cols = {a: np.tile(v, k) for a, v in angles.items()}
    channel = np.concatenate([p[0] for p in parts]).astype(str)
    values = np.concatenate([p[1] for p in parts])
    flag_col = (
        np.tile(flags, k).astype(np.int32) if flags is not None else np.zeros(values.size, np.int32)
    )
    if options.sigma.kind == "column":
        sigma = np.concatenate([p[2] for p in parts])
    elif options.sigma.kind == "repeats":
        cols, channel, values, sigma, flag_col = _from_repeats(
            path, cols, channel, values, flag_col
        )
    else:
        sigma = options.sigma.apply(values, channel)
    conversion = {
        "reader": "brdfdata.formats.csv_table",
        "angles": options.angles,
        "layout": "wide" if wide else "long",
        "columns": {**names, **({"values": wide} if wide else {})},
        "sigma": options.sigma.describe(),
        "rows_read": n_rows,
    }
    return SampleTable(
        **cols,
        channel=channel,
        f=values,
        sigma=sigma,
        flags=flag_col,
        metadata=provenance(path, "csv", conversion),
    )


def _from_repeats(path: Path, cols, channel, values, flags):
    """Group rows by (angles, channel): f = mean, σ = s/√n (sample standard deviation s)."""
    keys = np.stack([cols[a] for a in ANGLES], axis=1)
    _, chan_code = np.unique(channel, return_inverse=True)
    full = np.concatenate([keys, chan_code[:, None].astype(np.float64)], axis=1)
    uniq, inverse, counts = np.unique(full, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    if np.any(counts < 2):
        single = int(np.sum(counts < 2))
        raise FormatError(
            f"{path}: --sigma repeats needs ≥ 2 rows per (theta_i, phi_i, theta_o, phi_o, "
            f"channel); {single} of {len(counts)} direction(s) have only one; give a sigma "
            "column or rel=…"
        )
    n = counts.astype(np.float64)
    mean = np.bincount(inverse, weights=values) / n
    ss = np.bincount(inverse, weights=(values - mean[inverse]) ** 2)
    sigma = np.sqrt(ss / (n - 1)) / np.sqrt(n)
    first = np.zeros(len(uniq), np.int64)
    first[inverse[::-1]] = np.arange(len(inverse))[::-1]
    out_flags = np.zeros(len(uniq), np.int64)
    np.bitwise_or.at(out_flags, inverse, flags.astype(np.int64))
    new_cols = {a: uniq[:, i] for i, a in enumerate(ANGLES)}
    return new_cols, channel[first], mean, sigma, out_flags.astype(np.int32)


def csv_text(table: SampleTable, angles: str = "rad") -> str:
    """The long-form CSV of a samples table (header + one row per sample)."""
    if angles not in ("rad", "deg"):
        raise ValueError(f"angles must be 'rad' or 'deg', not {angles!r}")
    conv = np.degrees if angles == "deg" else (lambda v: v)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    extra = [k for k in ("capture_id", "pixel_x", "pixel_y") if k in table.extra]
    w.writerow([*ANGLES, "channel", "f", "sigma", "flags", *extra])
    cols = [conv(getattr(table, a)) for a in ANGLES]
    for i in range(len(table)):
        w.writerow(
            [repr(float(c[i])) for c in cols]
            + [table.channel[i], repr(float(table.f[i])), repr(float(table.sigma[i]))]
            + [int(table.flags[i])]
            + [int(table.extra[k][i]) for k in extra]
        )
    return buf.getvalue()


def write_csv_table(path: str | os.PathLike, table: SampleTable, angles: str = "rad") -> Path:
    """Write the long-form CSV atomically; with ``angles="rad"`` read → same float64 values."""
    return atomic_write_bytes(path, csv_text(table, angles).encode("utf-8"), overwrite=True)

"""What the studies share: the simulated rig they run on, CSV rows, a run record beside the
CSV (so a page can be rebuilt without rerunning the sweep), the machine's state, and
matplotlib without a screen."""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import Any

from plumbing.atomic import atomic_write_bytes
from plumbing.errors import UserError
from plumbing.inputs import GiB, check_input

__all__ = [
    "sim_rig",
    "write_rows",
    "read_typed_rows",
    "read_rows",
    "write_record",
    "read_record",
    "machine",
    "load_average",
    "pyplot",
    "plain_log_ticks",
    "save_png",
]


def sim_rig():  # acquisition.config.RigConfig
    """The simulated two-arm rig every study runs on (configs/rigs/sim.toml)."""
    from acquisition.config import load_rig
    from gonio.pipeline import config_dir

    return load_rig(config_dir() / "rigs" / "sim.toml")


def write_rows(
    path: Path,
    rows: list[dict[str, Any]],
    columns: Sequence[str],
    fmt: Callable[[Any], Any] = lambda v: v,
) -> None:
    """Rows as CSV with exactly `columns` (atomic; a regenerated CSV replaces the old one)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns))
    w.writeheader()
    for r in rows:
        w.writerow({k: fmt(r[k]) for k in columns})
    atomic_write_bytes(path, buf.getvalue().encode(), overwrite=True)


def read_rows(
    path: Path, convert: Callable[[str, str], Any], required: Collection[str] = ()
) -> list[dict[str, Any]]:
    """Rows of a study CSV, each value through `convert(column, text)`; a missing `required`
    column, a short or long row, a value `convert` rejects or an infinite number is one line
    naming the file, the line and the column."""
    check_input(path, "study CSV", GiB)
    rows = []
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            missing = [c for c in required if c not in (reader.fieldnames or ())]
            if missing:
                raise UserError(
                    f"{path}: not this study's CSV, missing column(s) {', '.join(missing)}; "
                    "regenerate it with the study command"
                )
            for r in reader:
                if None in r or None in r.values():  # more, or fewer, fields than the header
                    raise UserError(
                        f"{path}: line {reader.line_num}: {len(reader.fieldnames or ())} "
                        "columns expected; regenerate it with the study command"
                    )
                row = {}
                for k, v in r.items():
                    try:
                        row[k] = convert(k, v)
                    except ValueError:
                        raise UserError(
                            f"{path}: line {reader.line_num}, column {k!r}: {v!r} is not a "
                            "valid value; regenerate it with the study command"
                        ) from None
                    if isinstance(row[k], float) and math.isinf(row[k]):
                        raise UserError(
                            f"{path}: line {reader.line_num}, column {k!r}: {v!r} is not "
                            "finite; regenerate it with the study command"
                        )
                rows.append(row)
    except (UnicodeDecodeError, csv.Error) as exc:
        raise UserError(f"{path}: not a study CSV ({exc}); regenerate it") from None
    return rows


def read_typed_rows(
    path: Path,
    text: Collection[str],
    ints: Collection[str] = (),
    bools: Collection[str] = (),
    required: Collection[str] = (),
) -> list[dict[str, Any]]:
    """Rows of a study CSV: `text` columns as str, `ints` as int, `bools` as bool ("True"),
    every other column as float."""

    def convert(k: str, v: str) -> Any:
        if k in text:
            return v
        if k in bools:
            return v in ("True", "true", "1", "yes")
        return int(v) if k in ints else float(v)

    return read_rows(path, convert, required)


def write_record(path: Path, record: dict[str, Any]) -> None:
    """The run record beside a study's CSV (its configuration, machine, wall time): what the
    page states besides the rows."""
    text = json.dumps(record, indent=2, sort_keys=True, default=str) + "\n"
    atomic_write_bytes(path, text.encode(), overwrite=True)


def read_record(path: Path) -> dict[str, Any]:
    from plumbing.errors import UserError

    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: no readable study record ({exc}); rerun the study") from None


def machine() -> dict[str, Any]:
    try:
        load = os.getloadavg()[0]
    except OSError:  # not on every platform
        load = float("nan")
    return {"cores": os.cpu_count() or 0, "load_1min": load}


def load_average() -> str:
    """ "load 1/5/15 min on N cores" — a wall time means little without it on a shared machine."""
    try:
        one, five, fifteen = os.getloadavg()
    except OSError:
        return ""
    return f"load average {one:.1f} / {five:.1f} / {fifteen:.1f} on {os.cpu_count()} cores"


def pyplot():  # matplotlib.pyplot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plain_log_ticks(ax) -> None:
    """Tick labels on a log y axis as plain numbers (0.02, not 2×10⁻²): the axis is in %."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}"))


def save_png(fig, path: Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(path, buf.getvalue(), overwrite=True)
    return path

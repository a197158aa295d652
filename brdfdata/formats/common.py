"""What every importer shares: the error type, the σ assumption for files that carry no
uncertainty, and the provenance written into the samples' Parquet metadata (docs/design.md §4).

Provenance keys (strings, in the Parquet key-value metadata):

* ``gonio.source.file`` — the imported file's name as given;
* ``gonio.source.sha256`` — SHA-256 of its bytes (hex);
* ``gonio.source.format`` — ``rgl`` | ``merl`` | ``csv``;
* ``gonio.source.conversion`` — JSON: what was done (grid, σ rule, rows dropped and why, counts).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from brdfdata.samples import SamplesError
from plumbing.hashing import sha256_file

__all__ = [
    "FormatError",
    "SigmaRule",
    "parse_sigma",
    "sha256_file",
    "provenance",
]


class FormatError(SamplesError):
    """A file is not in the format it was imported as, or an import option is wrong. One line,
    naming the file (and column or field) and the fix; the CLI prints it and exits 2."""


@dataclass(frozen=True)
class SigmaRule:
    """How σ is made for a source: ``kind`` = "column" (``value`` is the column name), "rel"
    (σ = value·|f| with a floor, below), "abs" (σ = value, sr⁻¹) or "repeats" (σ of the mean of
    repeated rows).

    The "rel" floor, per channel: the larger of value·median|f| (so f ≈ 0 keeps a positive σ) and
    the RMS of the channel's negative values. Why the negatives: a relative error vanishes at
    f = 0 where a real instrument's does not, and the values a source publishes below zero are
    that error showing — for values whose truth is ≈ 0 they are the lower half of the noise,
    whose mean square is σ² (a half-normal's second moment). Without that floor a published
    −0.4 sr⁻¹ (RGL's golden-yellow blue, out-of-gamut RGB) would sit 50 σ from any
    non-negative model; with it, the value is data of its own honest size (issue 43)."""

    kind: str
    value: float | str | None = None

    def describe(self) -> str:
        if self.kind == "rel":
            return (
                f"sigma = {self.value:g}·|f| (floor per channel: the larger of "
                f"{self.value:g}·median|f| and the RMS of its negative values), assumed"
            )
        if self.kind == "abs":
            return f"sigma = {self.value:g} sr^-1, assumed"
        if self.kind == "repeats":
            return "sigma = standard error of the mean of repeated rows"
        return f"sigma from column {self.value!r}"

    def apply(self, f: np.ndarray, channel: np.ndarray | None = None) -> np.ndarray:
        """σ for values ``f`` (of channels ``channel``; None: one channel) under a "rel" or
        "abs" rule."""
        f = np.asarray(f, dtype=np.float64)
        if self.kind == "abs":
            return np.full(f.shape, float(self.value))
        if self.kind != "rel":
            raise ValueError(f"sigma rule {self.kind!r} needs the table, not only f")
        sigma = float(self.value) * np.abs(f)
        groups = [slice(None)] if channel is None else [channel == c for c in np.unique(channel)]
        for rows in groups:
            sigma[rows] = np.maximum(sigma[rows], self.floor(f[rows]))
        return sigma

    def floor(self, f: np.ndarray) -> float:
        """The "rel" rule's floor for one channel's values ``f`` (class docstring)."""
        finite = f[np.isfinite(f)]
        floor = float(self.value) * (float(np.median(np.abs(finite))) if finite.size else 1.0)
        negative = finite[finite < 0]
        if negative.size:
            floor = max(floor, float(np.sqrt(np.mean(np.square(negative)))))
        return floor if floor > 0 else 1e-12


def parse_sigma(text: str, *, allow_column: bool = True) -> SigmaRule:
    """``rel=0.02`` | ``abs=0.001`` | ``repeats`` | a column name → SigmaRule (FormatError if
    the number is not positive and finite)."""
    text = text.strip()
    key, sep, value = text.partition("=")
    if sep and key in ("rel", "abs"):
        try:
            v = float(value)
        except ValueError:
            v = float("nan")
        if not (np.isfinite(v) and v > 0):
            raise FormatError(f"--sigma {text!r}: {key}= needs a positive number, e.g. {key}=0.02")
        return SigmaRule(key, v)
    if text == "repeats":
        return SigmaRule("repeats")
    if allow_column and text and not sep:
        return SigmaRule("column", text)
    raise FormatError(f"--sigma {text!r}: use rel=FRACTION, abs=VALUE_PER_SR, repeats or COLUMN")


def provenance(path: str | os.PathLike, fmt: str, conversion: dict) -> dict[str, str]:
    """The ``gonio.source.*`` metadata for a file imported as ``fmt``."""
    path = Path(path)
    return {
        "gonio.source.file": path.name,
        "gonio.source.sha256": sha256_file(path),
        "gonio.source.format": fmt,
        "gonio.source.conversion": json.dumps(conversion, sort_keys=True),
    }


#: Grid axes a user may give (degrees at the edge, docs/design.md §3); φ_i defaults to 0.
GRID_AXES = ("theta_i", "phi_i", "theta_o", "phi_o")
#: The most direction pairs a --grid may ask for: MERL's own table is 1.46 M cells, and 2·10⁷
#: rows are ~1.2 GB of samples before a fit starts; a 1e-5° step asked for ~10¹⁹.
GRID_MAX_PAIRS = 20_000_000


def parse_grid(text: str) -> dict[str, np.ndarray]:
    """``"theta_i=0:60:15,theta_o=0:80:10,phi_o=0:180:30"`` (degrees; START:STOP:STEP, STOP
    included, or a single value, or values separated by ``/``) → radians per axis. theta_i,
    theta_o and phi_o are required, phi_i defaults to 0."""
    axes: dict[str, np.ndarray] = {}
    for part in (p.strip() for p in text.split(",") if p.strip()):
        key, sep, spec = part.partition("=")
        key = key.strip()
        if not sep or key not in GRID_AXES:
            raise FormatError(
                f"--grid {part!r}: expected AXIS=START:STOP:STEP with AXIS one of "
                f"{', '.join(GRID_AXES)} (degrees)"
            )
        try:
            if ":" in spec:
                start, stop, step = (float(x) for x in spec.split(":"))
                if not step > 0 or stop < start or not np.isfinite(stop - start):
                    raise ValueError
                count = (stop - start) / step + 1
            else:
                values = np.array([float(x) for x in spec.split("/")])
                count = values.size
        except ValueError:
            raise FormatError(
                f"--grid {part!r}: START:STOP:STEP needs numbers with STEP > 0 and STOP ≥ START"
            ) from None
        if count > GRID_MAX_PAIRS:
            raise FormatError(
                f"--grid {part!r}: {count:.3g} values on one axis; a grid holds at most "
                f"{GRID_MAX_PAIRS:,} direction pairs — use a coarser step"
            )
        if ":" in spec:
            values = np.arange(start, stop + 1e-9 * max(1.0, abs(stop)), step)
        axes[key] = np.radians(values)
    missing = [a for a in ("theta_i", "theta_o", "phi_o") if a not in axes]
    if missing:
        raise FormatError(f"--grid: missing {', '.join(missing)} (degrees, e.g. theta_o=0:80:5)")
    axes.setdefault("phi_i", np.zeros(1))
    pairs = math.prod(int(v.size) for v in axes.values())
    if pairs > GRID_MAX_PAIRS:
        raise FormatError(
            f"--grid: {pairs:,} direction pairs; a grid holds at most {GRID_MAX_PAIRS:,} (each "
            "a row per channel) — use a coarser step"
        )
    for key in ("theta_i", "theta_o"):
        if np.any(axes[key] < 0) or np.any(axes[key] > np.pi / 2 + 1e-12):
            raise FormatError(f"--grid {key}: angles must lie in [0, 90] deg")
    return axes


def grid_directions(axes: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The Cartesian product of the grid axes as flat angle columns (radians). At θ = 0 every φ
    is the same direction (the pole): only the first φ is kept there, so no pair repeats."""
    mesh = np.meshgrid(*(axes[a] for a in GRID_AXES), indexing="ij")
    cols = {a: m.ravel() for a, m in zip(GRID_AXES, mesh, strict=True)}
    keep = np.ones(cols["theta_i"].size, bool)
    for t, p in (("theta_i", "phi_i"), ("theta_o", "phi_o")):
        keep &= ~((cols[t] == 0) & (cols[p] != axes[p][0]))
    return {a: v[keep] for a, v in cols.items()}

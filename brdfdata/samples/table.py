"""The BRDF sample table in memory (docs/design.md §4): its columns, flags and schema version.

Optional column `texel` (int32, issue 20): per-texel samples of a spatially varying sample, the
texel index iy·n + ix on the sample plane (calibration.texels), with the grid in the metadata key
``gonio.texels`` (JSON: texel_mm, n_x, n_y, size_m). Tables without it are one material.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from brdfdata.directions import spherical_to_vector
from plumbing.errors import UserError

__all__ = [
    "SCHEMA_VERSION",
    "REQUIRED_COLUMNS",
    "OPTIONAL_COLUMNS",
    "CHANNELS",
    "FORMAT_NAMES",
    "Flags",
    "FLAG_ROLES",
    "EXCLUDING",
    "CENSORING",
    "RowKinds",
    "row_kinds",
    "DARK_SNR",
    "dark_snr_of",
    "SampleTable",
    "SamplesError",
]

SCHEMA_VERSION = 1
REQUIRED_COLUMNS: dict[str, pa.DataType] = {
    "theta_i": pa.float64(),
    "phi_i": pa.float64(),
    "theta_o": pa.float64(),
    "phi_o": pa.float64(),
    "channel": pa.string(),
    "f": pa.float64(),
    "sigma": pa.float64(),
}
OPTIONAL_COLUMNS: dict[str, pa.DataType] = {
    "capture_id": pa.int64(),
    "pixel_x": pa.int32(),
    "pixel_y": pa.int32(),
    "flags": pa.int32(),
    # Per-texel samples (calibration.texels): the index iy·n + ix of the texel of the sample
    # plane the sample's surface point falls in; the grid is in metadata key "gonio.texels".
    "texel": pa.int32(),
    # The fraction of the camera's clip at which calibration's HDR merge read the sample
    # (calibration.linearity.bend_level): what the camera's remaining bend is proportional to,
    # for the fit's linearity nuisance (fitting.nuisance, ``linearity_pct``).
    "bend_level": pa.float32(),
}
CHANNELS = ("R", "G", "B", "Y")
FORMAT_NAMES = {"rgl": "an RGL tensor", "merl": "a MERL .binary", "csv": "a delimited text"}


class Flags:
    """Bitmask values of the `flags` column (0 = good). What each bit does to a row is
    :data:`FLAG_ROLES`, the one table every reader of the flags applies."""

    SATURATED = 1
    DARK = 2
    BELOW_HORIZON = 4
    MASKED = 8
    #: A value published below zero (e.g. out-of-gamut RGB in an RGL file): a measurement,
    #: marked for the record; it enters fits as any other value.
    NEGATIVE = 16


#: What each flag bit does to a row, for the likelihood, the binned path, the verdicts, the
#: report and the guards alike (docs/formats.md prints this table):
#: "exclude" — the row never enters a fit (nothing was measured there);
#: "censor" — the row enters as a bound (the Tobit likelihood, fitting.likelihood): a saturated
#: reading bounds the truth from below, a dark one says the reading fell below the detection
#: limit; with ``gonio fit --drop-flagged`` they are left out instead;
#: "keep" — the row enters as the measured value it is (a mark for the record).
#: Bits not listed (another tool's) keep their row. Of several bits, exclude beats censor beats
#: keep; saturated beats dark.
FLAG_ROLES: dict[int, tuple[str, str, str]] = {
    # bit: (name, role, meaning)
    Flags.SATURATED: ("saturated", "censor", "the reading hit the clip level: truth above it"),
    Flags.DARK: ("dark", "censor", "the reading fell below the detection limit min_snr·σ"),
    Flags.BELOW_HORIZON: ("below horizon", "exclude", "θ > π/2: f_r is 0 by convention"),
    Flags.MASKED: ("masked", "exclude", "off the sample or not measured"),
    Flags.NEGATIVE: ("negative", "keep", "a value published below zero, within its noise"),
}
EXCLUDING = sum(bit for bit, (_, role, _) in FLAG_ROLES.items() if role == "exclude")
CENSORING = sum(bit for bit, (_, role, _) in FLAG_ROLES.items() if role == "censor")


@dataclass(frozen=True)
class RowKinds:
    """Per row: whether it can enter a fit at all (no excluding bit; finite angles, f and σ;
    σ > 0), and of those which are censored saturated or dark; the rest enter as measured."""

    usable: np.ndarray
    saturated: np.ndarray
    dark: np.ndarray

    @property
    def measured(self) -> np.ndarray:
        return self.usable & ~self.saturated & ~self.dark


#: The calibration's default DARK rule (calibration.reduce.ReduceOptions.min_snr): f/σ < 3.
DARK_SNR = 3.0


def dark_snr_of(metadata: dict[str, str]) -> float:
    """The DARK rule's f/σ limit a calibration used (samples metadata ``gonio.calibration``,
    key min_snr), else the calibration's default."""
    try:
        value = json.loads(metadata.get("gonio.calibration", "{}")).get("min_snr")
    except (TypeError, ValueError, AttributeError):
        value = None
    return float(value) if isinstance(value, int | float) and value > 0 else DARK_SNR


def row_kinds(table: SampleTable) -> RowKinds:
    """:data:`FLAG_ROLES` applied to ``table``'s rows."""
    flags = np.asarray(table.flags, np.int64)
    sat = (flags & Flags.SATURATED) != 0
    dark = ((flags & Flags.DARK) != 0) & ~sat
    usable = (flags & EXCLUDING) == 0
    usable &= np.isfinite(table.f) & np.isfinite(table.sigma) & (table.sigma > 0)
    for a in (table.theta_i, table.phi_i, table.theta_o, table.phi_o):
        usable &= np.isfinite(a)
    return RowKinds(usable, sat, dark)


class SamplesError(UserError, ValueError):
    """A samples file is missing, unreadable, or not a samples table. The message is one line."""


@dataclass
class SampleTable:
    """Columns as numpy arrays (angles in radians, f and sigma in sr⁻¹)."""

    theta_i: np.ndarray
    phi_i: np.ndarray
    theta_o: np.ndarray
    phi_o: np.ndarray
    channel: np.ndarray
    f: np.ndarray
    sigma: np.ndarray
    flags: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    metadata: dict[str, str] = field(default_factory=dict)
    #: SHA-256 of the file the table was read from (None when built in memory); a fit records
    #: it so that a report or export can tell whether it is given the samples the fit used.
    source_sha256: str | None = None

    def __len__(self) -> int:
        return int(self.f.shape[0])

    @property
    def channels(self) -> list[str]:
        """Channels present, in canonical order R, G, B, Y then any others."""
        present = list(dict.fromkeys(self.channel.tolist()))
        order = {c: i for i, c in enumerate(CHANNELS)}
        return sorted(present, key=lambda c: order.get(c, len(order)))

    @property
    def wi(self) -> np.ndarray:
        return spherical_to_vector(self.theta_i, self.phi_i)

    @property
    def wo(self) -> np.ndarray:
        return spherical_to_vector(self.theta_o, self.phi_o)

    @property
    def relative(self) -> bool:
        """True when calibration could not make the values absolute."""
        return self.metadata.get("gonio.absolute", "true").lower() != "true"

    def select(self, mask: np.ndarray) -> SampleTable:
        mask = np.asarray(mask, dtype=bool)
        return SampleTable(
            theta_i=self.theta_i[mask],
            phi_i=self.phi_i[mask],
            theta_o=self.theta_o[mask],
            phi_o=self.phi_o[mask],
            channel=self.channel[mask],
            f=self.f[mask],
            sigma=self.sigma[mask],
            flags=self.flags[mask],
            extra={k: v[mask] for k, v in self.extra.items()},
            metadata=dict(self.metadata),
            source_sha256=self.source_sha256,
        )

    def good(self) -> SampleTable:
        """The rows a fit takes as measured values (:func:`row_kinds`: no excluding or censoring
        flag, finite values, positive σ)."""
        return self.select(row_kinds(self).measured)

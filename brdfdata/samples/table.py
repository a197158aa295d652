"""The BRDF sample table in memory (docs/design.md §4): its columns, flags and schema version.

Optional column `texel` (int32, issue 20): per-texel samples of a spatially varying sample, the
texel index iy·n + ix on the sample plane (calibration.texels), with the grid in the metadata key
``gonio.texels`` (JSON: texel_mm, n_x, n_y, size_m). Tables without it are one material.
"""

from __future__ import annotations

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
}
CHANNELS = ("R", "G", "B", "Y")
FORMAT_NAMES = {"rgl": "an RGL tensor", "merl": "a MERL .binary", "csv": "a delimited text"}


class Flags:
    """Bitmask values of the `flags` column (0 = good)."""

    SATURATED = 1
    DARK = 2
    BELOW_HORIZON = 4
    MASKED = 8
    #: A published value below zero (e.g. out-of-gamut RGB in an RGL file), kept for the record.
    NEGATIVE = 16


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
        """Rows with flags == 0 and finite values and positive σ."""
        ok = (self.flags == 0) & np.isfinite(self.f) & np.isfinite(self.sigma) & (self.sigma > 0)
        return self.select(ok)

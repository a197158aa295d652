"""MERL isotropic BRDF ``.binary`` files (Matusik, Pfister, Brand & McMillan 2003, "A data-driven
reflectance model", ACM TOG 22(3); layout and lookup as in MERL's published ``BRDFRead.cpp``).

Format (little endian)::

    3 × int32        dims = (90, 90, 180)  (θ_h, θ_d, φ_d bins)
    3 × 90·90·180    float64, channel-major (R, then G, then B), index
                     i = φ_d_bin + 180·(θ_d_bin + 90·θ_h_bin)

Values are f_r (sr⁻¹) divided by the channel scale: f = raw · scale with scale =
(1/1500, 1.15/1500, 1.66/1500) for (R, G, B). A negative raw value marks a bin with no data
(below the horizon, or not measured).

Bins (Rusinkiewicz half/difference angles, :mod:`brdfdata.rusinkiewicz`; ω_i plays MERL's "in"):

* θ_h bin = ⌊√(θ_h/(π/2)) · 90⌋ (non-linear: fine near the specular peak), 0 for θ_h ≤ 0;
* θ_d bin = ⌊θ_d/(π/2) · 90⌋;
* φ_d bin = ⌊φ_d/π · 180⌋ with φ_d folded to [0, π) — reciprocity: f(φ_d) = f(φ_d + π);

each clamped to its range. The lookup is nearest-bin (no interpolation), as in BRDFRead.cpp.

A bin's *representative direction* (what :func:`import_merl` writes and :func:`write_model_merl`
evaluates) is its centre in index space: θ_h = ((i + ½)/90)²·π/2, θ_d = (j + ½)/90·π/2,
φ_d = (k + ½)/180·π, with φ_h = 0; bins whose centre has ω_i or ω_o at or below the horizon
hold no data (raw −1).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from brdfdata.directions import spherical_to_vector, vector_to_spherical
from brdfdata.formats.common import FormatError, SigmaRule, grid_directions, provenance
from brdfdata.rusinkiewicz import from_half_diff, to_half_diff
from brdfdata.samples import SampleTable
from plumbing.atomic import atomic_write_bytes
from plumbing.inputs import MiB, read_input_bytes

__all__ = [
    "DIMS",
    "SCALES",
    "MerlTable",
    "read_merl",
    "merl_bytes",
    "write_merl",
    "bin_index",
    "bin_centres",
    "MerlImportOptions",
    "import_merl",
    "tabulate",
    "table_from_samples",
]

DIMS = (90, 90, 180)
#: RED_SCALE, GREEN_SCALE, BLUE_SCALE of BRDFRead.cpp: f = raw · scale.
SCALES = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)
_N = DIMS[0] * DIMS[1] * DIMS[2]
_CHANNELS = ("R", "G", "B")


@dataclass
class MerlTable:
    """``raw`` (3, 90, 90, 180) float64 exactly as stored (f / scale; negative = no data)."""

    raw: np.ndarray

    @property
    def f(self) -> np.ndarray:
        """f_r in sr⁻¹ per bin (3, 90, 90, 180); NaN where the bin has no data."""
        scaled = self.raw * np.asarray(SCALES)[:, None, None, None]
        return np.where(self.raw >= 0, scaled, np.nan)

    def lookup(self, wi, wo) -> np.ndarray:
        """f_r (N, 3) at direction pairs by nearest bin; NaN for bins with no data and for
        directions below the horizon."""
        wi = np.atleast_2d(np.asarray(wi, np.float64))
        wo = np.atleast_2d(np.asarray(wo, np.float64))
        ih, jd, kd = bin_index(*to_half_diff(wi, wo))
        out = self.f[:, ih, jd, kd].T
        below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
        out[below] = np.nan
        return out


def bin_index(theta_h, theta_d, phi_d) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MERL bin indices of (θ_h, θ_d, φ_d) in radians (module docstring)."""
    theta_h, theta_d, phi_d = (np.asarray(a, np.float64) for a in (theta_h, theta_d, phi_d))
    with np.errstate(invalid="ignore"):
        ih = np.floor(np.sqrt(np.maximum(theta_h, 0.0) / (np.pi / 2)) * DIMS[0])
    ih = np.where(theta_h <= 0, 0, ih)
    jd = np.floor(theta_d / (np.pi / 2) * DIMS[1])
    kd = np.floor(np.mod(phi_d, np.pi) / np.pi * DIMS[2])
    return (
        np.clip(ih, 0, DIMS[0] - 1).astype(np.int64),
        np.clip(jd, 0, DIMS[1] - 1).astype(np.int64),
        np.clip(kd, 0, DIMS[2] - 1).astype(np.int64),
    )


def bin_centres() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(θ_h, θ_d, φ_d) of every bin centre, each of shape (90, 90, 180), radians."""
    i, j, k = np.meshgrid(*(np.arange(n) for n in DIMS), indexing="ij")
    theta_h = np.square((i + 0.5) / DIMS[0]) * (np.pi / 2)
    theta_d = (j + 0.5) / DIMS[1] * (np.pi / 2)
    phi_d = (k + 0.5) / DIMS[2] * np.pi
    return theta_h, theta_d, phi_d


def _centre_directions() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ω_i, ω_o) (N, 3) of every bin centre, flat in file order, and the above-horizon mask."""
    th, td, pd = (a.ravel() for a in bin_centres())
    wi, wo = from_half_diff(th, td, pd)
    return wi, wo, (wi[:, 2] > 0) & (wo[:, 2] > 0)


def read_merl(path: str | os.PathLike) -> MerlTable:
    """Read a MERL ``.binary`` file; FormatError naming the file when it is not one."""
    path = Path(path)
    data = read_input_bytes(path, "MERL .binary file", 64 * MiB)  # one is 33.6 MB
    if len(data) < 12:
        raise FormatError(f"{path}: not a MERL .binary file (shorter than its 12-byte header)")
    dims = tuple(int(x) for x in np.frombuffer(data, "<i4", 3))
    if dims != DIMS:
        raise FormatError(
            f"{path}: not a MERL .binary file (header dims {dims}, expected {DIMS}); MERL files "
            "start with the int32 bin counts 90, 90, 180"
        )
    if len(data) != 12 + 3 * _N * 8:
        raise FormatError(
            f"{path}: MERL file has {len(data)} bytes, expected {12 + 3 * _N * 8} (truncated?)"
        )
    raw = np.frombuffer(data, "<f8", 3 * _N, 12).reshape(3, *DIMS).copy()
    return MerlTable(raw=raw)


def merl_bytes(table: MerlTable) -> bytes:
    raw = np.ascontiguousarray(table.raw, dtype="<f8")
    if raw.shape != (3, *DIMS):
        raise ValueError(f"MERL raw table must have shape {(3, *DIMS)}, got {raw.shape}")
    return np.asarray(DIMS, "<i4").tobytes() + raw.tobytes()


def write_merl(path: str | os.PathLike, table: MerlTable) -> Path:
    """Write ``table`` as a MERL ``.binary`` (atomically); read → write is byte-identical."""
    return atomic_write_bytes(path, merl_bytes(table), overwrite=True)


def tabulate(evaluate) -> MerlTable:
    """A MERL table of an analytic BRDF: ``evaluate(wi, wo)`` → f_r (N, 3) in sr⁻¹ is called once
    on every above-horizon bin centre; raw = f / scale, −1 elsewhere."""
    wi, wo, up = _centre_directions()
    f = np.asarray(evaluate(wi[up], wo[up]), np.float64)
    raw = np.full((3, _N), -1.0)
    raw[:, up] = (f / np.asarray(SCALES)).T
    return MerlTable(raw=raw.reshape(3, *DIMS))


def table_from_samples(table: SampleTable) -> tuple[MerlTable, int]:
    """Bin a samples table (good rows; channels R, G, B, or Y for all three) into MERL bins by
    the mean f per bin; empty bins get raw −1. Returns the table and the number of bins with
    data."""
    good = table.good()
    ih, jd, kd = bin_index(*to_half_diff(good.wi, good.wo))
    flat = (ih * DIMS[1] + jd) * DIMS[2] + kd
    sums, counts = np.zeros((3, _N)), np.zeros((3, _N))
    for c, name in enumerate(_CHANNELS):
        m = (good.channel == name) | (good.channel == "Y")
        np.add.at(sums[c], flat[m], good.f[m])
        np.add.at(counts[c], flat[m], 1)
    if not counts.any():
        raise FormatError("samples: no good R, G, B or Y row to bin into a MERL table")
    with np.errstate(invalid="ignore", divide="ignore"):
        raw = np.where(counts > 0, sums / counts / np.asarray(SCALES)[:, None], -1.0)
    return MerlTable(raw=raw.reshape(3, *DIMS)), int((counts > 0).all(axis=0).sum())


@dataclass(frozen=True)
class MerlImportOptions:
    """``grid`` None = every bin with data at its centre, else grid axes (radians) looked up by
    nearest bin; ``sigma`` the assumed σ (a MERL file carries none)."""

    grid: dict[str, np.ndarray] | None = None
    sigma: SigmaRule = SigmaRule("rel", 0.02)


def import_merl(path: str | os.PathLike, options: MerlImportOptions | None = None) -> SampleTable:
    """A MERL file as a samples table: one row per (bin with data, channel); bins with no data
    (negative raw value) are dropped and counted in the provenance. MERL's negatives are not
    measurements: its BRDFRead.cpp and the dataset write −1 (before the scale) where a bin has
    no data, so they are not kept as values the way RGL's are."""
    options = options or MerlImportOptions()
    if options.sigma.kind not in ("rel", "abs"):
        raise FormatError(f"{path}: a MERL file has no σ column; use --sigma rel=… or abs=…")
    table = read_merl(path)
    if options.grid is None:
        wi, wo, up = _centre_directions()
        f = table.f.reshape(3, _N).T  # (N, 3), NaN = no data
        below = int((~up).sum())
        wi, wo, f = wi[up], wo[up], f[up]
        where = "bin centres"
    else:
        g = grid_directions(options.grid)
        wi = spherical_to_vector(g["theta_i"], g["phi_i"])
        wo = spherical_to_vector(g["theta_o"], g["phi_o"])
        f = table.lookup(wi, wo)
        below, where = 0, "grid, nearest bin"
    valid = np.isfinite(f)
    theta_i, phi_i = vector_to_spherical(wi)
    theta_o, phi_o = vector_to_spherical(wo)
    cols: dict[str, list] = {k: [] for k in ("ti", "pi", "to", "po", "ch", "f")}
    for c, name in enumerate(_CHANNELS):
        m = valid[:, c]
        for key, arr in (("ti", theta_i), ("pi", phi_i), ("to", theta_o), ("po", phi_o)):
            cols[key].append(arr[m])
        cols["ch"].append(np.full(int(m.sum()), name))
        cols["f"].append(f[m, c])
    values = np.concatenate(cols["f"])
    if values.size == 0:
        raise FormatError(f"{path}: the MERL file holds no valid bin (all values negative)")
    conversion = {
        "reader": "brdfdata.formats.merl (BRDFRead.cpp layout and lookup)",
        "directions": where,
        "scales": list(SCALES),
        "sigma": options.sigma.describe(),
        "invalid_dropped": int((~valid).sum()),
        "bins_below_horizon": below,
    }
    meta = provenance(path, "merl", conversion)
    meta["gonio.absolute"] = "true"
    return SampleTable(
        theta_i=np.concatenate(cols["ti"]),
        phi_i=np.concatenate(cols["pi"]),
        theta_o=np.concatenate(cols["to"]),
        phi_o=np.concatenate(cols["po"]),
        channel=np.concatenate(cols["ch"]).astype(str),
        f=values,
        sigma=options.sigma.apply(values),
        flags=np.zeros(values.size, np.int32),
        metadata=meta,
    )

"""Binned samples: a table of any size read in bounded memory and reduced to one sample per
small cell of direction space (issue 22, "bounded cost"; docs/performance.md has the figures).

A camera measures millions of pixels per run, most of them within a fraction of a degree of
their neighbours. Fitting every row costs memory (≈ 1 KB per row through the fit) and time
(every likelihood evaluation visits every row); binning them first costs neither and, for a
Gaussian likelihood, loses almost nothing:

* The file is streamed in batches of ``batch_rows`` rows (Parquet row groups); each batch passes
  the same validation as :func:`brdfdata.samples.read_samples` (columns, finiteness, flags,
  channel names, the unit and range guards), so binning never accepts what a whole read refuses.
  Memory is one batch plus the bins, whatever the file's length.
* A bin is a pair of cells, one per direction (ω_i, ω_o), per channel and per kind (exact,
  saturated, dark). A cell is a θ band of width δ (``width_deg``) cut in φ into pieces of
  δ / sin θ_band, so every cell spans about δ × δ of arc, near the pole as at grazing. Rows
  flagged masked or below the horizon never enter a fit and are counted, not binned.
* Exact rows of a bin become one sample: f̄ = Σ w f / Σ w, σ̄ = (Σ w)^(−1/2), w = 1/σ², at the
  w-weighted mean direction (re-normalised). For a Gaussian likelihood of data at one geometry this
  carries exactly the group's information (the duplicate merge of brdfdata.samples.guards); across a
  bin the model is linear to first order around the mean direction, so the one error is the model's
  curvature over the bin: ε_b = Σw f̂(ω_j)/Σw − f̂(ω̄_b) ≈ ½ tr(H Σ_b), with Σ_b the within-bin
  direction spread. A parameter estimate moves by at most ‖ε/σ̄‖₂ posterior standard deviations
  (Cauchy–Schwarz on the linearised normal equations). A fit of a binned file (fitting.fit)
  therefore measures ε with the model at its least-squares optimum (a second streamed pass,
  :func:`binning_bias`), subtracts it from each bin's mean, refits, and states what is left as its
  ``binning`` verdict; tests/fitting/test_binning.py checks the predicted shift and the corrected
  optimum against unbinned fits of Mitsuba data.
* Censored rows of a bin (saturated: bound = the reading; dark: bound = max(f, k·σ), the
  detection limit of fitting.likelihood) become one row at the mean bound and the r.m.s. σ,
  carrying their count in column ``n_rows``: the likelihood weights its censored term by it.
* The fractional discrepancy (fitting.likelihood) then applies once per bin rather than once
  per row: model error is shared by neighbouring pixels, so this is the more honest count.

The result is an ordinary SampleTable (metadata key ``gonio.binned``: width, rows read, bins,
rows left out) that every fit accepts.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from brdfdata.directions import normalize, vector_to_spherical
from brdfdata.samples import (
    Flags,
    SamplesError,
    SampleTable,
    check_columns,
    dark_snr_of,
    open_samples_file,
    row_kinds,
    table_from_arrow,
)
from plumbing.hashing import sha256_file

__all__ = [
    "BinOptions",
    "BinReport",
    "MIN_WIDTH_DEG",
    "binning_bias",
    "bin_table",
    "read_binned",
    "read_bounded",
    "AUTO_BIN_ROWS",
    "AUTO_BIN_DEG",
    "rows_in",
]

#: Below this the packed bin key could overflow int64: at 0.02° it is (9001 θ cells · 18001 φ
#: cells)² × 48 (16 channels × 3 kinds) ≈ 1.3e18 < 9.2e18.
MIN_WIDTH_DEG = 0.02
#: Above this many rows readers bin by default: unbinned, a fit costs ≈ 1 KB and ≈ 0.3 ms of
#: least squares per row (docs/performance.md), and a report's plots show nothing more.
AUTO_BIN_ROWS = 1_000_000
AUTO_BIN_DEG = 0.1
_KIND_EXACT, _KIND_SATURATED, _KIND_DARK = 0, 1, 2
_SUMS = ("n", "w", "wf", "wix", "wiy", "wiz", "wox", "woy", "woz", "ws2")


@dataclass(frozen=True)
class BinOptions:
    """``width_deg``: the cell width δ in each angle; ``batch_rows``: rows read at a time;
    ``dark_snr``: the DARK rule's f/σ limit (the detection limit of a dark row's bound; None:
    the calibration's, from the table's metadata, as the fit uses it)."""

    width_deg: float = 0.1
    batch_rows: int = 1 << 20
    dark_snr: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.width_deg) and self.width_deg >= MIN_WIDTH_DEG):
            raise SamplesError(
                f"bin width {self.width_deg} deg: use at least {MIN_WIDTH_DEG} deg (0 = no binning)"
            )


@dataclass(frozen=True)
class BinReport:
    """What binning did: rows read, bins made, rows left out (masked, below the horizon)."""

    rows: int
    bins: int
    left_out: int
    width_deg: float
    #: Channel names in the order of their code in the bin keys (for a second pass).
    channels: tuple[str, ...] = ()

    def line(self) -> str:
        return (
            f"binned {self.rows:,} rows into {self.bins:,} bins of {self.width_deg:g}° "
            f"({self.rows / max(self.bins, 1):.0f} rows per bin; {self.left_out:,} masked or "
            "below-horizon rows left out); each bin is one sample of the fit (--bin 0 fits "
            "every row)"
        )


class _Accumulator:
    """Per-bin sums, merged batch by batch so memory stays a few times the number of bins."""

    def __init__(self, width_deg: float, dark_snr: float) -> None:
        self.delta = math.radians(width_deg)
        self.dark_snr = dark_snr
        self.n_theta = int(math.ceil(math.pi / self.delta)) + 1
        self.n_phi = int(math.ceil(2 * math.pi / self.delta)) + 1
        self.channels: dict[str, int] = {}
        self.keys = np.zeros(0, np.int64)
        self.sums = {k: np.zeros(0) for k in _SUMS}
        self.rows = 0
        self.left_out = 0
        self.metadata: dict[str, str] | None = None

    def add(self, t: SampleTable) -> None:
        if self.metadata is None:
            self.metadata = dict(t.metadata)
        self.rows += len(t)
        kinds = row_kinds(t)  # brdfdata.samples.FLAG_ROLES, read as the likelihood reads it
        usable, sat, dark = kinds.usable, kinds.saturated, kinds.dark
        self.left_out += int(np.sum(~usable))
        t = t.select(usable)
        sat, dark = sat[usable], dark[usable]
        key, kind = self.keys_of(t, sat, dark)
        exact = kind == _KIND_EXACT
        with np.errstate(invalid="ignore"):
            bound = np.where(dark, np.maximum(t.f, self.dark_snr * t.sigma), t.f)
        # Exact rows: inverse-variance weights; censored rows: plain means (module docstring).
        w = np.where(exact, 1.0 / np.square(t.sigma), 1.0)
        wi, wo = t.wi, t.wo
        values = {
            "n": np.ones(len(t)),
            "w": w,
            "wf": w * bound,
            "wix": w * wi[:, 0],
            "wiy": w * wi[:, 1],
            "wiz": w * wi[:, 2],
            "wox": w * wo[:, 0],
            "woy": w * wo[:, 1],
            "woz": w * wo[:, 2],
            "ws2": w * np.square(t.sigma),
        }
        self._merge(key, values)

    def keys_of(self, t: SampleTable, sat: np.ndarray, dark: np.ndarray):
        """(packed bin key, kind) of every row of ``t`` (all usable)."""
        kind = np.where(sat, _KIND_SATURATED, np.where(dark, _KIND_DARK, _KIND_EXACT))
        names, chan_idx = np.unique(t.channel, return_inverse=True)
        code = np.array([self.channels.setdefault(str(c), len(self.channels)) for c in names])
        if len(self.channels) > 16:
            raise SamplesError("more than 16 channels: binning packs at most 16")
        chan = code[chan_idx.ravel()] if len(names) else np.zeros(0, np.int64)
        return self._key(t, chan * 3 + kind), kind

    def _key(self, t: SampleTable, group: np.ndarray) -> np.ndarray:
        """The packed cell of each row: per direction a θ band of width δ, cut in φ into
        cells of width δ/sin θ_band (so a cell spans ≈ δ × δ of arc everywhere, not a sliver
        near the pole), then channel and kind."""
        key = group.astype(np.int64)
        for theta, phi in ((t.theta_i, t.phi_i), (t.theta_o, t.phi_o)):
            band, cell = self._cell(theta, phi)
            key = (key * self.n_theta + band) * self.n_phi + cell
        return key

    def _cell(self, theta: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self.delta
        band = np.clip(np.floor(theta / d), 0, self.n_theta - 1).astype(np.int64)
        n_cells = np.maximum(1, np.ceil(2 * np.pi * np.sin((band + 0.5) * d) / d)).astype(np.int64)
        frac = np.mod(phi, 2 * np.pi) / (2 * np.pi)
        cell = np.minimum(np.floor(frac * n_cells).astype(np.int64), n_cells - 1)
        return band, cell

    def _merge(self, key: np.ndarray, values: dict[str, np.ndarray]) -> None:
        keys = np.concatenate([self.keys, key])
        uniq, inv = np.unique(keys, return_inverse=True)
        inv = inv.ravel()
        for name in _SUMS:
            both = np.concatenate([self.sums[name], values[name]])
            self.sums[name] = np.bincount(inv, weights=both, minlength=uniq.size)
        self.keys = uniq

    def table(self) -> SampleTable:
        s = self.sums
        kind = (self.keys // (self.n_theta * self.n_phi) ** 2) % 3
        chan_code = (self.keys // (self.n_theta * self.n_phi) ** 2) // 3
        names = np.array(sorted(self.channels, key=self.channels.get), dtype=object)
        w = s["w"]
        wi = normalize(np.stack([s["wix"], s["wiy"], s["wiz"]], axis=1) / w[:, None])
        wo = normalize(np.stack([s["wox"], s["woy"], s["woz"]], axis=1) / w[:, None])
        theta_i, phi_i = vector_to_spherical(wi)
        theta_o, phi_o = vector_to_spherical(wo)
        exact = kind == _KIND_EXACT
        sigma = np.where(exact, 1.0 / np.sqrt(w), np.sqrt(s["ws2"] / w))
        flags = np.where(
            kind == _KIND_SATURATED, Flags.SATURATED, np.where(kind == _KIND_DARK, Flags.DARK, 0)
        ).astype(np.int32)
        return SampleTable(
            theta_i=np.clip(theta_i, 0.0, np.pi / 2),
            phi_i=phi_i,
            theta_o=np.clip(theta_o, 0.0, np.pi / 2),
            phi_o=phi_o,
            channel=names[chan_code].astype(str) if len(names) else np.zeros(0, str),
            f=s["wf"] / w,
            sigma=sigma,
            flags=flags,
            extra={"n_rows": s["n"].astype(np.int64), "bin_key": self.keys.copy()},
            metadata=dict(self.metadata or {}),
        )


def _dark_snr(opt: BinOptions, metadata: dict[str, str]) -> float:
    return float(opt.dark_snr) if opt.dark_snr is not None else dark_snr_of(metadata)


def bin_table(
    table: SampleTable, options: BinOptions | None = None, *, members: bool = False
) -> SampleTable | tuple[SampleTable, np.ndarray]:
    """``table`` (in memory) binned as :func:`read_binned` bins a file; with ``members`` also
    each row's bin (its row in the result; −1 for rows left out)."""
    opt = options or BinOptions()
    acc = _Accumulator(opt.width_deg, _dark_snr(opt, table.metadata))
    acc.add(table)
    out = acc.table()
    if members:
        kinds = row_kinds(table)
        sat, dark = kinds.saturated, kinds.dark
        index = _bin_of(acc.keys, acc.keys_of(table, sat, dark)[0])
    report = BinReport(acc.rows, len(out), acc.left_out, opt.width_deg, tuple(acc.channels))
    out.metadata["gonio.binned"] = json.dumps(report.__dict__)
    out.source_sha256 = table.source_sha256
    return (out, index) if members else out


def read_binned(
    path: str | Path, options: BinOptions | None = None, *, merge_duplicates: bool = False
) -> tuple[SampleTable, BinReport]:
    """Stream the samples file at ``path`` and bin it (module docstring); memory is bounded by
    one batch of rows plus the bins. Raises SamplesError (one line) as read_samples does."""
    opt = options or BinOptions()
    path = Path(path)
    parquet = open_samples_file(path)
    schema = parquet.schema_arrow
    check_columns(schema.names, path)
    if parquet.metadata.num_rows == 0:
        raise SamplesError(f"{path}: the samples table is empty")
    meta = {
        k.decode(): v.decode()
        for k, v in (schema.metadata or {}).items()
        if not k.startswith(b"ARROW")
    }
    acc = _Accumulator(opt.width_deg, _dark_snr(opt, meta))
    try:
        for batch in parquet.iter_batches(batch_size=opt.batch_rows):
            arrow = pa.Table.from_batches([batch]).replace_schema_metadata(schema.metadata)
            acc.add(table_from_arrow(arrow, path, merge_duplicates=merge_duplicates))
    except SamplesError:
        raise
    except (OSError, pa.ArrowException) as exc:  # a damaged row group behind a good footer
        raise SamplesError(
            f"{path}: a row group cannot be read ({type(exc).__name__}: damaged); re-create the "
            "file"
        ) from None
    out = acc.table()
    report = BinReport(acc.rows, len(out), acc.left_out, opt.width_deg, tuple(acc.channels))
    out.metadata["gonio.binned"] = json.dumps(report.__dict__)
    out.source_sha256 = sha256_file(path)
    return out, report


def _bin_of(keys: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Row of each ``key`` in the sorted bin ``keys``, −1 where it has no bin."""
    index = np.searchsorted(keys, key)
    found = (index < keys.size) & (keys[np.minimum(index, max(keys.size - 1, 0))] == key)
    return np.where(found, index, -1)


def binning_bias(
    path: str | Path,
    binned: SampleTable,
    predict: Callable[[SampleTable], np.ndarray],
    options: BinOptions | None = None,
) -> np.ndarray:
    """ε_b/σ̄_b per row of ``binned`` (module docstring: ε_b = Σw f̂(ω_j)/Σw − f̂(ω̄_b)) for
    the model values ``predict(table)`` (one per row; NaN for rows it does not fit, e.g.
    another channel); 0 for censored bins and bins the model does not fit — a second streamed
    pass over the file. Its norm bounds the shift of any estimate, in posterior sds."""
    opt = options or BinOptions()
    info = json.loads(binned.metadata["gonio.binned"])
    keys = np.asarray(binned.extra["bin_key"], np.int64)
    acc = _Accumulator(info["width_deg"], 0.0)
    acc.channels = {c: i for i, c in enumerate(info["channels"])}
    w_sum = np.zeros(keys.size)
    wf_sum = np.zeros(keys.size)
    path = Path(path)
    # The rows were validated when they were binned; a file changed since is refused rather
    # than re-checked batch by batch (the guards cost as much as the pass itself).
    if binned.source_sha256 is not None and sha256_file(path) != binned.source_sha256:
        raise SamplesError(f"{path}: changed while it was being fitted; fit it again")
    parquet = open_samples_file(path)
    schema = parquet.schema_arrow
    for batch in parquet.iter_batches(batch_size=opt.batch_rows):
        arrow = pa.Table.from_batches([batch]).replace_schema_metadata(schema.metadata)
        t = table_from_arrow(arrow, path, guards=False)
        kinds = row_kinds(t)  # brdfdata.samples.FLAG_ROLES, read as the likelihood reads it
        usable, sat, dark = kinds.usable, kinds.saturated, kinds.dark
        exact = usable & ~sat & ~dark
        t = t.select(exact)
        f_model = np.asarray(predict(t), dtype=np.float64)
        index = _bin_of(keys, acc.keys_of(t, np.zeros(len(t), bool), np.zeros(len(t), bool))[0])
        ok = (index >= 0) & np.isfinite(f_model)
        w = 1.0 / np.square(t.sigma[ok])
        w_sum += np.bincount(index[ok], w, keys.size)
        wf_sum += np.bincount(index[ok], w * f_model[ok], keys.size)
    at_mean = np.asarray(predict(binned), dtype=np.float64)
    use = (binned.flags == 0) & (w_sum > 0) & np.isfinite(at_mean)
    eps = np.zeros(len(binned))
    eps[use] = (wf_sum[use] / w_sum[use] - at_mean[use]) / binned.sigma[use]
    return eps


def read_bounded(path: str | Path) -> SampleTable:
    """The samples at ``path`` for display (gonio report): whole up to AUTO_BIN_ROWS rows, else
    streamed and binned (AUTO_BIN_DEG), so memory stays bounded whatever the file's length."""
    from brdfdata.samples import read_samples

    if rows_in(path) <= AUTO_BIN_ROWS:
        return read_samples(path)
    return read_binned(path, BinOptions(width_deg=AUTO_BIN_DEG))[0]


def rows_in(path: str | Path) -> int:
    """Rows of a samples file, from its footer (no rows read)."""
    return int(open_samples_file(Path(path)).metadata.num_rows)

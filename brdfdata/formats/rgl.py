"""RGL material-database BRDFs: our own reader of the adaptive parameterization of Dupuy & Jakob
(2018), "An adaptive parameterization for efficient material acquisition and rendering",
ACM TOG 37(6), 274 — not through Mitsuba.

Format (fields of the ``tensor_file`` container, :mod:`brdfdata.formats.tensor_file`), as the
RGL reference loader ``powitacq_rgb.inl`` and Mitsuba 3's ``measured`` plugin read it:

* ``theta_i`` (n_θ,), ``phi_i`` (n_φ,): incidence angles in radians where the tables are given
  (n_φ = 1 for isotropic materials);
* ``ndf`` (2, 128), ``sigma`` (2, 128): the microfacet distribution D and the projected area
  σ(ω_i), bilinear on the unit square (u_θ, u_φ) with θ = u_θ²·π/2 and φ = (2u_φ − 1)π;
* ``vndf`` (n_φ, n_θ, 128, 128): the visible-normal density that warps the unit square to the
  half vector (u_θm, u_φm) — a "Marginal2D" (marginal CDF over rows, conditional over columns,
  bilinear density, linear interpolation across the parameters φ_i, θ_i);
* ``rgb`` (n_φ, n_θ, 3, n, n) or ``spectra`` (n_φ, n_θ, n_λ, n, n) + ``wavelengths`` (n_λ,) nm:
  the reflectance on the *sample* square of that warp, bilinear, interpolated in the
  parameters (φ_i, θ_i, channel or wavelength);
* ``luminance``: a sampling density only; ``jacobian`` (uint8): when 1 the value is
  multiplied by D(ω_m)/(4 σ(ω_i)); ``description`` (uint8 text); ``valid``: a bitmask over
  (θ_i, n, n), most significant bit first, set where the node has no measurement — on the
  four published files exactly the nodes whose ω_o lies below the horizon.

Evaluation (powitacq ``BRDF::eval`` / Mitsuba ``Measured::eval``): ω_m = (ω_i + ω_o)/|…|,
u_m = (√(θ_m/(π/2)), ((φ_m − φ_i) + π)/(2π) mod 1), s = vndf⁻¹(u_m; φ_i, θ_i),
value = table(s; φ_i, θ_i, c) [· D(u_m)/(4 σ(u_i))]. The value is f_r·cos θ_o (Mitsuba's
``bsdf.eval`` convention); :meth:`RglBrdf.eval` divides by cos θ_o and returns f_r in sr⁻¹.
Unlike the reference loader we do not clamp negative values (out-of-gamut spectra give
slightly negative RGB): they are returned as they are and the importer flags them.

"The file's measured directions": for each tabulated θ_i (φ_i = the table's), the nodes
(k, l)/(n − 1) of the sample square mapped through the forward warp u_m = vndf(s), then
ω_o = 2(ω_m·ω_i)ω_m − ω_i. Nodes the ``valid`` mask marks, or with ω_o at or below the horizon,
or at grazing incidence (θ_i ≥ 89.9°), are not samples and are counted, not imported. Two
edges of the square are one direction each time: the last row (φ_m − φ_i = +π) repeats the
first (−π), and the first column (θ_m = 0) is the mirror direction for every row; those
repeats are left out too (counted), so no direction appears twice.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from brdfdata.directions import normalize, spherical_to_vector, vector_to_spherical
from brdfdata.formats.common import FormatError, SigmaRule, grid_directions, provenance
from brdfdata.formats.tensor_file import read_tensor_file
from brdfdata.samples import Flags, SampleTable

__all__ = [
    "Warp2D",
    "RglBrdf",
    "RglImportOptions",
    "load_rgl",
    "import_rgl",
    "measured_directions",
    "theta2u",
    "u2theta",
    "phi2u",
    "u2phi",
]

#: float32's largest value below 1, as the reference code clamps samples with it.
_ONE_MINUS_EPS = float(np.float32(0.999999940395355225))
#: Incidence at or beyond this is grazing: no irradiance reaches the sample, no sample is made.
GRAZING_THETA_I = np.radians(89.9)


def u2theta(u):
    return np.square(u) * (np.pi / 2)


def theta2u(theta):
    return np.sqrt(np.asarray(theta) * (2 / np.pi))


def u2phi(u):
    return (2 * np.asarray(u) - 1) * np.pi


def phi2u(phi):
    return (np.asarray(phi) + np.pi) / (2 * np.pi)


def _elevation(d: np.ndarray) -> np.ndarray:
    """θ of unit vectors as 2·asin(|d − z|/2): stable near the pole (Mitsuba ``elevation``)."""
    dist = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + (d[:, 2] - 1) ** 2)
    return 2 * np.arcsin(np.clip(0.5 * dist, -1.0, 1.0))


class Warp2D:
    """A Marginal2D of the reference code, vectorised in float64: a bilinear density on the unit
    square, tabulated as ``data`` of shape (*param_res, ny, nx), linearly interpolated in the
    parameters whose node values are ``params``; with ``normalize`` each slice is scaled to
    integrate to 1 and the marginal/conditional CDFs for :meth:`sample`/:meth:`invert` built.
    """

    def __init__(self, data: np.ndarray, params: list[np.ndarray], normalize: bool):
        data = np.asarray(data, dtype=np.float64)
        self.param_values = [np.asarray(p, dtype=np.float64) for p in params]
        self.param_res = tuple(int(p.size) for p in self.param_values)
        if data.shape[: len(params)] != self.param_res or data.ndim != len(params) + 2:
            raise ValueError(f"table shape {data.shape} does not match parameters {self.param_res}")
        self.ny, self.nx = data.shape[-2:]
        slices = int(np.prod(self.param_res, dtype=np.int64))
        self.data = data.reshape(slices, self.ny, self.nx)
        # Strides of each parameter in slices (the last one innermost), 0 for a single node.
        strides, acc = [], 1
        for res in reversed(self.param_res):
            strides.append(acc if res > 1 else 0)
            acc *= res
        self.strides = tuple(reversed(strides))
        self.normalized = normalize
        if normalize:
            d = self.data
            # Trapezoid sums along x, then over the rows' totals along y (no patch-size factor,
            # as in the reference; the normalisation below absorbs it).
            cond = np.concatenate(
                [np.zeros((slices, self.ny, 1)), np.cumsum(0.5 * (d[..., 1:] + d[..., :-1]), -1)],
                axis=-1,
            )
            rows = cond[..., -1]
            marg = np.concatenate(
                [np.zeros((slices, 1)), np.cumsum(0.5 * (rows[:, 1:] + rows[:, :-1]), -1)], -1
            )
            norm = 1.0 / marg[:, -1]
            self.cond = cond * norm[:, None, None]
            self.marg = marg * norm[:, None]
            self.data = d * norm[:, None, None]
            self.density_scale = float((self.nx - 1) * (self.ny - 1))
        else:
            self.density_scale = 1.0

    # -- parameter interpolation ---------------------------------------------------------------
    def _corners(self, params: list[np.ndarray] | None, n: int):
        """[(slice index (n,), weight (n,)), …] over the 2^D corners of the parameter cell."""
        corners = [(np.zeros(n, np.int64), np.ones(n))]
        for dim, values in enumerate(self.param_values):
            if values.size == 1:
                continue  # weight (1, 0): the single node
            p = np.broadcast_to(np.asarray(params[dim], dtype=np.float64), (n,))
            idx = np.clip(np.searchsorted(values, p, side="right") - 1, 0, values.size - 2)
            p0, p1 = values[idx], values[idx + 1]
            w1 = np.clip((p - p0) / (p1 - p0), 0.0, 1.0)
            stride = self.strides[dim]
            corners = [
                (s + (idx + bit) * stride, w * (w1 if bit else 1.0 - w1))
                for (s, w), bit in itertools.product(corners, (0, 1))
            ]
        return corners

    @staticmethod
    def _lookup(table: np.ndarray, corners, *index) -> np.ndarray:
        """Σ_corners w·table[slice, *index] (index arrays per point, (n,) or (n, k))."""
        extra = max((np.ndim(i) for i in index), default=1) - 1
        shape = (-1,) + (1,) * extra
        return sum(w.reshape(shape) * table[(s.reshape(shape), *index)] for s, w in corners)

    # -- evaluation ---------------------------------------------------------------------------
    def eval(self, pos: np.ndarray, params: list[np.ndarray] | None = None) -> np.ndarray:
        """Bilinear density at ``pos`` (n, 2) = (x, y) in the unit square."""
        pos = np.asarray(pos, dtype=np.float64)
        n = pos.shape[0]
        corners = self._corners(params, n)
        x, y = pos[:, 0] * (self.nx - 1), pos[:, 1] * (self.ny - 1)
        ix = np.clip(x.astype(np.int64), 0, self.nx - 2)
        iy = np.clip(y.astype(np.int64), 0, self.ny - 2)
        fx, fy = x - ix, y - iy
        v00 = self._lookup(self.data, corners, iy, ix)
        v10 = self._lookup(self.data, corners, iy, ix + 1)
        v01 = self._lookup(self.data, corners, iy + 1, ix)
        v11 = self._lookup(self.data, corners, iy + 1, ix + 1)
        value = (1 - fy) * ((1 - fx) * v00 + fx * v10) + fy * ((1 - fx) * v01 + fx * v11)
        return value * self.density_scale

    def invert(self, u: np.ndarray, params: list[np.ndarray] | None = None):
        """The sample-square point that :meth:`sample` maps to ``u`` (n, 2), and the density."""
        u = np.asarray(u, dtype=np.float64)
        corners = self._corners(params, u.shape[0])
        x, y = u[:, 0] * (self.nx - 1), u[:, 1] * (self.ny - 1)
        ix = np.clip(x.astype(np.int64), 0, self.nx - 2)
        iy = np.clip(y.astype(np.int64), 0, self.ny - 2)
        fx, fy = x - ix, y - iy
        v00 = self._lookup(self.data, corners, iy, ix)
        v10 = self._lookup(self.data, corners, iy, ix + 1)
        v01 = self._lookup(self.data, corners, iy + 1, ix)
        v11 = self._lookup(self.data, corners, iy + 1, ix + 1)
        c0 = (1 - fy) * v00 + fy * v01
        c1 = (1 - fy) * v10 + fy * v11
        pdf = (1 - fx) * c0 + fx * c1
        sx = fx * (c0 + 0.5 * fx * (c1 - c0))
        sx += (1 - fy) * self._lookup(self.cond, corners, iy, ix) + fy * self._lookup(
            self.cond, corners, iy + 1, ix
        )
        r0 = self._lookup(self.cond, corners, iy, self.nx - 1)
        r1 = self._lookup(self.cond, corners, iy + 1, self.nx - 1)
        sx /= (1 - fy) * r0 + fy * r1
        sy = fy * (r0 + 0.5 * fy * (r1 - r0)) + self._lookup(self.marg, corners, iy)
        return np.stack([sx, sy], axis=1), pdf * self.density_scale

    def sample(self, s: np.ndarray, params: list[np.ndarray] | None = None):
        """Warp unit-square points ``s`` (n, 2) by the density; returns (points, density)."""
        s = np.clip(np.asarray(s, dtype=np.float64), 1 - _ONE_MINUS_EPS, _ONE_MINUS_EPS)
        n = s.shape[0]
        corners = self._corners(params, n)
        every = np.arange(self.ny)[None, :]
        marg = self._lookup(self.marg, corners, every)  # (n, ny) interpolated marginal CDF
        sx, sy = s[:, 0].copy(), s[:, 1].copy()
        row = np.clip(np.sum(marg < sy[:, None], axis=1) - 1, 0, self.ny - 2)
        sy -= marg[np.arange(n), row]
        r0 = self._lookup(self.cond, corners, row, self.nx - 1)
        r1 = self._lookup(self.cond, corners, row + 1, self.nx - 1)
        sy = _solve_linear_cdf(sy, r0, r1)
        sx *= (1 - sy) * r0 + sy * r1
        cols = np.arange(self.nx)[None, :]
        cond = (1 - sy[:, None]) * self._lookup(self.cond, corners, row[:, None], cols)
        cond += sy[:, None] * self._lookup(self.cond, corners, row[:, None] + 1, cols)
        col = np.clip(np.sum(cond < sx[:, None], axis=1) - 1, 0, self.nx - 2)
        sx -= cond[np.arange(n), col]
        v00 = self._lookup(self.data, corners, row, col)
        v10 = self._lookup(self.data, corners, row, col + 1)
        v01 = self._lookup(self.data, corners, row + 1, col)
        v11 = self._lookup(self.data, corners, row + 1, col + 1)
        c0 = (1 - sy) * v00 + sy * v01
        c1 = (1 - sy) * v10 + sy * v11
        sx = _solve_linear_cdf(sx, c0, c1)
        pts = np.stack([(col + sx) / (self.nx - 1), (row + sy) / (self.ny - 1)], axis=1)
        return pts, ((1 - sx) * c0 + sx * c1) * self.density_scale


def _solve_linear_cdf(t, a, b):
    """x ∈ [0, 1] with ∫₀ˣ ((1 − s)a + s b) ds = t (the reference's quadratic, with its
    near-constant branch)."""
    const = np.abs(a - b) < 1e-4 * (a + b)
    with np.errstate(invalid="ignore", divide="ignore"):
        quad = (a - np.sqrt(np.maximum(a * a - 2 * t * (a - b), 0.0))) / (a - b)
        lin = 2 * t / (a + b)
    return np.where(const, lin, quad)


@dataclass
class RglBrdf:
    """A loaded RGL material: :meth:`eval_cos` (f_r·cos θ_o, the file's quantity) and
    :meth:`eval` (f_r, sr⁻¹) for direction pairs (ω_i, ω_o), per channel."""

    path: Path
    description: str
    theta_i: np.ndarray
    phi_i: np.ndarray
    channels: list[str]
    channel_params: np.ndarray
    spectral: bool
    ndf: Warp2D
    sigma: Warp2D
    vndf: Warp2D
    table: Warp2D
    jacobian: bool
    isotropic: bool
    reduction: int
    unmeasured: np.ndarray | None = None  # (n_θ, n, n) True where the file has no measurement
    fields: dict = field(default_factory=dict, repr=False)

    @property
    def grid_size(self) -> int:
        return self.table.nx

    def _prepare(self, wi, wo):
        wi = np.atleast_2d(np.asarray(wi, dtype=np.float64)).copy()
        wo = np.atleast_2d(np.asarray(wo, dtype=np.float64)).copy()
        if self.reduction >= 2:  # fold into the tabulated part of the φ_i range (Mitsuba)
            sy = wi[:, 1]
            sx = wi[:, 0] if self.reduction == 4 else sy
            for v in (wi, wo):
                v[:, 0] = _mulsign_neg(v[:, 0], sx)
                v[:, 1] = _mulsign_neg(v[:, 1], sy)
        return wi, wo

    def eval_cos(self, wi, wo, channels: list[int] | None = None) -> np.ndarray:
        """f_r·cos θ_o, shape (n, n_channels), zero where either direction is below the horizon;
        negative table values are kept."""
        wi, wo = self._prepare(wi, wo)
        n = wi.shape[0]
        chans = list(range(len(self.channels))) if channels is None else list(channels)
        out = np.zeros((n, len(chans)))
        active = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        if not active.any():
            return out
        wi, wo = wi[active], wo[active]
        wm = normalize(wi + wo)
        theta_i, phi_i = _elevation(wi), np.arctan2(wi[:, 1], wi[:, 0])
        theta_m, phi_m = _elevation(wm), np.arctan2(wm[:, 1], wm[:, 0])
        u_wi = np.stack([theta2u(theta_i), phi2u(phi_i)], axis=1)
        u_m = np.stack(
            [theta2u(theta_m), phi2u(phi_m - phi_i if self.isotropic else phi_m)], axis=1
        )
        u_m[:, 1] -= np.floor(u_m[:, 1])
        params = [phi_i, theta_i]
        s, _ = self.vndf.invert(u_m, params)
        vals = np.stack(
            [
                self.table.eval(s, [phi_i, theta_i, np.full(s.shape[0], self.channel_params[c])])
                for c in chans
            ],
            axis=1,
        )
        if self.jacobian:
            vals *= (self.ndf.eval(u_m) / (4 * self.sigma.eval(u_wi)))[:, None]
        out[active] = vals
        return out

    def eval(self, wi, wo, channels: list[int] | None = None) -> np.ndarray:
        """f_r in sr⁻¹ (n, n_channels): :meth:`eval_cos` / cos θ_o; zero below the horizon."""
        wo_arr = np.atleast_2d(np.asarray(wo, dtype=np.float64))
        v = self.eval_cos(wi, wo, channels)
        cos_o = wo_arr[:, 2]
        return np.divide(v, cos_o[:, None], out=np.zeros_like(v), where=cos_o[:, None] > 0)


def _mulsign_neg(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x·(−sign y) with sign(±0) = ±1 (drjit ``mulsign_neg``)."""
    return np.where(np.signbit(y), x, -x)


def load_rgl(path: str | os.PathLike) -> RglBrdf:
    """Read an RGL ``.bsdf`` tensor file (RGB or spectral). FormatError naming the file and
    field when a field is missing or has the wrong shape."""
    path = Path(path)
    f = read_tensor_file(path)
    spectral = "spectra" in f and "wavelengths" in f
    table_name = "spectra" if spectral else "rgb"
    need = ["theta_i", "phi_i", "ndf", "sigma", "vndf", table_name]
    missing = [k for k in need if k not in f]
    if missing:
        raise FormatError(
            f"{path}: not an RGL BRDF tensor (missing field(s) {', '.join(missing)}); "
            "expected an isotropic or anisotropic *_rgb.bsdf or *_spec.bsdf file"
        )
    theta_i = np.asarray(f["theta_i"], np.float64)
    phi_i = np.asarray(f["phi_i"], np.float64)
    table = np.asarray(f[table_name], np.float64)
    n_phi, n_theta = phi_i.size, theta_i.size
    if (
        table.ndim != 5
        or table.shape[:2] != (n_phi, n_theta)
        or f["vndf"].shape[:2] != (n_phi, n_theta)
        or f["ndf"].ndim != 2
        or f["sigma"].ndim != 2
    ):
        raise FormatError(
            f"{path}: field shapes do not fit together ({table_name} {table.shape}, vndf "
            f"{f['vndf'].shape}, theta_i {theta_i.shape}, phi_i {phi_i.shape})"
        )
    if spectral:
        wl = np.asarray(f["wavelengths"], np.float64)
        channels, chan_params = [f"{w:g}nm" for w in wl], wl
    else:
        channels, chan_params = ["R", "G", "B"], np.arange(3.0)
    isotropic = n_phi <= 2
    reduction = 1
    if not isotropic:
        reduction = int(np.rint(2 * np.pi / (phi_i[-1] - phi_i[0])))
    unmeasured = None
    if "valid" in f:
        bits = np.unpackbits(np.asarray(f["valid"], np.uint8).ravel(), bitorder="big")
        n = table.shape[-1]
        if bits.size >= n_phi * n_theta * n * n:
            unmeasured = bits[: n_phi * n_theta * n * n].reshape(n_phi * n_theta, n, n) == 1
    desc = bytes(np.asarray(f.get("description", np.zeros(0, np.uint8)), np.uint8)).decode(
        "utf-8", "replace"
    )
    return RglBrdf(
        path=path,
        description=desc,
        theta_i=theta_i,
        phi_i=phi_i,
        channels=channels,
        channel_params=chan_params,
        spectral=spectral,
        ndf=Warp2D(f["ndf"], [], normalize=False),
        sigma=Warp2D(f["sigma"], [], normalize=False),
        vndf=Warp2D(f["vndf"], [phi_i, theta_i], normalize=True),
        table=Warp2D(table, [phi_i, theta_i, chan_params], normalize=False),
        jacobian=bool(np.asarray(f.get("jacobian", np.ones(1, np.uint8))).ravel()[0]),
        isotropic=isotropic,
        reduction=reduction,
        unmeasured=unmeasured,
        fields=f,
    )


def measured_directions(brdf: RglBrdf) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """(ω_i, ω_o) (N, 3) at the file's measured nodes (module docstring) and the counts of
    nodes left out, by reason."""
    n = brdf.grid_size
    grid = np.linspace(0.0, 1.0, n)
    sx, sy = np.meshgrid(grid, grid, indexing="xy")  # node (row l = y, column k = x)
    s = np.stack([sx.ravel(), sy.ravel()], axis=1)
    rows, cols = np.divmod(np.arange(n * n), n)
    repeat = (rows == n - 1) | ((cols == 0) & (rows > 0))  # the seam row and the pole column
    wis, wos = [], []
    counts = {"grazing_incidence": 0, "not_measured": 0, "below_horizon": 0, "repeated": 0}
    for ip, phi_i in enumerate(brdf.phi_i):
        for it, theta_i in enumerate(brdf.theta_i):
            if theta_i >= GRAZING_THETA_I:
                counts["grazing_incidence"] += s.shape[0]
                continue
            keep = ~repeat
            counts["repeated"] += int(repeat.sum())
            if brdf.unmeasured is not None:
                miss = brdf.unmeasured[ip * brdf.theta_i.size + it].ravel()
                counts["not_measured"] += int((miss & keep).sum())
                keep = keep & ~miss
            params = [np.full(s.shape[0], phi_i), np.full(s.shape[0], theta_i)]
            u_m, _ = brdf.vndf.sample(s, params)
            theta_m, phi_m = u2theta(u_m[:, 0]), u2phi(u_m[:, 1])
            if brdf.isotropic:
                phi_m = phi_m + phi_i
            wm = spherical_to_vector(theta_m, phi_m)
            wi = np.repeat(spherical_to_vector(theta_i, phi_i)[None, :], s.shape[0], axis=0)
            wo = 2 * np.sum(wm * wi, axis=1, keepdims=True) * wm - wi
            up = wo[:, 2] > 1e-6
            counts["below_horizon"] += int((keep & ~up).sum())
            keep &= up
            wis.append(wi[keep])
            wos.append(normalize(wo[keep]))
    return np.concatenate(wis), np.concatenate(wos), counts


@dataclass(frozen=True)
class RglImportOptions:
    """``grid`` None = the file's measured directions, else grid axes in radians
    (:func:`brdfdata.formats.common.parse_grid`); ``sigma`` the assumed σ (the file has none);
    ``wavelengths_nm`` for spectral files: evaluate at these (default: the file's own)."""

    grid: dict[str, np.ndarray] | None = None
    sigma: SigmaRule = SigmaRule("rel", 0.02)
    wavelengths_nm: tuple[float, ...] | None = None


def import_rgl(path: str | os.PathLike, options: RglImportOptions | None = None) -> SampleTable:
    """An RGL file as a samples table (docs/design.md §4) with provenance metadata; values
    published below zero are data (flag ``Flags.NEGATIVE`` marks them for the record) and the
    "rel" σ rule's floor sizes them (:class:`SigmaRule`)."""
    options = options or RglImportOptions()
    if options.sigma.kind not in ("rel", "abs"):
        raise FormatError(f"{path}: an RGL file has no σ column; use --sigma rel=… or abs=…")
    brdf = load_rgl(path)
    if options.grid is None:
        wi, wo, dropped = measured_directions(brdf)
        where = "measured"
    else:
        g = grid_directions(options.grid)
        wi = spherical_to_vector(g["theta_i"], g["phi_i"])
        wo = spherical_to_vector(g["theta_o"], g["phi_o"])
        dropped, where = {}, "grid"
    channels, names = None, list(brdf.channels)
    if options.wavelengths_nm is not None:
        if not brdf.spectral:
            raise FormatError(f"{path}: --wavelengths needs a spectral file; this one is RGB")
        brdf.channel_params = np.asarray(options.wavelengths_nm, np.float64)
        names = [f"{w:g}nm" for w in options.wavelengths_nm]
        channels = list(range(len(names)))
    f = brdf.eval(wi, wo, channels)  # (N, C)
    theta_i, phi_i = vector_to_spherical(wi)
    theta_o, phi_o = vector_to_spherical(wo)
    n, c = f.shape
    values = f.T.ravel()  # channel-major: all of R, then G, then B
    flags = np.where(values < 0, Flags.NEGATIVE, 0).astype(np.int32)
    channel = np.repeat(np.asarray(names, dtype=object), n).astype(str)
    conversion = {
        "reader": "brdfdata.formats.rgl (own implementation of Dupuy & Jakob 2018)",
        "directions": where,
        "description": brdf.description,
        "value": "f_r = table·D/(4σ)/cos(theta_o), not clamped",
        "channels": names,
        "sigma": options.sigma.describe(),
        "nodes_left_out": dropped,
        "negative_flagged": int((values < 0).sum()),
    }
    if options.sigma.kind == "rel":
        conversion["sigma_floor"] = {c: options.sigma.floor(values[channel == c]) for c in names}
    meta = provenance(path, "rgl", conversion)
    meta["gonio.absolute"] = "true"
    return SampleTable(
        theta_i=np.tile(theta_i, c),
        phi_i=np.tile(phi_i, c),
        theta_o=np.tile(theta_o, c),
        phi_o=np.tile(phi_o, c),
        channel=channel,
        f=values,
        sigma=options.sigma.apply(values, channel),
        flags=flags,
        metadata=meta,
    )

"""Reference-target radiometric calibration: the light × camera scale from a target of known BRDF.

Instead of trusting the lamp's certified intensity *and* the camera's absolute responsivity (QE,
f-number, pixel pitch, gain), a lab images a reference target of known BRDF f_ref (a Lambertian
standard, or Spectralon with a calibrated f_ref(θ_i, θ_o) table — Spectralon departs from Lambert by
up to ~20 % at large angles, docs/design.md §7) at known poses. With the camera irradiance equation
as a *nominal* conversion (calibration.radiometry, L̃ = k_rad · Φ) each reference pixel gives the
effective source intensity

    k = L̃_ref / (f_ref(ω_i, ω_o) · cos θ_i / r²)                         [W sr⁻¹]

— the true intensity times the ratio of the camera's true to nominal responsivity. Used in place
of the certified intensity in f = L̃ / (k · cos θ_i / r²) this is exactly the reference-target
method f = f_ref · (S_s/t_s)/(S_ref/t_ref) · (E_ref/E_s) (docs/design.md §7; Nicodemus et al., NBS
Monograph 160, 1977, §4) with matched per-pixel geometry (calibration.geometry): every error
common to the reference and the sample captures (lamp intensity, QE, aperture, gain, the flat's
absolute scale) cancels.

Uncertainty: each reference pose gives k per channel with the standard error of its pixel mean
(the larger of the noise-model and the empirical value); poses combine by inverse-variance
weighting, inflated by the Birge ratio √(χ²/dof) when they disagree beyond their errors; the
certificate's own relative uncertainty (rig file `[reference] albedo_sigma` / `table_sigma`) is
added in quadrature. The relative σ_k/k is a *correlated* systematic of every sample of that
channel; the reduction adds it in quadrature to each sample's σ and also reports it in the
Parquet metadata.

Files (docs/design.md §4, next to the darks and flats of calibration.darks): raw frames under
``RUN/calibration/reference/``, listed in the manifest's calibration table with kind
"reference" and the pose (``axes_rad``, measured arm angles as for a measurement capture), the
bracket's exposure and the light monitor's reading; the target's description (what the rig
file's ``[reference]`` said; a table file is copied into the run, so the run stays
self-contained) with the take (acquisition.calibration_capture).

f_ref tables (CSV or TOML): one row per calibrated geometry, columns ``theta_i_deg``,
``theta_o_deg``, optionally ``delta_phi_deg`` (|φ_o − φ_i| folded to [0, 180]; without it the
table is taken to hold for every azimuth), and either ``f`` (grey) or ``f_R, f_G, f_B`` (sr⁻¹).
The rows must fill a regular grid; values are interpolated (multi-)linearly. A geometry outside
the table is an error, never an extrapolation. TOML: ``[[point]]`` tables with the same keys
(``f`` a number or a 3-list).
"""

from __future__ import annotations

import csv
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibration.darks import (
    CalibrationFrameError,
    calibration_frames,
    calibration_take_description,
)
from plumbing.atomic import atomic_write_bytes
from plumbing.inputs import MiB, check_input, open_input

__all__ = [
    "REFERENCE_KIND",
    "FRefTable",
    "ReferenceTarget",
    "ReferenceScale",
    "load_f_ref_table",
    "load_reference_target",
    "reference_entries",
    "pixel_scale",
    "combine_scales",
]

REFERENCE_KIND = "reference"


def _fold_delta_phi(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """|φ_o − φ_i| folded to [0, π] (an isotropic f_ref depends on nothing else in azimuth)."""
    d = np.arctan2(wo[..., 1], wo[..., 0]) - np.arctan2(wi[..., 1], wi[..., 0])
    return np.abs((d + np.pi) % (2.0 * np.pi) - np.pi)


@dataclass(frozen=True)
class FRefTable:
    """f_ref on a regular grid of (θ_i, θ_o[, Δφ]) in radians; values (..., 3) in sr⁻¹."""

    axes: tuple[np.ndarray, ...]
    values: np.ndarray

    def __call__(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """f_ref (N, 3) at unit directions wi, wo (N, 3) (sample frame, pointing away)."""
        from scipy.interpolate import RegularGridInterpolator

        wi = np.atleast_2d(wi)
        wo = np.atleast_2d(wo)
        pts = [np.arccos(np.clip(wi[:, 2], -1, 1)), np.arccos(np.clip(wo[:, 2], -1, 1))]
        if len(self.axes) == 3:
            pts.append(_fold_delta_phi(wi, wo))
        pts = np.stack(pts, axis=-1)
        # 1e-9 rad slack: a grid edge at exactly 0 or π must not reject its own boundary.
        lo = np.array([a[0] for a in self.axes]) - 1e-9
        hi = np.array([a[-1] for a in self.axes]) + 1e-9
        bad = np.any((pts < lo) | (pts > hi), axis=1)
        if bad.any():
            p = np.degrees(pts[np.argmax(bad)])
            rng = ", ".join(f"{np.degrees(a[0]):g}..{np.degrees(a[-1]):g}" for a in self.axes)
            raise CalibrationFrameError(
                f"reference geometry {np.round(p, 2).tolist()} deg is outside the f_ref table "
                f"({rng} deg): measure the reference inside its calibrated range"
            )
        pts = np.clip(pts, [a[0] for a in self.axes], [a[-1] for a in self.axes])
        interp = RegularGridInterpolator(self.axes, self.values, method="linear")
        return interp(pts)

    def to_rows(self) -> tuple[list[str], list[list[float]]]:
        names = ["theta_i_deg", "theta_o_deg", "delta_phi_deg"][: len(self.axes)]
        names += ["f_R", "f_G", "f_B"]
        grids = np.meshgrid(*self.axes, indexing="ij")
        flat = [np.degrees(g).ravel() for g in grids]
        vals = self.values.reshape(-1, 3)
        rows = [[*(float(c[k]) for c in flat), *map(float, vals[k])] for k in range(len(vals))]
        return names, rows

    def write_csv(self, path: str | Path) -> None:
        names, rows = self.to_rows()
        lines = [",".join(names)] + [",".join(f"{v:.10g}" for v in r) for r in rows]
        atomic_write_bytes(Path(path), ("\n".join(lines) + "\n").encode())


def _table_from_rows(rows: list[dict], source: str) -> FRefTable:
    if not rows:
        raise CalibrationFrameError(f"{source}: the f_ref table is empty")
    keys = set(rows[0])
    need = {"theta_i_deg", "theta_o_deg"}
    if not need <= keys:
        raise CalibrationFrameError(f"{source}: f_ref table needs columns theta_i_deg, theta_o_deg")
    has_phi = "delta_phi_deg" in keys
    if "f" in keys:

        def value(r):
            v = r["f"]
            v = v if isinstance(v, list | tuple) else [v, v, v]
            if len(v) != 3:
                raise ValueError("f must be one number or three")
            return [float(x) for x in v]
    elif {"f_R", "f_G", "f_B"} <= keys:

        def value(r):
            return [float(r["f_R"]), float(r["f_G"]), float(r["f_B"])]
    else:
        raise CalibrationFrameError(f"{source}: f_ref table needs a column f or f_R, f_G, f_B")
    cols = ["theta_i_deg", "theta_o_deg"] + (["delta_phi_deg"] if has_phi else [])
    try:
        coords = np.array([[float(r[c]) for c in cols] for r in rows])
        vals = np.array([value(r) for r in rows])
    except (TypeError, ValueError, KeyError) as exc:
        raise CalibrationFrameError(f"{source}: unreadable f_ref row ({exc})") from None
    if not np.all(np.isfinite(coords)) or not np.all(np.isfinite(vals)) or np.any(vals < 0):
        raise CalibrationFrameError(f"{source}: f_ref table has non-finite or negative values")
    axes = [np.unique(coords[:, k]) for k in range(coords.shape[1])]
    shape = tuple(len(a) for a in axes)
    if math.prod(shape) != len(rows) or any(n < 2 for n in shape):
        raise CalibrationFrameError(
            f"{source}: f_ref rows do not fill a regular grid of ≥ 2 values per angle "
            f"({len(rows)} rows for a {'×'.join(map(str, shape))} grid)"
        )
    grid = np.full((*shape, 3), np.nan)
    idx = tuple(np.searchsorted(a, coords[:, k]) for k, a in enumerate(axes))
    grid[idx] = vals
    if np.isnan(grid).any():
        raise CalibrationFrameError(f"{source}: f_ref rows repeat a geometry and miss another")
    return FRefTable(tuple(np.radians(a) for a in axes), grid)


def load_f_ref_table(path: str | Path) -> FRefTable:
    """Read a calibrated f_ref table (CSV with a header row, or TOML ``[[point]]``)."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".toml":
            with open_input(path, "f_ref table", 16 * MiB) as fh:
                rows = tomllib.load(fh).get("point", [])
        else:
            check_input(path, "f_ref table", 16 * MiB)
            with open(path, newline="") as fh:
                rows = [
                    {k.strip(): v for k, v in r.items()}
                    for r in csv.DictReader(line for line in fh if not line.startswith("#"))
                ]
    except (OSError, tomllib.TOMLDecodeError, csv.Error) as exc:
        raise CalibrationFrameError(f"{path}: cannot read the f_ref table ({exc})") from None
    return _table_from_rows(rows, str(path))


@dataclass(frozen=True)
class ReferenceTarget:
    """The reference target's BRDF: Lambertian f = ρ/π, or a calibrated table."""

    reflectance: tuple[float, float, float] | None = (0.99, 0.99, 0.99)
    table: FRefTable | None = None
    rel_sigma: float = 0.0  # the certificate's relative 1-σ (a systematic of the scale k)
    size_m: float | None = None  # side of the square target (None: the sample's)

    def f_ref(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """f_ref (N, 3) in sr⁻¹ at unit directions wi, wo (N, 3)."""
        if self.table is not None:
            return self.table(wi, wo)
        n = np.atleast_2d(wi).shape[0]
        return np.broadcast_to(np.asarray(self.reflectance) / np.pi, (n, 3)).copy()


def reference_entries(run_dir: str | Path) -> dict[int, list[dict]]:
    """The run's reference captures grouped by pose ({} if none were recorded)."""
    out: dict[int, list[dict]] = {}
    for e in calibration_frames(run_dir, REFERENCE_KIND):
        if "axes_rad" not in e or "pose" not in e:
            raise CalibrationFrameError(f"{e.get('path')}: reference entry without its pose")
        out.setdefault(int(e["pose"]), []).append(e)
    return out


def load_reference_target(run_dir: str | Path) -> ReferenceTarget:
    """The reference target recorded with the run's reference take: what the rig file's
    [reference] said (albedo or the f_ref table, copied into the run), and its certificate's
    relative uncertainty."""
    run_dir = Path(run_dir)
    d = calibration_take_description(run_dir, REFERENCE_KIND)
    where = f"{run_dir}: reference target"
    rel = float(d.get("rel_sigma", 0.0) or 0.0)
    size = float(d["size_m"]) if d.get("size_m") else None
    if d.get("type") == "lambertian":
        rho = d.get("reflectance")
        if not (isinstance(rho, list) and len(rho) == 3 and all(0 < float(r) <= 1 for r in rho)):
            raise CalibrationFrameError(f"{where}: reflectance must be 3 values in (0, 1]")
        return ReferenceTarget(reflectance=tuple(float(r) for r in rho), rel_sigma=rel, size_m=size)
    if d.get("type") == "table":
        rel_path = Path(str(d.get("file", "")))
        if rel_path.is_absolute() or ".." in rel_path.parts:
            raise CalibrationFrameError(f"{where}: table path {rel_path} is not inside the run")
        table = load_f_ref_table(run_dir / rel_path)
        return ReferenceTarget(reflectance=None, table=table, rel_sigma=rel, size_m=size)
    raise CalibrationFrameError(f"{where}: no description recorded (type lambertian or table)")


@dataclass
class ReferenceScale:
    """Effective source intensity per channel (W sr⁻¹ at monitor reading = commanded level)
    and its 1-σ, from the reference captures; ``per_pose`` keeps each pose's estimate."""

    channels: list[str]
    k: np.ndarray
    sigma: np.ndarray
    n_poses: int
    birge: np.ndarray
    per_pose: list[dict] = field(default_factory=list)

    def of(self, name: str) -> tuple[float, float]:
        j = self.channels.index(name)
        return float(self.k[j]), float(self.sigma[j])

    def describe(self) -> dict:
        return {
            "channels": self.channels,
            "k_W_sr": self.k.tolist(),
            "sigma_W_sr": self.sigma.tolist(),
            "rel_sigma": (self.sigma / self.k).tolist(),
            "n_poses": self.n_poses,
            "birge_ratio": self.birge.tolist(),
            "per_pose": self.per_pose,
        }


def pixel_scale(
    radiance: np.ndarray, var: np.ndarray, e_geom: np.ndarray, f_ref: np.ndarray
) -> tuple[float, float]:
    """k = mean over pixels of L̃/(f_ref · cos θ_i/r²) and its standard error.

    The standard error is the larger of the noise-model value √(Σ Var k_p)/N and the empirical
    std/√N (which also sees any pixel-to-pixel error the noise model lacks, e.g. residual PRNU).
    """
    kp = radiance / (e_geom * f_ref)
    var_kp = var / (e_geom * f_ref) ** 2
    ok = np.isfinite(kp) & np.isfinite(var_kp)
    kp, var_kp = kp[ok], var_kp[ok]
    n = kp.size
    if n < 2:
        raise CalibrationFrameError("a reference capture has fewer than 2 usable pixels")
    model = math.sqrt(float(var_kp.sum())) / n
    empirical = float(np.std(kp, ddof=1)) / math.sqrt(n)
    return float(kp.mean()), max(model, empirical)


def combine_scales(values: np.ndarray, sigmas: np.ndarray) -> tuple[float, float, float]:
    """Inverse-variance mean of per-pose k, its σ, and the Birge ratio √(χ²/dof) (≥ 1 applied):
    if the poses scatter more than their errors allow, something pose-dependent (f_ref table,
    geometry) is off, and the quoted σ must grow accordingly."""
    w = 1.0 / np.square(sigmas)
    mean = float(np.sum(w * values) / np.sum(w))
    sigma = math.sqrt(1.0 / float(np.sum(w)))
    birge = 1.0
    if len(values) > 1:
        chi2 = float(np.sum(w * np.square(values - mean)))
        birge = max(1.0, math.sqrt(chi2 / (len(values) - 1)))
    return mean, sigma * birge, birge

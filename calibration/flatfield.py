"""Flat-field correction: the per-pixel relative response (vignetting × PRNU) from flat frames.

The camera images a uniform radiance field (integrating sphere or diffuser; in the simulator
``SimCamera.capture_flat``) N times at one exposure; the frames are kept raw under
``RUN/calibration/flat/`` (see `calibration.darks` for the layout and `record_frames`). Then

    g(u, v) = ē(u, v) / ē₀,     ē = mean over frames of (DN − master dark) · K⁻¹   [electrons]

where ē₀ is the response *at the optical centre*, taken from a smooth fit ē ≈ Σ_k a_k ρ^k (ρ =
r²/f², k = 0..3) per colour channel, ē₀ = a₀. Fitting the whole image, rather than averaging a few
central pixels, keeps their PRNU out of the absolute scale (the fit averages the PRNU of every
pixel, ~σ_PRNU/√N_px). Natural vignetting E ∝ cos⁴α = (1 + ρ)⁻² (Horn, Robot Vision §10.2;
docs/design.md §7 "measure vignetting with a flat field rather than trusting cos⁴") is reproduced by
the cubic in ρ to ~4ρ³ (≤ 4·10⁻⁶ at ρ ≤ 0.01, an 11° half-diagonal). Normalising per colour channel
makes the flat independent of the source's colour; the camera irradiance equation keeps the absolute
scale on axis.

The correction divides a measured flux by g. g is itself measured with shot noise: its relative
variance per pixel, (ē + σ_d²)/(N ē²) with σ_d² the dark temporal variance in e², is added to each
sample's σ (it is a per-pixel fixed error, so it cannot average away across poses).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

import plumbing.numba_policy  # noqa: F401 — the vector width, chosen before a kernel here compiles
from calibration.darks import (
    CalibrationFrameError,
    DarkLibrary,
    calibration_frames,
    decoded_frames,
)

__all__ = ["FlatField", "master_flat", "load_flat", "colour_index"]


def colour_index(shape: tuple[int, ...], channels: str, cfa_pattern: str | None) -> np.ndarray:
    """Integer colour class per element of a frame's DN array (CFA: 0 R, 1 G, 2 B by site)."""
    if channels == "CFA":
        pattern = str(cfa_pattern).upper()
        lut = {"R": 0, "G": 1, "B": 2}
        tile = np.array([[lut[pattern[0]], lut[pattern[1]]], [lut[pattern[2]], lut[pattern[3]]]])
        h, w = shape
        return tile[np.arange(h)[:, None] % 2, np.arange(w)[None, :] % 2]
    if len(shape) == 3:
        return np.broadcast_to(np.arange(shape[2]), shape)
    return np.zeros(shape, dtype=int)


@dataclass(frozen=True)
class FlatField:
    gain: np.ndarray  # relative response per photosite/pixel (1 at the optical centre)
    rel_var: np.ndarray  # relative variance of `gain` per element (statistical)
    exposure_s: float
    n_frames: int

    def apply(self, flux: np.ndarray, var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Correct a flux map (same layout as the frames) and propagate the variance:
        Φ' = Φ/g,  Var Φ' = Var Φ / g² + Φ'² · Var g / g²."""
        out = flux / self.gain
        return out, var / self.gain**2 + out**2 * self.rel_var


@numba.njit(cache=True, nogil=True)
def _add_unsaturated(total, x, clip_dn):
    """total += x (in float64) in one pass; True if any value of x is at or above `clip_dn`."""
    saturated = False
    for k in range(total.shape[0]):
        v = np.float64(x[k])
        saturated |= v >= clip_dn
        total[k] += v
    return saturated


def _centre_value(e: np.ndarray, rho: np.ndarray) -> float:
    """a₀ of the least-squares cubic in ρ = r²/f² (the response on the optical axis)."""
    a = np.stack([np.ones_like(rho), rho, rho**2, rho**3], axis=-1)
    coef, *_ = np.linalg.lstsq(a, e, rcond=None)
    return float(coef[0])


def master_flat(
    frames: Iterable[np.ndarray],
    *,
    channels: str,
    cfa_pattern: str | None,
    exposure_s: float,
    darks: DarkLibrary | None,
    radiometry,
    intrinsics,
) -> FlatField:
    """Build the flat from raw DN frames (all at ``exposure_s``); `radiometry` (a
    calibration.radiometry.CameraRadiometry) gives the black and clip levels, the gain and
    the read noise."""
    black_level_dn, white_level_dn = radiometry.black_level_dn, radiometry.white_level_dn
    gain_e_per_dn, read_noise_e = radiometry.gain_e_per_dn, radiometry.read_noise_e
    # Summed one frame at a time: memory independent of the number of frames (see
    # calibration.darks._decode_all).
    total, n = None, 0
    for f in frames:
        x = np.asarray(f)
        if total is None:
            total = np.zeros(x.shape)
        if _add_unsaturated(total.reshape(-1), x.reshape(-1), white_level_dn - 0.5):
            raise CalibrationFrameError(
                "flat frames are saturated: lower the exposure or the source level"
            )
        n += 1
    if total is None:
        raise CalibrationFrameError("no flat frames")
    if darks is not None:
        dark = darks.for_exposure(exposure_s)
        base = dark.dn
        noise_var_e = gain_e_per_dn**2 * dark.temporal_var_dn2 * (1.0 + 1.0 / dark.n_frames)
    else:
        base = black_level_dn
        noise_var_e = read_noise_e**2 + gain_e_per_dn**2 / 12.0
    e = (total / n - base) * gain_e_per_dn
    if np.any(e <= 0):
        raise CalibrationFrameError("flat frames have pixels with no signal above dark")
    shape = e.shape
    vv, uu = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    rho = ((uu - intrinsics.cx) / intrinsics.fx) ** 2 + ((vv - intrinsics.cy) / intrinsics.fy) ** 2
    cls = colour_index(shape, channels, cfa_pattern)
    if e.ndim == 3:
        rho = np.broadcast_to(rho[..., None], shape)
    gain = np.empty_like(e)
    for c in np.unique(cls):
        m = cls == c
        gain[m] = e[m] / _centre_value(e[m], rho[m])
    rel_var = (e + noise_var_e) / (n * e**2)
    return FlatField(gain, rel_var, float(exposure_s), n)


def load_flat(
    run_dir: str | Path,
    darks: DarkLibrary | None,
    radiometry,
    intrinsics,
) -> FlatField | None:
    """The run's flat field from ``RUN/calibration/flat/`` frames; None if none were recorded."""

    run_dir = Path(run_dir)
    entries = calibration_frames(run_dir, "flat")
    if not entries:
        return None
    exposures = {float(e["exposure_s"]) for e in entries}
    if len(exposures) != 1:
        raise CalibrationFrameError(f"flat frames at several exposures {sorted(exposures)}")
    frames = decoded_frames(run_dir, entries)  # raises a one-line error on a bad frame
    first = next(frames)  # its layout (channels, mosaic) is every flat's
    return master_flat(
        itertools.chain([first.dn], (f.dn for f in frames)),
        channels=first.channels,
        cfa_pattern=first.cfa_pattern,
        exposure_s=exposures.pop(),
        darks=darks,
        radiometry=radiometry,
        intrinsics=intrinsics,
    )

"""The square regions a colour plane's samples are made of, summed in one pass.

A sample is a b × b region of a colour plane (calibration.reduce: ``ReduceOptions.bin_px``) whose
pixels are all on the sample: its value is the mean over the region of each pixel's
f = L̃/E = Φ·k/(I cos θ_i / r²) (the camera irradiance equation divided by the surface irradiance
at the pixel's own surface point), its variance the mean of the pixels' variances (divided by b²
for the σ of the mean, by the caller), its directions the mean of the pixels' ω_i and ω_o (the
caller normalises them), and its flags whether any pixel was saturated in every bracket or off
the segmented sample. `region_means` computes all of these for the on-sample regions only, one
pass over their pixels, summing each region's pixels row by row as the whole-plane numpy block
means it replaced did (the same values, bit for bit: tests/calibration/test_regions.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

import plumbing.numba_policy  # noqa: F401 — the vector width, chosen before a kernel here compiles
from calibration.planes import Plane, block_all

__all__ = ["RegionMeans", "region_means"]


@dataclass(frozen=True)
class RegionMeans:
    """Per on-sample region (row-major order of the regions): its row and column among the
    plane's regions, and the means of its pixels (see the module doc)."""

    rows: np.ndarray
    cols: np.ndarray
    f: np.ndarray
    var_f: np.ndarray
    wi: np.ndarray  # (n, 3), not normalised
    wo: np.ndarray
    point_m: np.ndarray
    saturated: np.ndarray  # bool: a pixel saturated in every bracket
    masked: np.ndarray  # bool: a pixel off the segmented sample


def region_means(
    plane: Plane, off_image: np.ndarray, b: int, scale: float, intensity: float
) -> RegionMeans | None:
    """The on-sample b × b regions of `plane` with their means:
    f = Φ·scale/(I cos θ_i/r²), `scale` the radiance per e⁻/s of one value of the plane,
    `intensity` I the light's (W/sr) for this channel. None when no region is on the sample."""
    geo = plane.geo
    on = block_all(geo.on_sample, b)
    rows, cols = np.nonzero(on)
    n = rows.size
    if n == 0:
        return None
    out = RegionMeans(
        rows, cols, np.empty(n), np.empty(n), np.empty((n, 3)), np.empty((n, 3)),
        np.empty((n, 3)), np.empty(n, bool), np.empty(n, bool),
    )  # fmt: skip
    pixels = (plane.flux, plane.var, plane.all_sat, off_image, geo.wi, geo.wo)
    means = (out.f, out.var_f, out.wi, out.wo, out.point_m, out.saturated, out.masked)
    where = (geo.light_distance_m, geo.point_m)
    _sum_regions(rows, cols, b, pixels, where, scale, intensity, means)
    return out


@numba.njit(cache=True, nogil=True)
def _sum_regions(rows, cols, b, pixels, where, scale, intensity, out):
    flux, var, sat, off, wi, wo = pixels
    dist, point = where
    f_mean, var_mean, wi_mean, wo_mean, p_mean, saturated, masked = out
    n_px = b * b
    for k in range(rows.shape[0]):
        f_sum = 0.0
        v_sum = 0.0
        sat_any = False
        off_any = False
        # the direction sums as scalars: three np.zeros(3) a region were heap allocations,
        # most of this kernel's time
        wi0 = wi1 = wi2 = wo0 = wo1 = wo2 = p0 = p1 = p2 = 0.0
        for i in range(b):
            y = rows[k] * b + i
            for j in range(b):
                x = cols[k] * b + j
                # E/I = cos θ_i / r² at the pixel's own surface point (radiometry.
                # surface_irradiance), then × I; f = Φ·scale/E, Var f = Var Φ·(scale/E)².
                e = 1.0 * max(wi[y, x, 2], 0.0) / (dist[y, x] * dist[y, x]) * intensity
                f_sum += flux[y, x] * scale / e
                r = scale / e
                v_sum += var[y, x] * (r * r)
                sat_any |= sat[y, x]
                off_any |= off[y, x]
                wi0 += wi[y, x, 0]
                wi1 += wi[y, x, 1]
                wi2 += wi[y, x, 2]
                wo0 += wo[y, x, 0]
                wo1 += wo[y, x, 1]
                wo2 += wo[y, x, 2]
                p0 += point[y, x, 0]
                p1 += point[y, x, 1]
                p2 += point[y, x, 2]
        f_mean[k] = f_sum / n_px
        var_mean[k] = v_sum / n_px
        saturated[k] = sat_any
        masked[k] = off_any
        wi_mean[k, 0], wi_mean[k, 1], wi_mean[k, 2] = wi0 / n_px, wi1 / n_px, wi2 / n_px
        wo_mean[k, 0], wo_mean[k, 1], wo_mean[k, 2] = wo0 / n_px, wo1 / n_px, wo2 / n_px
        p_mean[k, 0], p_mean[k, 1], p_mean[k, 2] = p0 / n_px, p1 / n_px, p2 / n_px

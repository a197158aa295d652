"""calibration.regions.region_means (the one-pass region sums a reduction bins with) against
the same means written as whole-plane numpy (the reduction's formulation before the kernel):
f = Φ·scale/(I cos θ_i/r²) and its variance per pixel, then b × b block means of those and of
ω_i, ω_o and the surface point, and any-saturated / any-masked per region, for the regions
whose pixels are all on the sample. Asserted bit for bit: both sum each region's pixels row
by row in the same IEEE operations."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.store import RunStore
from calibration.planes import block_all, pose_planes
from calibration.radiometry import surface_irradiance
from calibration.reduce import ReduceOptions, _captures_by_pose, _decode_pose, _run_calibration
from calibration.regions import region_means
from tests.support.small_runs import small_run


def _block_views(a: np.ndarray, b: int) -> list[np.ndarray]:
    """The b² strided views whose element (r, c) is element (i, j) of block (r, c), in the
    order the reduction summed them (row by row within a block)."""
    h, w = a.shape[0] // b * b, a.shape[1] // b * b
    return [a[i:h:b, j:w:b] for i in range(b) for j in range(b)]


def block_mean(a: np.ndarray, b: int) -> np.ndarray:
    total = _block_views(a, b)[0].astype(np.float64)
    for v in _block_views(a, b)[1:]:
        total += v
    return total / (b * b)


def block_any(a: np.ndarray, b: int) -> np.ndarray:
    return np.logical_or.reduce(_block_views(a, b))


@pytest.fixture(scope="module")
def planes(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("regions") / "run"
    small_run(out, "raw.toml", theta_i_deg=40.0, theta_o_deg=(30.0,))
    with RunStore.open(out) as store:
        cal, _rig = _run_calibration(store, out, ReduceOptions())
        recs = next(iter(_captures_by_pose(store, out).values()))
    good, decoded = _decode_pose(recs, out, [], False)
    exposures = [float(r.exposure_s) for r in good]
    return pose_planes(cal, decoded, exposures, good[0].axes_measured)


@pytest.mark.parametrize("b", [1, 2, 3])
def test_region_means_are_the_block_means_of_the_pixels(planes, b: int) -> None:
    plane_list, seg = planes
    scale, intensity = 3.7e-9, 0.8
    for pl in plane_list:
        off = ~seg
        reg = region_means(pl, off, b, scale, intensity)
        geo = pl.geo
        on = block_all(geo.on_sample, b)
        assert reg is not None and reg.f.size == on.sum() > 10
        e = surface_irradiance(1.0, geo.wi[..., 2], geo.light_distance_m) * intensity
        with np.errstate(divide="ignore", invalid="ignore"):
            f_px = pl.flux * scale / e
            var_px = pl.var * (scale / e) ** 2
        np.testing.assert_array_equal(np.column_stack(np.nonzero(on)), np.c_[reg.rows, reg.cols])
        np.testing.assert_array_equal(reg.f, block_mean(f_px, b)[on])
        np.testing.assert_array_equal(reg.var_f, block_mean(var_px, b)[on])
        np.testing.assert_array_equal(reg.wi, block_mean(geo.wi, b)[on])
        np.testing.assert_array_equal(reg.wo, block_mean(geo.wo, b)[on])
        np.testing.assert_array_equal(reg.point_m, block_mean(geo.point_m, b)[on])
        np.testing.assert_array_equal(reg.saturated, block_any(pl.all_sat, b)[on])
        np.testing.assert_array_equal(reg.masked, block_any(off, b)[on])

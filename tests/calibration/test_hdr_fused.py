"""The fused HDR merge the reduction runs (calibration.hdr.merge_frames_local, compiled) computes
the documented numpy merge (`merge_brackets_local`, whose bias and noise tests are
tests/calibration/test_hdr_bias.py) from the raw frames, on frames that exercise every branch: a
Bayer mosaic and an RGB image, per-pixel darks, a bright patch that saturates the long brackets and
one that saturates them all, pixels with no valid neighbour (some near the clip, so that the clip
test drops a bracket of theirs), an on-sample mask, and 1 to 4 brackets.

Tolerance: the kernel computes the same quantities with a different rounding order — the
neighbours' sum (scipy's running 3-tap sums × 9 − self in numpy, a direct sum of ≤ 8 values in
the kernel) and the weighted mean as one fraction (Σ tᵢsᵢPᵢ / Σ tᵢ²Pᵢ with Pᵢ the other
brackets' denominators, instead of 2B + 1 divisions) — each a few ulps (≤ 1e-15 relative) of
the flux and variance, so 1e-12 relative is 1000× the rounding. The bracket choice (a
comparison against the clip) is asserted identical: a flip would need a reference within 1e-15
of a threshold, which these seeded frames do not have.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.hdr import RawBrackets, merge_brackets_local, merge_frames_local
from simulator.render import world_to_camera_cv

GAIN_E_PER_DN = 2.0
WHITE_DN = 4095.0
EXPOSURES_S = [0.001, 0.004, 0.016]
READ_E = np.array([3.1, 3.3, 3.9])  # grows with exposure, as a dark's temporal noise does


def _frames(shape, rng, exposures_s=EXPOSURES_S, read_e=READ_E):
    """Raw brackets (B, *shape) of a flux field with a bright and a blinding patch, and their
    per-pixel darks."""
    h, w = shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    flux_e_s = 2e4 * (1.0 + 0.5 * np.sin(xx / 7.0) * np.cos(yy / 5.0))
    flux_e_s[10:20, 10:24] = 5e5  # saturates the 16 ms and 4 ms brackets
    flux_e_s[30:36, 40:50] = 5e7  # saturates all three
    # Off the sample's mask (the valid disc below) and near the 16 ms bracket's clip
    # (7840 e of 8062): values with no usable neighbour whose clip test drops that bracket
    flux_e_s[0:6, 0:8] = 4.9e5
    if len(shape) == 3:
        flux_e_s = flux_e_s[..., None] * np.array([0.7, 1.0, 1.3])
    dark_dn = 64.0 + rng.normal(0.0, 2.0, (len(exposures_s), *shape))
    dn = []
    for i, t in enumerate(exposures_s):
        electrons = rng.poisson(flux_e_s * t) + rng.normal(0.0, read_e[i], shape)
        dn.append(np.clip(np.round(dark_dn[i] + electrons / GAIN_E_PER_DN), 0, WHITE_DN))
    return np.array(dn, dtype=np.float32), dark_dn


# Three brackets (the camera-scale benchmark's), two (the plans' default) and one take the
# kernel's one-pass weighted mean; four take its general form.
BRACKET_SETS = {
    3: (EXPOSURES_S, READ_E),
    2: ([0.004, 0.016], np.array([3.3, 3.9])),
    1: ([0.016], np.array([3.9])),
    4: ([0.001, 0.004, 0.016, 0.03], np.array([3.1, 3.3, 3.9, 4.4])),
}


@pytest.mark.parametrize(
    "shape, cfa, n_brackets",
    [((48, 64), True, 3), ((40, 56, 3), False, 3), ((48, 64), True, 2), ((48, 64), True, 1)]
    + [((48, 64), True, 4), ((40, 56, 3), False, 4)],
)
def test_fused_merge_is_the_documented_merge(shape, cfa, n_brackets) -> None:
    exposures_s, read_e = BRACKET_SETS[n_brackets]
    rng = np.random.default_rng(7)
    dn, dark_dn = _frames(shape, rng, exposures_s, read_e)
    h, w = shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    valid = (yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (0.45 * w) ** 2
    valid[5, 5] = True  # an isolated valid pixel: no valid neighbour (the own-merge fallback)
    b = len(exposures_s)
    electrons = [(dn[i].astype(np.float64) - dark_dn[i]) * GAIN_E_PER_DN for i in range(b)]
    saturated = [dn[i] >= WHITE_DN - 0.5 for i in range(b)]
    clips = [(WHITE_DN - dark_dn[i]) * GAIN_E_PER_DN for i in range(b)]
    want = merge_brackets_local(
        electrons, exposures_s, saturated, read_e, clips, valid=valid, cfa=cfa
    )
    brackets = RawBrackets(dn, dark_dn, exposures_s, read_e, GAIN_E_PER_DN, WHITE_DN)
    got = merge_frames_local(brackets, valid=valid, cfa=cfa)
    assert want[2].any() and not want[2].all()  # the blinding patch is all-saturated
    np.testing.assert_array_equal(got[2], want[2])
    np.testing.assert_allclose(got[0], want[0], rtol=1e-12, atol=0)
    finite = np.isfinite(want[1])
    np.testing.assert_array_equal(np.isfinite(got[1]), finite)
    np.testing.assert_allclose(got[1][finite], want[1][finite], rtol=1e-12, atol=0)


def test_threads_do_not_change_the_merge_or_the_geometry() -> None:
    """The parallel twins (bands of rows on numba's threads) give the serial ones' results bit
    for bit:
    every value's arithmetic is its own, so only the speed may depend on the machine's load
    (the "auto" policy picks a twin by timing, plumbing.numba_policy.set_threading)."""
    from calibration.geometry import Intrinsics, pixel_geometry
    from plumbing.numba_policy import PARALLEL_MIN_WORK, set_threading

    rng = np.random.default_rng(11)
    # 84 480 values ≥ PARALLEL_MIN_WORK: threads are allowed; 330 rows are 5 whole bands of
    # 64 rows (calibration.hdr._BAND_ROWS) and a partial one
    shape = (330, 256)
    assert shape[0] * shape[1] >= PARALLEL_MIN_WORK
    dn, dark_dn = _frames(shape, rng)
    brackets = RawBrackets(dn, dark_dn, EXPOSURES_S, READ_E, GAIN_E_PER_DN, WHITE_DN)
    valid = rng.random(shape) < 0.9
    intr = Intrinsics(shape[1], shape[0], 900.0, 900.0, 127.5, 159.5)
    cam = np.array([0.1, 0.05, 0.45])

    def run() -> tuple:
        # a mosaic (neighbours 2 rows away) and a plain image (1 row): the threaded merge's
        # bands of rows recompute step 1 for that many rows beyond their ends
        merged = merge_frames_local(brackets, valid=valid, cfa=True)
        plain = merge_frames_local(brackets, valid=valid, cfa=False)
        # a camera looking at the centre (the simulator's pinhole): threaded against serial rays
        rot = world_to_camera_cv(cam)[0].T
        geo = pixel_geometry(intr, cam, np.array([-0.2, 0.0, 0.4]), 0.05, rotation=rot)
        return (*merged, *plain, geo.point_m, geo.wi, geo.wo, geo.light_distance_m, geo.on_sample)

    previous = set_threading("serial")
    try:
        serial = run()
        set_threading("parallel")
        threaded = run()
    finally:
        set_threading(previous)
    for a, b in zip(serial, threaded, strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_flat_divided_in_the_merge_is_the_flat_fields_own_division() -> None:
    """`flat=` divides the merged flux in the kernel's pass exactly as FlatField.apply does
    after it (the same IEEE operations: bit for bit)."""
    from calibration.flatfield import FlatField

    rng = np.random.default_rng(5)
    shape = (48, 64)
    dn, dark_dn = _frames(shape, rng)
    gain = rng.uniform(0.7, 1.1, shape)
    rel_var = rng.uniform(1e-6, 1e-4, shape)
    brackets = RawBrackets(dn, dark_dn, EXPOSURES_S, READ_E, GAIN_E_PER_DN, WHITE_DN)
    plain = merge_frames_local(brackets, cfa=True)
    want = FlatField(gain, rel_var, 0.01, 32).apply(plain[0], plain[1])
    got = merge_frames_local(brackets, cfa=True, flat=(gain, rel_var))
    assert not np.array_equal(got[0], plain[0])
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_array_equal(got[2], plain[2])


@pytest.mark.parametrize("n_brackets", [2, 3])
def test_the_one_pass_weighted_mean_is_the_general_one_bit_for_bit(n_brackets) -> None:
    """The merge's one-pass weighted mean (2 or 3 brackets) against its general form (any
    number of brackets, one operation per pass) on the values a row can hold: brackets kept and
    dropped in every combination, references that are negative, zero, huge, infinite or NaN,
    and an infinite read variance. Both compute the same IEEE operations in the same order, so
    the results are equal bit for bit (NaN where NaN)."""
    from calibration import hdr

    rng = np.random.default_rng(17)
    n = 4096
    s = rng.normal(500.0, 300.0, (n_brackets, n))
    ok = (rng.random((n_brackets, n)) < 0.7).astype(np.float64)
    ref = rng.uniform(-1e3, 1e6, n)
    ref[::7] = np.inf
    ref[3::11] = np.nan
    ref[5::13] = 0.0
    t = np.array([0.001, 0.004, 0.016])[:n_brackets]
    for var_read in (np.array([9.6, 10.9, 15.2])[:n_brackets], np.array([9.6, np.inf, 15.2])):
        var_read = var_read[:n_brackets]
        fused = (np.empty(n), np.empty(n))
        general = (np.empty(n), np.empty(n))
        hdr._row_weighted_fused(s, ok, t, var_read, ref, *fused)
        scratch = (np.empty((n_brackets, n)), np.empty(n), np.empty(n), np.empty(n), np.empty(n))
        hdr._row_weighted_general(s, ok, t, var_read, ref, scratch, *general)
        assert np.isnan(general[0]).any() and np.isfinite(general[0]).any()
        for a, b in zip(fused, general, strict=True):
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
            number = ~np.isnan(a)  # the same bits, the sign of zero included
            np.testing.assert_array_equal(a[number].view(np.int64), b[number].view(np.int64))

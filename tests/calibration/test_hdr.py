"""HDR merge (calibration.hdr.merge_brackets) against an independent electron-level simulation.

Electrons are drawn here with numpy (EMVA 1288: Poisson shot noise, full-well clipping, Gaussian
read noise), not with the simulator's sensor, for four exposures spanning five decades. The truth
is the flux Φ we drew from; the merge must be unbiased and its predicted σ must be the scatter.
"""

from __future__ import annotations

import numpy as np

from calibration.hdr import merge_brackets

FULL_WELL_E = 30000.0
READ_E = 3.0
EXPOSURES_S = list(10.0 ** np.linspace(0.0, -5.0, 4))  # 1 s … 10 µs: five decades
REPEATS = 4000


def _simulate(flux_e_s: np.ndarray, rng: np.random.Generator):
    electrons, saturated = [], []
    for t in EXPOSURES_S:
        mu = np.broadcast_to(flux_e_s[:, None] * t, (flux_e_s.size, REPEATS))
        e = np.minimum(rng.poisson(mu).astype(float), FULL_WELL_E)
        e = e + rng.normal(0.0, READ_E, e.shape)
        electrons.append(e)
        # A camera knows its clip level, not the true count: flag within 6σ_read of the well (read
        # noise is added after the well clips; at 4σ one clipped value in ~30 000 would pass as
        # valid and, with a long exposure's large weight, ruin that pixel).
        saturated.append(e >= FULL_WELL_E - 6 * READ_E)
    return electrons, saturated


def test_four_brackets_five_decades_unbiased_and_sigma_honest() -> None:
    rng = np.random.default_rng(20261123)
    flux = 10.0 ** np.linspace(1.0, 9.3, 84)  # e/s: from read-noise-limited to the last bracket
    electrons, saturated = _simulate(flux, rng)
    phi, var, all_sat = merge_brackets(electrons, EXPOSURES_S, saturated, READ_E)
    assert not all_sat.any()  # the shortest bracket never fills the well here
    mean = phi.mean(axis=1)
    emp_sd = phi.std(axis=1, ddof=1)
    pred_sd = np.sqrt(var.mean(axis=1))
    snr = flux / pred_sd
    sel = snr > 25
    assert sel.sum() > 60  # most of the range is above SNR 25
    # Bias ≤ 0.5%: the statistical error of the mean over 4000 repeats is ≤ (1/25)/√4000 =
    # 0.06%, so this tests the estimator (iterated weights, saturation handling), not luck.
    bias = np.abs(mean[sel] / flux[sel] - 1.0)
    assert bias.max() <= 0.005, (flux[sel][np.argmax(bias)], bias.max())
    # Predicted σ within 10% of the empirical σ: the sample std of 4000 draws has a relative
    # standard error of 1/√(2·4000) = 1.1%, so 10% is ~9 standard errors.
    ratio = pred_sd[sel] / emp_sd[sel]
    assert np.all(np.abs(ratio - 1.0) <= 0.10), (flux[sel][np.argmax(np.abs(ratio - 1))], ratio)


def test_saturated_brackets_get_no_weight() -> None:
    """A bracket clipped at the full well would bias the flux low if it were used."""
    rng = np.random.default_rng(1)
    flux = np.array([1e6])  # fills the 1 s and 0.0215 s brackets, not the shorter ones
    electrons, saturated = _simulate(flux, rng)
    phi, _, _ = merge_brackets(electrons, EXPOSURES_S, saturated, READ_E)
    assert abs(phi.mean() / flux[0] - 1.0) < 0.005
    # Ignoring the saturation flags must fail the same check (the test can fail).
    none = [np.zeros_like(s) for s in saturated]
    phi_bad, _, _ = merge_brackets(electrons, EXPOSURES_S, none, READ_E)
    assert abs(phi_bad.mean() / flux[0] - 1.0) > 0.05


def test_per_bracket_noise_matches_a_scalar() -> None:
    """The per-bracket noise form (used with dark frames) reduces to the scalar one."""
    rng = np.random.default_rng(2)
    electrons, saturated = _simulate(np.array([1e3, 1e5]), rng)
    a = merge_brackets(electrons, EXPOSURES_S, saturated, READ_E)
    b = merge_brackets(electrons, EXPOSURES_S, saturated, [READ_E] * 4)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])

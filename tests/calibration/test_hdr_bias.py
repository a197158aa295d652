"""No brightness-dependent bias in the HDR merge a reduction uses (calibration.hdr).

A known flux field (a ramp from read-noise-limited to 4× the long exposure's clip level) is
exposed by the simulator's EMVA 1288 sensor (simulator.sensor: Poisson shot noise, full well,
read noise, ADC rounding and clipping) for the coverage plan's brackets, 2 ms and 16 ms, and
merged by `merge_brackets_local`. The truth is the flux we exposed. Per brightness bin the mean
of z = (Φ̂ − Φ)/σ̂ must be 0 within what n independent unit-variance z's allow.

Why z and not (Φ̂ − Φ)/Φ: a σ-weighted fit sees Σ (Φ̂ − Φ)/σ̂²; if σ̂ were computed from the
pixel's own value it would be correlated with the noise and the fit biased even with an unbiased
Φ̂. z catches both: E[z] = 0 only if Φ̂ is unbiased and σ̂ does not depend on the pixel's own
noise. The merge's bracket choice and weights come from the neighbours, so given them the merged
flux is a constant-weight mean of unbiased bracket estimates and E[z] = 0 (ADC rounding of a
signal with ≥ 3 e⁻ read noise and 2 e⁻/DN biases it by ≪ 1e-6; a bracket is kept within 5σ of
the clip, so a clipped value slips through with probability ≤ 3e-7). The tolerance is therefore
purely statistical: 4.5 standard errors of the mean (sd/√n) per bin, ~1e-4 family-wise false
alarm for the 14 checks, deterministic with the fixed seed.

The same check on the plain own-value merge (weights, σ and saturation from the pixel's own
value — the merge before neighbours were used) must fail: near the clip the long exposure
survives only when it fluctuated low (z ≈ −0.2 there), and its own-value σ biases z everywhere.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.hdr import merge_brackets, merge_brackets_local
from simulator.scene import SensorSpec
from simulator.sensor import Sensor, expected_electrons

SPEC = SensorSpec()  # EMVA defaults = the demo scene's sensor: 30 ke⁻ well, 3 e⁻ read, 2 e⁻/DN
F_NUMBER = 4.0
EXPOSURES_S = [0.002, 0.016]  # the coverage plan's brackets (ratio 8)
REPEATS = 96
ROWS = 64
# Camera clip level as the simulated camera reports it (simulator.camera.SimCamera): 6σ_read
# below the full well, because read noise is added after the well clips.
CLIP_DN = math.floor(
    SPEC.black_level_dn + (SPEC.full_well_e - 6 * SPEC.read_noise_e) / SPEC.gain_e_per_dn
)
CLIP_E = (CLIP_DN - SPEC.black_level_dn) * SPEC.gain_e_per_dn
# Signal-independent noise per bracket: read noise and ADC rounding (uniform, step K).
READ_E = math.sqrt(SPEC.read_noise_e**2 + SPEC.gain_e_per_dn**2 / 12.0)
# Bins of the long exposure's expected signal / clip level; dense around the clip (1.0).
EDGES = [0.01, 0.1, 0.3, 0.6, 0.85, 0.95, 0.98, 1.0, 1.02, 1.05, 1.15, 1.5, 2.5, 4.0]


def _ramp() -> np.ndarray:
    """Long-exposure signal / clip per column: log 0.01→0.8, linear 0.8→1.25 (0.35 % per column
    across the clip, so each neighbourhood is locally linear and its mean is the pixel's flux),
    log 1.25→4."""
    return np.concatenate(
        [
            np.geomspace(0.01, 0.8, 96, endpoint=False),
            np.linspace(0.8, 1.25, 128, endpoint=False),
            np.geomspace(1.25, 4.0, 32),
        ]
    )


def _z_by_bin(
    merge, spec: SensorSpec = SPEC
) -> tuple[list[tuple[float, float, int]], tuple[float, float, int]]:
    """(mean z, its standard error, n) per brightness bin and pooled, for a merge function."""
    level = _ramp()
    e_per_radiance = float(expected_electrons(1.0, 1.0, spec, F_NUMBER))  # e⁻/s per W m⁻² sr⁻¹
    flux = np.broadcast_to(level * CLIP_E / EXPOSURES_S[-1], (ROWS, level.size))
    radiance = np.repeat((flux / e_per_radiance)[..., None], 3, axis=-1)
    truth = expected_electrons(radiance, 1.0, spec, F_NUMBER)  # e⁻/s, independent of the merge
    sensor = Sensor(spec, F_NUMBER, rng=np.random.default_rng(20261123))
    level_map = np.broadcast_to(level[None, :], (ROWS, level.size))
    if truth.ndim == 3:  # one value per colour channel; a mosaic has one per photosite
        level_map = level_map[..., None]
    bins = np.digitize(np.broadcast_to(level_map, truth.shape), EDGES) - 1
    zs = []
    for _ in range(REPEATS):
        dns = [sensor.capture(radiance, t).astype(np.float64) for t in EXPOSURES_S]
        electrons = [(dn - SPEC.black_level_dn) * SPEC.gain_e_per_dn for dn in dns]
        saturated = [dn >= CLIP_DN - 0.5 for dn in dns]
        phi, var, all_sat = merge(electrons, saturated, spec.bayer is not None)
        assert not all_sat.any()  # the short bracket never clips on this ramp
        zs.append((phi - truth) / np.sqrt(var))
    z = np.stack(zs)
    per_bin = []
    for b in range(len(EDGES) - 1):
        zb = z[:, bins == b]
        per_bin.append((float(zb.mean()), float(zb.std() / math.sqrt(zb.size)), int(zb.size)))
    return per_bin, (float(z.mean()), float(z.std() / math.sqrt(z.size)), int(z.size))


def _local(electrons, saturated, cfa):
    return merge_brackets_local(electrons, EXPOSURES_S, saturated, [READ_E] * 2, CLIP_E, cfa=cfa)


def _own_value(electrons, saturated, cfa):
    return merge_brackets(electrons, EXPOSURES_S, saturated, [READ_E] * 2)


def _failures(per_bin, pooled) -> list[str]:
    bad = [
        f"bin {EDGES[b]}–{EDGES[b + 1]} of clip: mean z {m:+.4f} ± {se:.4f} (n={n})"
        for b, (m, se, n) in enumerate(per_bin)
        if abs(m) > 4.5 * se
    ]
    m, se, n = pooled
    if abs(m) > 4.5 * se:
        bad.append(f"pooled: mean z {m:+.4f} ± {se:.4f} (n={n})")
    return bad


@pytest.mark.parametrize("bayer", [None, "RGGB"], ids=["rgb", "mosaic"])
def test_merged_flux_has_no_brightness_dependent_bias(bayer) -> None:
    """A 3-channel sensor, and an RGGB mosaic (neighbours are the same-colour photosites)."""
    per_bin, pooled = _z_by_bin(_local, SPEC.model_copy(update={"bayer": bayer}))
    # Every bin is populated enough to resolve a bias of ~0.03σ (a few × 1e-4 relative).
    assert min(n for _, _, n in per_bin) >= 20000
    assert pooled[1] < 0.0015
    assert _failures(per_bin, pooled) == []


def test_own_value_merge_fails_the_same_check() -> None:
    """The check has the power to see the bias it is about: bracket choice from the pixel's own
    value fails it next to the clip level, and an own-value σ (correlated with the noise) fails
    the pooled mean (z ≈ −0.01 there, ~20 standard errors)."""
    per_bin, pooled = _z_by_bin(_own_value)
    bad = _failures(per_bin, pooled)
    assert any("0.98–1.0 of clip" in b for b in bad), bad
    assert any("pooled" in b for b in bad), bad

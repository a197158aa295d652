"""EMVA 1288 sensor model: statistics, stage instrumentation and the effect of each stage.

The expected photon counts are computed here from SI constants (scipy.constants), independently
of simulator.sensor's own arithmetic.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import constants

from simulator.scene import SensorSpec
from simulator.sensor import Sensor, bayer_select, expected_dn

F_NUMBER = 4.0
EXPOSURE_S = 0.01


def _photons(L, spec, exposure_s=EXPOSURE_S, f_number=F_NUMBER):
    """Φ = L·π/(4N²) · pitch² · t / (h c / λ) — camera irradiance equation + photon energy."""
    e_irr = L * np.pi / (4 * f_number**2)
    return (
        e_irr * spec.pixel_pitch_m**2 * exposure_s * spec.wavelength_m / (constants.h * constants.c)
    )


def _radiance_for_electrons(mu_e, spec):
    return mu_e / (spec.quantum_efficiency * _photons(1.0, spec))


@pytest.mark.parametrize("mu_e", [150.0, 3000.0, 20000.0])
def test_emva_mean_and_variance(mu_e):
    spec = SensorSpec(read_noise_e=4.0, gain_e_per_dn=2.5, black_level_dn=100, full_well_e=60000)
    sensor = Sensor(spec, F_NUMBER, rng=np.random.default_rng(7))
    L = np.full((64, 64, 3), _radiance_for_electrons(mu_e, spec))
    frames = np.stack([sensor.capture(L, EXPOSURE_S).astype(float) for _ in range(20)])
    qe_phot = spec.quantum_efficiency * _photons(L[0, 0, 0], spec)
    mean_expect = spec.black_level_dn + qe_phot / spec.gain_e_per_dn
    # EMVA 1288 eq. (7)-(9): σ²_y = (μ_e + σ_read²)/K⁻² + 1/12 (quantisation).
    var_expect = (qe_phot + spec.read_noise_e**2) / spec.gain_e_per_dn**2 + 1 / 12
    # Means: standard error ≈ σ/√(20·64²·3) ≤ 0.02 % of the signal — 0.5 % is a loose bound.
    signal = frames.mean() - spec.black_level_dn
    assert abs(signal / (mean_expect - spec.black_level_dn) - 1) < 5e-3
    # Temporal variance per pixel (ddof=1) averaged over 12288 pixels: relative standard error
    # ≈ √(2/19/12288) ≈ 0.3 %; the 5 % bound has a wide margin.
    var = frames.var(axis=0, ddof=1).mean()
    assert abs(var / var_expect - 1) < 0.05


def test_noise_free_output_and_expected_dn():
    spec = SensorSpec(noise=False, black_level_dn=64, gain_e_per_dn=2.0)
    s = Sensor(spec, F_NUMBER, rng=1)
    rng = np.random.default_rng(3)
    L = rng.uniform(0, _radiance_for_electrons(25000, spec), (16, 20, 3))
    dn = s.capture(L, EXPOSURE_S)
    e = spec.quantum_efficiency * _photons(L, spec)
    truth = np.clip(np.rint(64 + np.minimum(e, spec.full_well_e) / 2.0), 0, 2**14 - 1)
    np.testing.assert_array_equal(dn, truth)
    np.testing.assert_allclose(expected_dn(L, EXPOSURE_S, spec, F_NUMBER), dn, atol=0.5)


class _SpyRng:
    """A Generator stand-in that fails the test if any random stage draws from it."""

    def poisson(self, *a, **k):
        raise AssertionError("shot noise ran although disabled")

    def normal(self, *a, **k):
        raise AssertionError("a Gaussian stage (read noise / PRNU / DSNU) ran although disabled")


def test_disabled_stages_never_run():
    spec = SensorSpec(noise=False, prnu=0.0, dsnu_e=0.0, dark_current_e_s=0.0)
    s = Sensor(spec, F_NUMBER, rng=_SpyRng())
    s.capture(np.ones((8, 8, 3)), EXPOSURE_S)
    assert s.executed_stages == ["irradiance", "photons", "full_well", "adc"]
    assert s.executed_stages == s.enabled_stages()
    for st in ("vignetting", "bayer", "prnu", "dark_current", "dsnu", "shot_noise", "read_noise"):
        assert s.stage_counts[st] == 0


def test_each_enabled_stage_changes_output_only_as_expected():
    base = dict(noise=False, black_level_dn=0, gain_e_per_dn=1.0, full_well_e=1e9, adc_bits=16)
    L = np.full((24, 32, 3), _radiance_for_electrons(20000, SensorSpec()))
    ref = Sensor(SensorSpec(**base), F_NUMBER, rng=0).capture(L, EXPOSURE_S).astype(float)

    # Vignetting: ratio = cos⁴α of each pixel's chief ray, α from the pinhole intrinsics.
    k = {"fx": 40.0, "fy": 40.0, "cx": 15.5, "cy": 11.5}
    s = Sensor(SensorSpec(vignetting=True, **base), F_NUMBER, rng=0, intrinsics=k)
    vig = s.capture(L, EXPOSURE_S).astype(float)
    assert "vignetting" in s.executed_stages
    uu, vv = np.meshgrid(np.arange(32), np.arange(24))
    cos_a = 40.0 / np.sqrt((uu - 15.5) ** 2 + (vv - 11.5) ** 2 + 40.0**2)
    # ±0.5 DN rounding on ~20000 DN → relative 2.5e-5.
    np.testing.assert_allclose(
        vig / ref, np.broadcast_to((cos_a**4)[..., None], vig.shape), atol=1e-4
    )

    # PRNU: spatial relative std of the gain ≈ prnu (2304 samples: ±3 % relative error).
    s = Sensor(SensorSpec(prnu=0.01, **base), F_NUMBER, rng=0)
    pr = s.capture(L, EXPOSURE_S).astype(float)
    assert abs((pr / ref).std() / 0.01 - 1) < 0.1
    assert abs((pr / ref).mean() - 1) < 1e-3

    # Dark current: a uniform offset dark·t electrons = DN at gain 1.
    s = Sensor(SensorSpec(dark_current_e_s=500.0, **base), F_NUMBER, rng=0)
    dk = s.capture(L, EXPOSURE_S).astype(float)
    np.testing.assert_allclose(dk - ref, 5.0, atol=1.0)  # 500 e/s · 0.01 s, ±1 from rounding

    # Bayer: mosaic = channel select of the 3-channel image (noise off → identical numbers).
    L3 = L * np.array([1.0, 0.5, 0.25])
    full = Sensor(SensorSpec(**base), F_NUMBER, rng=0).capture(L3, EXPOSURE_S)
    mos = Sensor(SensorSpec(bayer="RGGB", **base), F_NUMBER, rng=0).capture(L3, EXPOSURE_S)
    assert mos.shape == (24, 32)
    np.testing.assert_array_equal(mos[0::2, 0::2], full[0::2, 0::2, 0])
    np.testing.assert_array_equal(mos[0::2, 1::2], full[0::2, 1::2, 1])
    np.testing.assert_array_equal(mos[1::2, 0::2], full[1::2, 0::2, 1])
    np.testing.assert_array_equal(mos[1::2, 1::2], full[1::2, 1::2, 2])
    np.testing.assert_array_equal(bayer_select(full), mos)


def test_full_well_and_adc_clip():
    spec = SensorSpec(noise=False, full_well_e=1000, gain_e_per_dn=1.0, black_level_dn=10)
    s = Sensor(spec, F_NUMBER, rng=0)
    dn = s.capture(np.full((4, 4, 3), _radiance_for_electrons(5000, spec)), EXPOSURE_S)
    assert np.all(dn == 1010)
    spec = SensorSpec(noise=False, full_well_e=1e6, gain_e_per_dn=1.0, adc_bits=12)
    dn = Sensor(spec, F_NUMBER, rng=0).capture(
        np.full((4, 4, 3), _radiance_for_electrons(5e5, spec)), EXPOSURE_S
    )
    assert np.all(dn == 4095)


def test_seeded_and_deterministic():
    spec = SensorSpec(prnu=0.01, dsnu_e=2.0, dark_current_e_s=10.0)
    L = np.full((16, 16, 3), _radiance_for_electrons(1000, spec))
    a = Sensor(spec, F_NUMBER, rng=42).capture(L, EXPOSURE_S)
    b = Sensor(spec, F_NUMBER, rng=42).capture(L, EXPOSURE_S)
    c = Sensor(spec, F_NUMBER, rng=43).capture(L, EXPOSURE_S)
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)

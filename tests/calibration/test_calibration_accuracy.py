"""BRDF accuracy of the whole calibration chain on a RAW camera with every sensor effect on.

A simulated acquisition (configs/scenes/raw.toml: DNG, RGGB Bayer, shot + read noise, dark
current + DSNU, PRNU 0.5%, cos⁴ vignetting) is reduced with master darks and a flat field, and
every sample is compared with the truth at its own (ω_i, ω_o): Mitsuba's own BSDF of the
rendered material (simulator.render.Renderer.truth_bsdf, f_r per channel) — independent of the
calibration code under test (decode, darks, flat, HDR merge, irradiance equation, geometry).
"""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from acquisition.config import PlanConfig, load_rig
from acquisition.operator import AutoOperator
from brdfdata.directions import spherical_to_vector
from brdfdata.samples import Flags
from calibration.darks import calibration_frames
from calibration.reduce import ReduceOptions, reduce_run
from gonio.pipeline import AcquireSpec, acquire
from simulator.render import Renderer
from simulator.scene import load_scene, world_scene
from tests.support.paths import REPO

SCENE = REPO / "configs" / "scenes" / "raw.toml"
RIG = REPO / "configs" / "rigs" / "sim.toml"


def _world():
    """The emulated world the run renders: the scene completed by the rig file's description."""
    return world_scene(load_scene(SCENE), load_rig(RIG))


EXPOSURES_S = [0.002, 0.016]
FLAT_EXPOSURE_S = 0.016


@pytest.fixture(scope="module")
def raw_run(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("raw") / "run"
    plan = PlanConfig.model_validate(
        {
            "name": "accuracy",
            "type": "isotropic",
            "theta_i_deg": [30.0, 55.0],
            "theta_o_deg": [0.0, 20.0, 40.0, 60.0],
            "delta_phi_deg": [180.0, 120.0, 60.0],
            "exposures_s": EXPOSURES_S,
            "order": "nearest",
            # Master darks per exposure and a flat at the longest, taken as the run's first
            # phases with the same (simulated) camera body, as a lab shoots them.
            "calibration": {"dark": {}, "flat": {}},
        }
    )
    res = acquire(
        out, AcquireSpec(rig=RIG, scene=SCENE, progress=False, plan=plan, operator=AutoOperator())
    )
    assert res.outcome.complete
    assert {e["exposure_s"] for e in calibration_frames(out, "dark")} == set(EXPOSURES_S)
    assert {e["exposure_s"] for e in calibration_frames(out, "flat")} == {FLAT_EXPOSURE_S}
    renderer = Renderer(_world())
    return out, renderer


def _truth(table, renderer: Renderer) -> np.ndarray:
    wi = spherical_to_vector(table.theta_i, table.phi_i)
    wo = spherical_to_vector(table.theta_o, table.phi_o)
    f = renderer.truth_bsdf(wi, wo)
    idx = np.array([{"R": 0, "G": 1, "B": 2}[c] for c in table.channel.astype(str)])
    return f[np.arange(len(idx)), idx]


def test_raw_bayer_vignetted_noisy_run_recovers_mitsuba_brdf(raw_run) -> None:
    run, renderer = raw_run
    # "center": one superpixel per 2×2 region with its own exact directions (no averaging bias).
    table = reduce_run(run, ReduceOptions(bin_px=2, mode="center"))
    good = (table.flags & Flags.SATURATED) == 0
    snr = table.f / table.sigma
    sel = good & (snr > 50)
    assert sel.sum() > 3000  # enough samples for the statistics below to mean something
    assert set(table.channel[sel].astype(str)) == {"R", "G", "B"}
    truth = _truth(table, renderer)[sel]
    f, sigma = table.f[sel], table.sigma[sel]
    rel = np.abs(f / truth - 1.0)
    # SNR > 50 means σ/f < 2%, so the median |error| (≈ 0.67σ for Gaussian errors) is < 1.4%
    # when σ is honest; 2% allows no systematic error of the size of vignetting (cos⁴ at the
    # corner is 2%) or PRNU.
    assert np.median(rel) <= 0.02
    z = (f - truth) / sigma
    # σ honest: unit-variance residuals. With N > 3000 the sample std has a standard error
    # ≈ 1/√(2N) < 1.3%, so [0.8, 1.25] only fails for a wrong noise model, and a mean
    # beyond ±0.1 (≈ 6 standard errors 1/√N) is a systematic bias of ≥ 0.1σ.
    assert 0.8 <= np.std(z) <= 1.25, np.std(z)
    assert abs(np.mean(z)) <= 0.1, np.mean(z)


def test_without_flat_and_darks_the_vignetting_shows(raw_run, tmp_path) -> None:
    """The same run with the calibration frames removed is biased: the check can fail."""
    import shutil

    run, renderer = raw_run
    bare = tmp_path / "bare"
    shutil.copytree(run, bare, ignore=shutil.ignore_patterns("calibration"))
    # The same run as if its plan had no calibration phases: their rows leave the manifest.
    with sqlite3.connect(bare / "manifest.sqlite") as db:
        db.execute("DELETE FROM calibration_captures")
        db.execute("DELETE FROM calibration_takes")
    table = reduce_run(bare, ReduceOptions(bin_px=2, mode="center"), out=tmp_path / "s.parquet")
    sel = ((table.flags & Flags.SATURATED) == 0) & (table.f / table.sigma > 50)
    z = (table.f[sel] - _truth(table, renderer)[sel]) / table.sigma[sel]
    # cos⁴ darkens the sample's pixels by 0.1-0.6% (ρ ≤ 0.003 here): a bias of a fraction of σ
    # at SNR 50-200, which the acceptance criteria above (|mean z| ≤ 0.1) must catch.
    assert not (abs(np.mean(z)) <= 0.1 and 0.8 <= np.std(z) <= 1.25), (np.mean(z), np.std(z))


def test_master_darks_match_the_sensor_spec(raw_run) -> None:
    """Master dark − black = the mean dark electrons, and the temporal variance is
    (σ_read² + μ_dark)/K² + 1/12 (Poisson + read + quantisation): EMVA 1288 with the scene's own
    numbers. DSNU is an offset of either sign (simulator.sensor), so over the pixels it averages
    to 0 and the mean is the dark current's, μ_dark = dark·t, which alone is Poisson."""
    from calibration.darks import load_darks

    run, _ = raw_run
    s = _world().sensor
    darks = load_darks(run)
    assert sorted(darks.masters) == EXPOSURES_S
    for t, m in darks.masters.items():
        mu = s.dark_current_e_s * t
        mean_expect = mu
        mean_e = (m.dn.mean() - s.black_level_dn) * s.gain_e_per_dn
        # Mean over 4096 pixels of a 16-frame mean: DSNU (5 e) averages to 5/64 ≈ 0.08 e,
        # temporal noise to ≈ 0.02 e; allow 0.4 e.
        assert abs(mean_e - mean_expect) < 0.4, (t, mean_e, mean_expect)
        expect = (s.read_noise_e**2 + mean_expect) / s.gain_e_per_dn**2 + 1 / 12
        # Pixel-averaged unbiased variance from 16 frames: relative error ≈ √(2/15/4096) ≈ 0.6%.
        assert abs(m.temporal_var_dn2 / expect - 1.0) < 0.05, (t, m.temporal_var_dn2, expect)


def test_flat_field_is_cos4_times_prnu(raw_run) -> None:
    """The measured flat divided by the sensor model's own cos⁴ (simulator.sensor) leaves only
    the PRNU: mean 1, scatter ≈ the scene's PRNU σ (plus the flat's shot noise)."""
    from acquisition.store import RunStore
    from calibration.darks import load_darks
    from calibration.flatfield import load_flat
    from calibration.geometry import Intrinsics
    from calibration.radiometry import CameraRadiometry
    from simulator.sensor import cos4_vignetting

    run, renderer = raw_run
    cam = RunStore.open(run).run_config()["camera"]
    flat = load_flat(
        run,
        load_darks(run),
        CameraRadiometry.from_description(cam),
        Intrinsics.from_description(cam),
    )
    ratio = flat.gain / cos4_vignetting(flat.gain.shape, renderer.intrinsics)
    prnu = _world().sensor.prnu
    shot = float(np.sqrt(np.mean(flat.rel_var)))
    # Mean of 4096 PRNU draws: ±0.005/64 ≈ 8e-5; allow 5e-4.
    assert abs(ratio.mean() - 1.0) < 5e-4
    expected_sd = np.hypot(prnu, shot)
    assert abs(ratio.std() / expected_sd - 1.0) < 0.1, (ratio.std(), expected_sd)
    # And the vignetting is really there to be removed (corner cos⁴ ≈ 0.98).
    assert flat.gain.min() < 0.985

"""Calibrated uncertainty on simulated data (issue #7): over 60 repeats with independent sensor
noise — Mitsuba renders, the EMVA sensor, the real calibration chain, then the MCMC fit — the
reported 68% interval covers the scene's truth in 55–80% of repeats and the 95% interval in at
least 88%, for every parameter. The test prints the coverage.

Each repeat runs in a fresh interpreter (a spawn pool of two, one per core): a repeat is then
a function of its seed alone. Run in the same process after the rest of the suite, the same
seeds gave other noise realisations (cause not found; every realisation is equally valid, but
a test's outcome should not depend on which tests ran before it).

Issue 43 item 4 asked for the cause of this test's error/half-width sd of 1.07–1.08 (above 1:
intervals too narrow). Over 256 repeats of this test's repeat (2026-12-07) the sd read ks 1.24,
m 1.06 — all of it three runs (of 256; two among these 60) whose ks and m were 4–8 half-widths
off: runs where noise alone passed calibration's 3σ test for the camera's bend, so calibration
"corrected" a straight camera by 0.25 % at the clip and no interval knew. The fit now carries the
bend calibration leaves in (fitting.nuisance, ``linearity_pct``): over the same 256 repeats the
largest |error/half-width| is 3.6, the sd kd 0.87, ks 0.86, m 0.94, and 68 % / 95 % coverage
kd 0.76 / 0.97, ks 0.76 / 0.98, m 0.74 / 0.94 (a little wide: the bend's prior σ is there in a
world without a bend). These 60: kd 0.75 / 0.97, ks 0.78 / 0.95, m 0.68 / 0.92 (sd 0.95, 1.01,
1.09: an sd over 60 repeats has a sampling sd of 0.09).

Stop 58 (2026-12-07, the Zen 3 machine CI runs on, where these 60 read ks 0.82 / 0.98, sd 0.79,
and failed): two mends. Each sample's bend level was read from its own flux, so it carried the
sample's noise and the fit found a bend in noise alone (calibration.reduce._region_level); and the
bend's prior was centred on 0 where calibration left β̂ in (fitting.nuisance). Over the same 256
repeats: 68 % / 95 % coverage kd 0.71 / 0.96, ks 0.69 / 0.93, m 0.74 / 0.98, error/half-width
mean +0.05, −0.04, −0.05 and sd 0.94, 1.02, 0.89, largest |error/half-width| 3.0. These 60 on
that machine: kd 0.68 / 0.90, ks 0.68 / 0.95, m 0.70 / 0.95 (mean −0.11, −0.12, −0.04; sd 1.07,
0.97, 0.94); with the level mended and the prior still centred on 0, ks read 0.80 / 0.98, sd
0.79."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

from acquisition.config import PlanConfig, load_rig
from calibration.reduce import ReduceOptions, reduce_run
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions
from gonio.pipeline import AcquireSpec, acquire
from simulator.scene import load_scene
from simulator.truth import reference_parameters
from tests.support.paths import REPO
from tests.support.repeats import repeat_map, repeat_pool

# Scheduled first (tests/conftest.py: the longest files start first, so both workers end together).
pytestmark = pytest.mark.heavy(151)

# 60, not 30: at 30 repeats the binomial sd of a 68 % coverage is 0.085, so even perfectly
# calibrated intervals fall outside the bands below for some parameter about one run in four;
# at 60 the sd is 0.060 (0.028 for the 95 % interval) and the same bands test something.
REPEATS = 60
PLAN = PlanConfig(
    name="coverage",
    theta_i_deg=(25.0, 50.0),
    theta_o_deg=(0.0, 20.0, 40.0, 60.0),
    delta_phi_deg=(180.0, 120.0),
    exposures_s=(0.002, 0.016),
)


def _one_repeat(k: int) -> dict[str, tuple[bool, bool]]:
    """Acquire, calibrate and fit repeat `k`; per parameter, (truth in 68 %, truth in 95 %)."""
    base = load_scene(REPO / "configs" / "scenes" / "demo.toml")
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    truth = reference_parameters(base)
    scene = base.model_copy(update={"seed": 1000 + k})  # independent noise per repeat
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        acquire(run, AcquireSpec(rig=rig, plan=PLAN, scene=scene, progress=False, announce=False))
        table = reduce_run(run, ReduceOptions(bin_px=2, mode="center"))
    # 600 steps: the fits' convergence verdict asks for more (R̂ ≈ 1.02–1.04), but 3000 steps
    # gave the same coverage to within one repeat in 90 — the intervals are settled by then.
    fit = fit_samples(
        table,
        FitOptions(
            model="torrance-sparrow",
            model_options={"fresnel": "none", "shadowing": "smith-rational"},
            channels=["G"],
            mcmc=McmcOptions(walkers=24, max_steps=600),
            seed=k,
            n_starts=2,
        ),
    ).to_dict()
    out = {}
    for name, p in fit["parameters"].items():
        t = truth.get(name)
        if t is None:  # the discrepancy term has no truth
            continue
        z = (p["median"] - t) / ((p["p84"] - p["p16"]) / 2)  # error / half-width
        out[name] = (p["p16"] <= t <= p["p84"], p["p2.5"] <= t <= p["p97.5"], z)
    return out


def test_interval_coverage_over_simulated_repeats() -> None:
    with repeat_pool() as pool:
        repeats = repeat_map(pool, _one_repeat, range(REPEATS))
    names = set(repeats[0])
    assert names == {"kd_G", "ks_G", "m"}
    for name in sorted(names):
        c68 = np.mean([r[name][0] for r in repeats])
        c95 = np.mean([r[name][1] for r in repeats])
        z = np.array([r[name][2] for r in repeats])
        print(
            f"{name}: 68% interval covers the truth in {c68:.2f}, 95% in {c95:.2f} "
            f"of {REPEATS} repeats; error/half-width mean {z.mean():+.2f}, sd {z.std(ddof=1):.2f}"
        )
        # The bands: nominal 0.68 and 0.95, less about two binomial sd at 30 repeats.
        assert 0.55 <= c68 <= 0.80, (name, c68)
        assert c95 >= 0.88, (name, c95)

"""Coverage where the instrument is realistic (issue 17; issue 43 item 4: with every effect on):
32 simulated rigs, each with fresh sensor noise *and* a fresh draw of the instrument's shared
errors from the distributions its rig file states — the lamp's certificate (1.5 %), the lamp's
distance (3 mm), the arms' encoder zeros (0.2° each), the sample's tilt (0.2° about x and y), the
gears' play (0.3° ± 50 % per axis), the arms' sag (0.15°), the sample's bow (0.1 mm), the
camera's distance (5 mm), the flat source's fall-off (2 %) and the room's light (|N(0, 5e-4)|
W m⁻² sr⁻¹) — on `configs/scenes/realistic.toml`, whose 5 mm lamp (the rig states its radius),
drift and 0.5 % camera bend (calibration measures it from the brackets, and the fit carries what
remains) stay. Darks and a flat field are recorded, as a lab run would. A real rig has one such
error for its life; coverage is a statement about rigs, so every repeat is another rig
(simulator.instrument_draws.sobol_normal: why Sobol' points).

The fit carries the shared errors as nuisance parameters (fitting.nuisance): its 68 % interval
must hold the truth in 55–80 % of repeats and its 95 % interval in ≥ 88 %, for kd, ks and m.
The twin fits the same samples the old way — the scale's σ added to every sample's σ in
quadrature, the angles not carried; by least squares and its Laplace interval — and its 95 %
coverage of kd must fall below 80 %: the shared error averaged away as if it were independent
(so this test can fail).

Measured (stop 35): kd 0.63 / 0.97, ks 0.60 / 0.93, m 0.80 / 0.93 (68 % / 95 %), m's intervals
then about 1.4× too wide. 2026-12-06, with the bow, the camera's distance and the flat's fall-off
off: kd 0.70 / 0.97, ks 0.73 / 1.00, m 0.70 / 0.97. With everything on and the bend measured
(32 Sobol' rigs, this test as it stands): kd 0.66 / 0.97, ks 0.62 / 0.97, m 0.56 / 0.91
(error/half-width sd 1.00, 1.02, 1.16). 2026-12-07, the least squares' starts searching the
model's parameters with the nuisances held (fitting.lsq.fit_least_squares): kd 0.69 / 0.97, ks
0.69 / 0.97, m 0.59 / 0.91 (sd 0.98, 1.00, 1.16). Then with the room's light drawn per rig and
carried, and the camera bend's remainder carried (fitting.nuisance, ``linearity_pct``): kd 0.62 /
0.94, ks 0.59 / 0.94, m 0.66 / 0.91 (sd 1.08, 1.13, 1.11).

Each repeat runs in a fresh interpreter (spawn, as tests/fitting/test_coverage_sim.py, which says
why).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

from acquisition.config import (
    CalibrationPhasesConfig,
    DarkPhaseConfig,
    FlatPhaseConfig,
    PlanConfig,
    load_rig,
)
from acquisition.operator import AutoOperator
from calibration.reduce import ReduceOptions, reduce_run
from fitting.budget import read_budget, scale_sigma
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions
from gonio.pipeline import AcquireSpec, acquire
from simulator.instrument_draws import InstrumentBudget, sobol_normal
from simulator.scene import load_scene
from simulator.truth import reference_parameters
from tests.support.paths import REPO
from tests.support.repeats import repeat_map, repeat_pool

# Scheduled first (tests/conftest.py: the longest files start first, so both workers end together).
pytestmark = pytest.mark.heavy(269)

# 32 ≥ the issue's 30, a power of 2 for the Sobol' draws (simulator.instrument_draws.sobol_normal:
# why not a Latin hypercube): the binomial sd of a 95 % coverage is then 0.039, so ≥ 0.88 is
# nominal less 1.8 sd; and the twin's expected kd coverage (below) is far under 0.80.
REPEATS = 32
PLAN = PlanConfig(
    name="coverage-realistic",
    theta_i_deg=(25.0, 50.0),
    theta_o_deg=(0.0, 20.0, 40.0, 60.0),
    delta_phi_deg=(180.0, 120.0),
    exposures_s=(0.002, 0.016),
    # A lab run records darks and a flat field: uncorrected, the realistic sensor's 0.5 % PRNU
    # alone puts χ²/dof at 1.37.
    calibration=CalibrationPhasesConfig(
        dark=DarkPhaseConfig(count=8), flat=FlatPhaseConfig(count=16)
    ),
)
#: What the rig file states (k = 1) and each repeat's world draws from: the lamp's certificate
#: 1.5 %, its distance 3 mm, the three encoder zeros 0.2°, the tilts 0.2°, play 0.3° ± 50 %, sag
#: 0.15°, bow 0.1 mm, camera distance 5 mm, flat fall-off 2 %, room light 5e-4 W m⁻² sr⁻¹
#: (simulator.instrument_draws.InstrumentBudget says where each size comes from).
BUDGET = InstrumentBudget()
FIT = dict(
    model="torrance-sparrow",
    model_options={"fresnel": "none", "shadowing": "smith-rational"},
    channels=["G"],
    mcmc=McmcOptions(walkers=24, max_steps=600),
    n_starts=2,
)


def _world_and_rig(k: int):
    """Repeat k's world (realistic.toml with a fresh draw of the shared errors, and fresh noise)
    and the rig file that states their distributions (configs/rigs/sim.toml plus the budget).
    The draws are scrambled Sobol' points over the repeats (sobol_normal: why)."""
    base = load_scene(REPO / "configs" / "scenes" / "realistic.toml")
    z = sobol_normal(REPEATS, InstrumentBudget.N_DRAWS, seed=17)[k]
    scene = BUDGET.world(base, z, seed=3000 + k)
    rig = BUDGET.rig(load_rig(REPO / "configs" / "rigs" / "sim.toml"),
                     lamp_radius_m=base.light.radius_m)  # fmt: skip
    return base, scene, rig


def _quadrature(table):
    """The same samples as calibration made them before shared errors had a budget: the
    scale's σ in every sample's σ, in quadrature, and no budget for the fit to carry."""
    rel = scale_sigma(read_budget(table.metadata), "G")
    old = table.select(np.ones(len(table), bool))
    old.sigma = np.hypot(table.sigma, rel * np.abs(table.f))
    old.metadata = {k: v for k, v in table.metadata.items() if k != "gonio.budget"}
    return old


def _one_repeat(k: int) -> dict[str, dict[str, tuple[bool, bool]]]:
    """Per treatment and parameter: (truth in 68 %, truth in 95 %)."""
    base, scene, rig = _world_and_rig(k)
    truth = reference_parameters(base)
    truth["sample_bow_um"] = 1e6 * scene.geometry.sample_bow_m  # this rig's dome (µm)
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        spec = AcquireSpec(rig=rig, plan=PLAN, scene=scene, progress=False, announce=False,
                           operator=AutoOperator())  # fmt: skip
        acquire(run, spec)
        table = reduce_run(run, ReduceOptions(bin_px=2, mode="center"))
    out = {}
    # The twin's intervals by least squares and its Laplace approximation (no MCMC): what it
    # shows — an error shared by every sample, put in each σ, shrinks by √N — is in the
    # covariance either way, and it saves 30 chains (~40 CPU-s of the suite).
    twin = {**FIT, "mcmc": None}
    for label, data, fit_kw in (
        ("nuisance", table, FIT),
        ("quadrature", _quadrature(table), twin),
    ):
        fit = fit_samples(data, FitOptions(seed=k, **fit_kw)).to_dict()
        out[label] = {
            name: (
                p["p16"] <= truth[name] <= p["p84"],
                p["p2.5"] <= truth[name] <= p["p97.5"],
                (p["median"] - truth[name]) / ((p["p84"] - p["p16"]) / 2),  # error / half-width
            )
            for name, p in fit["parameters"].items()
            if name in truth
        }
    return out


# 30 acquisitions and 60 fits on the 2 cores, which the suite's other worker shares: ~5 min
# alone, 10 min when the cores are contended (measured) — the suite's 600 s default is too close.
@pytest.mark.timeout(1200)
def test_coverage_on_realistic_rigs_and_the_quadrature_twin_fails() -> None:
    with repeat_pool() as pool:
        repeats = repeat_map(pool, _one_repeat, range(REPEATS))
    cover = {
        label: {
            name: (
                float(np.mean([r[label][name][0] for r in repeats])),
                float(np.mean([r[label][name][1] for r in repeats])),
            )
            for name in ("kd_G", "ks_G", "m", "sample_bow_um")
            if name in repeats[0][label]
        }
        for label in ("nuisance", "quadrature")
    }
    for label, by_name in cover.items():
        for name, (c68, c95) in by_name.items():
            z = np.array([r[label][name][2] for r in repeats])
            # sd(z) is the intervals' width check: 1 when calibrated, > 1 too narrow, < 1 too
            # wide (the notes' m "1.4× too wide" would read 0.7)
            print(
                f"{label}: {name} 68 % covers {c68:.2f}, 95 % covers {c95:.2f} of {REPEATS}; "
                f"error/half-width mean {z.mean():+.2f}, sd {z.std(ddof=1):.2f}"
            )
    for name in ("kd_G", "ks_G", "m"):
        c68, c95 = cover["nuisance"][name]
        # The bands: nominal 0.68 and 0.95, less about two binomial sd at 32 repeats
        # (the 68 % band's top is 1.4 sd above nominal).
        assert 0.55 <= c68 <= 0.80, (name, c68)
        assert c95 >= 0.88, (name, c95)
    # The old treatment: the 1.9 % scale σ shrunk by √N into kd's interval (σ_kd ≈ 0.1 %),
    # so a 95 % interval holds the truth only when the rig's scale error is ≲ 0.1 %: rarely.
    assert cover["quadrature"]["kd_G"][1] < 0.80, cover["quadrature"]["kd_G"]

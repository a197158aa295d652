"""Ngan et al. 2005's published Cook-Torrance fits, rendered as a Python BSDF in the simulator,
recovered within their 95 % intervals (issue 7, acceptance "Recovery").

Truth: the published values (docs/design.md §6: nickel m = 0.0424, F₀ = 0.733; teflon m = 0.139,
F₀ = 0.0203), and the per-channel albedos of the same table (data/brdf_fits, bbm's
ngan_cooktorrance.fit) mapped by fitting.ngan (kd = ρ_d, ks = 4·albedo/π; the mapping is
checked against an independent transcription of bbm's formula in tests/fitting/test_ngan.py).

Data: the scene material of configs/scenes/ngan_<name>.toml (the mapping above) is loaded into
Mitsuba as the registered Python BSDF (simulator.materials, "gonio_model") and evaluated
through Mitsuba's ``bsdf.eval``/cos θ_i (simulator.truth.mitsuba_brdf, float32 like any
Mitsuba render) at an isotropic gonioreflectometer plan: 5 incidence angles, an in-plane
specular scan in 0.5° steps near the mirror, azimuth offsets, and a coarse hemisphere grid
(brdfdata.directions.isotropic_gonio_directions). Nickel's lobe is sharp (m = 0.0424: D falls
to 1/e at θ_h = m, i.e. |θ_o − θ_i| ≈ 2m ≈ 4.9° in the plane): the plan puts ≥ 8 samples per
incidence angle inside that, asserted below. Noise: Gaussian, σ = 1 % · f + 10⁻⁴ sr⁻¹ (the
floor is well below nickel's diffuse level kd/π ≥ 0.0045 sr⁻¹, so the small diffuse albedo is
measured too), fixed seeds. The teflon fit through the full rig (camera, HDR, calibration) is
tests/fitting/test_ngan.py::test_teflon_fit_recovers_ngan_roughness; nickel's rig data are checked
there against this BSDF.

Which parameters and how often: m and F₀ (the published scalars) must lie in their 95 %
intervals, as the issue asks. A single noise realisation misses a 95 % interval 1 time in 20 by
design (a test that fails for 5 % of seeds, per parameter, is not a test of the code), so each
material is fitted to REPEATS = 4 independent noise draws and the check is
(a) the truth inside the 95 % interval in ≥ 3 of 4 (chance failure 1 − 0.95⁴ − 4·0.05·0.95³
≈ 1.4 %), and (b) no bias: the mean z = (median − truth)/SD over the 4 fits within ±1.5
(standard error 0.5, so a 3-SE band, chance failure 0.3 %; a 2-SD bias fails it 84 % of the
time). With direct Mitsuba data the z of m had std 1.1 (teflon) / 0.9 (nickel) over 24 seeds, so
the intervals are calibrated here. kd and ks per channel get a bias bound (median within 3 %).
The intervals must also be informative (narrow), or the interval check would be empty.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import data_file

from brdfdata.directions import isotropic_gonio_directions
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions
from fitting.ngan import COOK_TORRANCE_OPTIONS, ngan_cook_torrance_parameters, read_ngan_fits
from simulator.scene import load_scene
from simulator.truth import direct_samples

# docs/design.md §6 (Ngan, Durand & Matusik 2005): (m, F₀).
PUBLISHED = {"nickel": (0.0424, 0.733), "teflon": (0.139, 0.0203)}
REPEATS = 4


@pytest.mark.parametrize("name", ["nickel", "teflon"])
def test_ngan_published_fit_recovered(name: str, configs) -> None:
    m_true, f0_true = PUBLISHED[name]
    entry = read_ngan_fits(data_file("brdf_fits/ngan_cooktorrance.fit"))[name]
    truth = ngan_cook_torrance_parameters(entry)
    assert (truth["m"], truth["f0"]) == (m_true, f0_true)  # the table is the published one
    scene = load_scene(configs / "scenes" / f"ngan_{name}.toml")
    assert scene.material.type == "model"  # rendered as the Python BSDF

    wi, wo = isotropic_gonio_directions()
    h = wi + wo
    theta_h = np.arccos(h[:, 2] / np.linalg.norm(h, axis=1))
    for ti in np.unique(np.round(wi[:, 2], 9)):
        assert np.sum((theta_h < m_true) & np.isclose(wi[:, 2], ti)) >= 8
    inside: dict[str, list[bool]] = {"m": [], "f0": []}
    z: dict[str, list[float]] = {"m": [], "f0": []}
    for r in range(REPEATS):
        seed = {"nickel": 4100, "teflon": 4200}[name] + r
        table, f_true = direct_samples(
            scene.material, wi, wo, rel_sigma=0.01, floor_sr=1e-4, rng=seed
        )
        # The Python BSDF really rendered the published material: its peak is the lobe's.
        assert f_true.max() > 10 * np.max(truth["kd"]) / np.pi

        # 500 steps × 32 walkers from the LSQ optimum (τ ≈ 20–50): ≥ 200 effective samples,
        # enough for 2.5/97.5 % percentiles to ~±0.1 posterior SD.
        fit = fit_samples(
            table,
            FitOptions(
                model="torrance-sparrow",
                model_options=COOK_TORRANCE_OPTIONS,
                mcmc=McmcOptions(max_steps=500),
                seed=seed,
            ),
        )
        p = fit.parameters
        assert fit.diagnostics["ess"]["m"] >= 200, fit.diagnostics
        for key, t in (("m", m_true), ("f0", f0_true)):
            q = p[key]
            print(
                f"{name} seed {seed}: {key} {q['median']:.5g} [{q['p2.5']:.5g}, {q['p97.5']:.5g}]"
            )
            inside[key].append(q["p2.5"] <= t <= q["p97.5"])
            z[key].append((q["median"] - t) / (0.5 * (q["p84"] - q["p16"])))
        # Informative: m pinned to better than ±2 % (a fit that learnt nothing would pass).
        assert p["m"]["p97.5"] - p["m"]["p2.5"] < 0.04 * m_true, p["m"]
        for i, c in enumerate("RGB"):
            for key in ("kd", "ks"):
                t = truth[key][i]
                q = p[f"{key}_{c}"]
                assert abs(q["median"] - t) <= 0.03 * t, (name, key, c, q, t)
    for key in ("m", "f0"):
        assert sum(inside[key]) >= REPEATS - 1, (name, key, inside[key], z[key])
        assert abs(np.mean(z[key])) <= 1.5, (name, key, z[key])

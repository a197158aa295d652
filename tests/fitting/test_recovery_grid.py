"""Parameter recovery on Mitsuba's own BSDFs (issue 7, acceptance "Recovery"): roughconductor
Au and Cu, and a blendbsdf of diffuse + roughconductor, for m ∈ {0.03, 0.1, 0.3, 0.6}.

Ground truth is independent of the code under test: m = the scene's Beckmann α (Mitsuba's
roughconductor uses α = m, the RMS slope, docs/design.md §7), kd = (1 − w)ρ and ks = w·specular
reflectance from the blend's config, and the conductor's RGB (η, k) are read back from the BSDF
Mitsuba loaded (simulator.truth.mitsuba_conductor_ior: its own reduction of the spectral Au/Cu
tables to RGB). The data are Mitsuba's ``bsdf.eval``/cos θ_i at the directions of an isotropic
gonioreflectometer plan (brdfdata.directions.isotropic_gonio_directions: 5 incidence angles,
an in-plane specular scan in 0.5° steps near the mirror — so even the m = 0.03 lobe, 1/e wide
at |θ_o − θ_i| ≈ 2m ≈ 3.4°, holds ≥ 6 samples per side per θ_i — out-of-plane azimuth offsets,
and a coarse hemisphere grid for the diffuse part), with Gaussian noise σ = 1 % · f + 0.001 sr⁻¹
and a fixed seed per case. Direct evaluation rather than the rendered rig: it isolates the fit
(the rig + calibration have their own tests) and keeps 12 fits in CI time.

The matching model: torrance-sparrow with distribution=beckmann, shadowing=smith-rational
(Mitsuba's separable Smith with Walter's rational G₁), fresnel=conductor with (η, k) per channel
held at Mitsuba's values; kd, ks per channel and a shared m are fitted, plus the discrepancy term.

Why the bounds test bias, not noise: at 1 % noise on ~290 direction pairs × 3 channels the
95 % half-width of m's posterior is ≤ 0.1 % and kd's ≤ 0.7 % — an order of magnitude inside
the issue's 5 % (m) and 3 % (kd) bounds. The test asserts that too (half-width < bound/3), so a
failure of the median bound means the fit is biased (wrong model algebra, wrong convention,
an optimiser stuck in a local minimum), never unlucky noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from brdfdata.directions import isotropic_gonio_directions
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions
from simulator.scene import BlendMaterial, DiffuseMaterial, RoughConductorMaterial
from simulator.truth import direct_samples, material_reference_parameters

M_GRID = (0.03, 0.1, 0.3, 0.6)
OPTIONS = {"distribution": "beckmann", "shadowing": "smith-rational", "fresnel": "conductor"}
M_BOUND = 0.05  # issue 7: posterior median of m within 5 % of the truth
KD_BOUND = 0.03  # issue 7: diffuse albedo within 3 %
# A blend whose diffuse part is coloured differently from the conductor's Fresnel colour, so
# kd and ks·F cannot trade off across channels.
BLEND_WEIGHT = 0.4
DIFFUSE_RHO = (0.6, 0.45, 0.3)


def material(kind: str, m: float):
    if kind == "blend":
        return BlendMaterial(
            weight=BLEND_WEIGHT,
            first=DiffuseMaterial(reflectance=DIFFUSE_RHO),
            second=RoughConductorMaterial(alpha=m, conductor="Cu"),
        )
    return RoughConductorMaterial(alpha=m, conductor=kind)


def test_mitsuba_rgb_ior_is_the_published_rgb_value() -> None:
    """The Fresnel truth read from Mitsuba is the RGB (η, k) of docs/design.md §6 (Mitsuba's
    spectral tables reduced to RGB), to the 4 digits printed there — so it is a real conductor,
    not a default such as the perfect mirror."""
    au = material_reference_parameters(RoughConductorMaterial(alpha=0.1, conductor="Au"))
    cu = material_reference_parameters(RoughConductorMaterial(alpha=0.1, conductor="Cu"))
    design = {
        "Au": ((0.1431, 0.3750, 1.4425), (3.9832, 2.3857, 1.6032)),
        "Cu": ((0.2004, 0.9240, 1.1022), (3.9129, 2.4528, 2.1422)),
    }
    for name, truth in (("Au", au), ("Cu", cu)):
        eta = [truth[f"eta_{c}"] for c in "RGB"]
        k = [truth[f"k_{c}"] for c in "RGB"]
        # docs/design.md §6's values come from another Mitsuba/spectral reduction: agree to ≤ 0.5 %.
        np.testing.assert_allclose(eta, design[name][0], rtol=5e-3)
        np.testing.assert_allclose(k, design[name][1], rtol=5e-3)


@pytest.mark.parametrize("m", M_GRID)
@pytest.mark.parametrize("kind", ["Au", "Cu", "blend"])
def test_recovery(kind: str, m: float) -> None:
    mat = material(kind, m)
    truth = material_reference_parameters(mat)
    wi, wo = isotropic_gonio_directions()
    seed = 1000 + 10 * M_GRID.index(m) + ["Au", "Cu", "blend"].index(kind)
    table, f_true = direct_samples(mat, wi, wo, rel_sigma=0.01, floor_sr=1e-3, rng=seed)
    # The direction set resolves the lobe: many pairs have a half vector within m of the
    # normal (where D > e⁻¹ of its peak), from every incidence angle.
    h = wi + wo
    theta_h = np.arccos(h[:, 2] / np.linalg.norm(h, axis=1))
    assert np.sum(theta_h < m) >= 50, np.sum(theta_h < m)
    assert np.all(f_true >= 0) and np.all(np.isfinite(f_true))

    fix = {k: v for k, v in truth.items() if k.startswith(("eta_", "k_"))}
    assert len(fix) == 6  # Fresnel of every channel held at Mitsuba's own (η, k)
    # 400 steps × 32 walkers from the LSQ optimum: τ ≈ 20–45, so ≥ 100 effective samples,
    # enough for a median (its Monte-Carlo error ≈ 1.25 SD/√ESS ≤ 0.13 posterior SD).
    fit = fit_samples(
        table,
        FitOptions(
            model="torrance-sparrow",
            model_options=OPTIONS,
            shared=["m"],
            fix=fix,
            mcmc=McmcOptions(max_steps=400),
            seed=seed,
        ),
    )
    p = fit.parameters
    assert fit.diagnostics["ess"]["m"] >= 100, fit.diagnostics

    def check(name: str, bound: float) -> None:
        t = truth[name]
        q = p[name]
        half = 0.5 * (q["p97.5"] - q["p2.5"])
        # The noise alone cannot reach the bound (see module docstring) …
        assert half < bound * t / 3, (name, q, t)
        # … so this is a bias check.
        assert abs(q["median"] - t) <= bound * t, (name, q["median"], t)

    check("m", M_BOUND)
    for c in "RGB":
        if truth[f"kd_{c}"] > 0:
            check(f"kd_{c}", KD_BOUND)
        else:
            # Pure conductor: no diffuse part. 0.01 = the 3 % bound on a mid-grey albedo 0.3.
            assert p[f"kd_{c}"]["median"] < 0.01, p[f"kd_{c}"]
        # ks (specular albedo) is recovered as well as kd with the matching model.
        check(f"ks_{c}", KD_BOUND)

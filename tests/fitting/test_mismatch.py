"""Honest intervals when the model does not fit (issue 18 item 3 and its acceptance).

Torrance-Sparrow (Beckmann, rational Smith, dielectric Fresnel with η fixed at 1.5) is fitted to
three materials it does not describe: Mitsuba's ``roughplastic`` (a diffuse base seen through a
rough coating) and two RGL measurements (white paper, red Colodur wall paint) through Mitsuba's
``measured`` plugin. The truth is Mitsuba's own BSDF, never the model under test.

The target of the intervals is the **best approximation on the measured domain**
(fitting.fit.best_approximation): the fit's own optimum on noise-free f over the domain — a
midpoint grid of 30 θ_i × 30 θ_o × 36 Δφ cells, the integral of the fit's criterion over the
distribution the measured directions are drawn from. Each repeat measures 2500 directions drawn
afresh from that domain (θ_i, θ_o uniform in 0–70°, Δφ uniform) with 1 % noise + 0.001 sr⁻¹,
so the repeats vary both the noise and which directions were measured, as two labs measuring
one material would; the truth's deviation from the model is then part of what a repeat draws,
and an interval is honest when it covers θ* as often as it says. (At 1000 directions the
paper's kd was covered in 83 % of the repeats: the sandwich's J then rests on a few samples
in the lobe, and its typical value falls short of its mean; at 2500, 93–100 % everywhere.)

What is asserted, per material, over 30 repeats (each repeat in a fresh interpreter, a spawn pool
of two, so it is a function of its seed alone — see tests/fitting/test_coverage_sim.py):

* 95 % intervals of kd, ks and m cover θ* in ≥ 88 % of repeats (the issue's bound; with 30
  repeats a perfectly calibrated interval falls below it with probability ≈ 4 %, so the three
  parameters × three materials are run with fixed seeds, not re-drawn per CI run);
* the 95 % predictive band for the true f holds Mitsuba's value at 85–100 % of 5000 held-out
  directions in every (θ_h, θ_d) region with samples nearby (the region held ≥ 20 measured
  samples), pooled over the repeats;
* and each half can fail: the sampler's own intervals (not widened) cover θ* in fewer than 88 %
  of repeats for some parameter, and a band with one global model-error fraction misses the
  85 % in some region — the measured reasons for the two mends in fitting.mismatch.
"""

from __future__ import annotations

import numpy as np
import pytest

from brdfdata.data_paths import find_data
from brdfdata.directions import normalize, vector_to_spherical
from brdfdata.samples import SampleTable
from fitting.fit import FitOptions, best_approximation, fit_samples
from fitting.mcmc import McmcOptions
from fitting.mismatch import (
    OTHER_REGIONS,
    REGION_MIN_SAMPLES,
    BandSource,
    predictive_band,
    region_index,
    region_label,
    sandwich_adjust,
)
from tests.support.repeats import repeat_map, repeat_pool

# Scheduled first (tests/conftest.py: the longest files start first, so both workers end together).
pytestmark = pytest.mark.heavy(123)

REPEATS = 30
N_MEASURED = 2500
N_HELDOUT = 5000
THETA_MAX_DEG = 70.0
REL_NOISE, FLOOR_SR = 0.01, 1e-3
PARAMS = ("kd_G", "ks_G", "m")
OPTIONS = FitOptions(
    model="torrance-sparrow",
    model_options={
        "distribution": "beckmann",
        "shadowing": "smith-rational",
        "fresnel": "dielectric",
    },
    fix={"ior": 1.5},
    channels=["G"],
    # Shorter than the default chain (2000 steps, 32 walkers) to keep CI within its time: four
    # parameters, and the 95 % intervals of these posteriors are settled by then. Measured: 32
    # walkers × 2000 steps gave the same coverage, repeat for repeat, on the paper; 800 steps
    # with 4 starts gave the same as these 400 with 2 to within one repeat per parameter
    # (widened 0.93–1.00 both; sampler's own 0.60–0.93 and 0.63–0.93).
    mcmc=McmcOptions(walkers=16, max_steps=400),
    n_starts=2,
)
MATERIALS = ("roughplastic", "paper", "colodur")


def _material(name: str):
    from simulator.scene import MeasuredMaterial, RoughPlasticMaterial

    if name == "roughplastic":
        return RoughPlasticMaterial(
            alpha=0.2, diffuse_reflectance=(0.5, 0.35, 0.2), int_ior=1.49, ext_ior=1.000277
        )
    files = {"paper": "paper_white_rgb.bsdf", "colodur": "colodur_napoli_4f_rgb.bsdf"}
    return MeasuredMaterial(filename=str(find_data(f"rgl_brdf/{files[name]}")))


def _directions(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n (ω_i, ω_o) pairs, θ uniform in 0–70° on both sides, Δφ uniform; float32-rounded like
    Mitsuba's own vectors so data and model see one geometry."""
    rng = np.random.default_rng(seed)
    ti, to = np.radians(rng.uniform(0.0, THETA_MAX_DEG, (2, n)))
    po = rng.uniform(0.0, 2 * np.pi, n)
    wi = np.stack([np.sin(ti), np.zeros(n), np.cos(ti)], axis=1)
    wo = np.stack([np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], axis=1)
    return wi.astype(np.float32).astype(np.float64), wo.astype(np.float32).astype(np.float64)


def _table(wi, wo, f, sigma) -> SampleTable:
    ti, pi = vector_to_spherical(normalize(wi))
    to, po = vector_to_spherical(normalize(wo))
    return SampleTable(
        theta_i=ti,
        phi_i=pi,
        theta_o=to,
        phi_o=po,
        channel=np.full(f.size, "G"),
        f=f,
        sigma=sigma,
        flags=np.zeros(f.size, dtype=np.int32),
    )


def _truth(name: str, wi, wo) -> np.ndarray:
    from simulator.truth import mitsuba_brdf

    return mitsuba_brdf(_material(name), wi, wo)[:, 1]


def _domain_grid() -> tuple[np.ndarray, np.ndarray]:
    """Midpoints of 30 θ_i × 30 θ_o × 36 Δφ cells over the measured domain (θ ≤ 70°): equal
    weights, like the uniform distribution the repeats draw from."""
    t = np.radians((np.arange(30) + 0.5) * THETA_MAX_DEG / 30)
    p = (np.arange(36) + 0.5) * 2 * np.pi / 36
    ti, to, po = (a.ravel() for a in np.meshgrid(t, t, p, indexing="ij"))
    wi = np.stack([np.sin(ti), np.zeros(ti.size), np.cos(ti)], axis=1)
    wo = np.stack([np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], axis=1)
    return wi.astype(np.float32).astype(np.float64), wo.astype(np.float32).astype(np.float64)


def _best(name: str) -> dict[str, float]:
    wi, wo = _domain_grid()
    f = _truth(name, wi, wo)
    return best_approximation(_table(wi, wo, f, REL_NOISE * f + FLOOR_SR), OPTIONS)


def _band_fractions(source: BandSource, name: str, measured_regions, seed: int):
    """{region: (held-out count, fraction inside)} for regions with ≥ 20 measured samples."""
    wi, wo = _directions(N_HELDOUT, 999)
    f = _truth(name, wi, wo)
    lo, hi = predictive_band(source, wi, wo, "G", rng=seed)
    inside = (f >= lo) & (f <= hi)
    reg = region_index(wi, wo)
    counts = np.bincount(measured_regions, minlength=9)
    return {
        int(k): (int(np.sum(reg == k)), float(np.mean(inside[reg == k])))
        for k in range(9)
        if counts[k] >= REGION_MIN_SAMPLES and np.any(reg == k)
    }


def _one_repeat(job: tuple[str, int]) -> dict:
    """Measure, fit and score repeat `rep` of material `name` (runs in a spawn worker)."""
    name, rep = job
    rng = np.random.default_rng(1000 + rep)
    wi, wo = _directions(N_MEASURED, 5000 + rep)
    f = _truth(name, wi, wo)
    sigma = REL_NOISE * f + FLOOR_SR
    fit = fit_samples(
        _table(wi, wo, f + sigma * rng.standard_normal(f.size), sigma), OPTIONS.replace(seed=rep)
    )
    space = fit.extras["space"]
    raw = space.to_natural(fit.extras["raw_draws"])
    q = np.percentile(raw, [2.5, 97.5], axis=0)
    measured = region_index(wi, wo)
    source = BandSource.of_fit(fit)
    # The same draws with one global fraction s for every region: the band before the mend.
    s = raw[:, space.index("discrepancy")]
    one = [
        {
            "label": OTHER_REGIONS,
            "regions": list(range(9)),
            "median": float(np.median(s)),
            "quantiles": np.quantile(s, np.linspace(0.0, 1.0, 41)).tolist(),
        }
    ]
    global_source = BandSource(source.model, space, fit.extras["raw_draws"], one)
    return {
        "name": name,
        "widened": {p: (fit.parameters[p]["p2.5"], fit.parameters[p]["p97.5"]) for p in PARAMS},
        "raw": {p: (q[0, space.index(p)], q[1, space.index(p)]) for p in PARAMS},
        "band": _band_fractions(source, name, measured, rep),
        "band_global": _band_fractions(global_source, name, measured, rep),
    }


def _pooled(repeats, key: str) -> dict[int, float]:
    """Per region: the fraction inside over every held-out direction of every repeat."""
    total: dict[int, list[float]] = {}
    for r in repeats:
        for k, (n, frac) in r[key].items():
            total.setdefault(k, [0.0, 0.0])
            total[k][0] += n * frac
            total[k][1] += n
    return {k: a / b for k, (a, b) in total.items()}


@pytest.fixture(scope="module")
def study():
    jobs = [(name, rep) for name in MATERIALS for rep in range(REPEATS)]
    with repeat_pool() as pool:
        best = dict(zip(MATERIALS, repeat_map(pool, _best, MATERIALS), strict=True))
        repeats = list(pool.map(_one_repeat, jobs))
    return best, repeats


def _coverage(best, repeats, name: str, key: str) -> dict[str, float]:
    mine = [r for r in repeats if r["name"] == name]
    return {
        p: float(np.mean([lo <= best[name][p] <= hi for lo, hi in (r[key][p] for r in mine)]))
        for p in PARAMS
    }


def test_intervals_cover_the_best_approximation(study) -> None:
    best, repeats = study
    for name in MATERIALS:
        widened = _coverage(best, repeats, name, "widened")
        raw = _coverage(best, repeats, name, "raw")
        print(f"{name}: θ* {best[name]}; 95 % coverage widened {widened}, sampler's own {raw}")
        for p in PARAMS:
            assert widened[p] >= 0.88, (name, p, widened, raw)
    # The widening is what makes it hold: the sampler's own draws (the posterior with one
    # global model-error fraction) fall short of 88 % somewhere — on the paper the measured
    # coverage of m was 50 %.
    worst_raw = min(min(_coverage(best, repeats, n, "raw").values()) for n in MATERIALS)
    assert worst_raw < 0.88, worst_raw


def test_predictive_band_is_right_in_every_region(study) -> None:
    _best_params, repeats = study
    short_global = []
    for name in MATERIALS:
        mine = [r for r in repeats if r["name"] == name]
        regional = _pooled(mine, "band")
        one = _pooled(mine, "band_global")
        worst_fit = {
            region_label(k): min(r["band"][k][1] for r in mine if k in r["band"]) for k in regional
        }
        print(
            f"{name}: inside the 95 % band, per region "
            + ", ".join(
                f"{region_label(k)} {v:.3f} (global s: {one[k]:.3f})" for k, v in regional.items()
            )
            + f"; worst single fit per region {worst_fit}"
        )
        assert len(regional) >= 5, regional  # the test covers most of the hemisphere
        for k, frac in regional.items():
            assert 0.85 <= frac <= 1.0, (name, region_label(k), frac)
        short_global += [frac for frac in one.values() if frac < 0.85]
    # One global fraction is right on average but not locally: some region falls short.
    assert short_global, "the global-s band held 85 % everywhere: the test cannot fail"


def test_best_approximation_is_the_truth_when_the_model_fits() -> None:
    """The target's definition, checked where it has an independent answer: on Mitsuba's blend of
    diffuse and a Beckmann roughconductor with k = 0 (whose Fresnel is the dielectric one, η =
    1.5), the model is exact and θ* must be the material's own parameters. 1e-3 relative:
    Mitsuba's float32 evaluation (≈ 1e-6) and its rational-Smith G are the model's too, so
    only the optimiser's tolerance is left."""
    from simulator.scene import BlendMaterial, DiffuseMaterial, RoughConductorMaterial
    from simulator.truth import mitsuba_brdf

    material = BlendMaterial(
        weight=0.5,
        first=DiffuseMaterial(reflectance=(0.5, 0.4, 0.3)),
        second=RoughConductorMaterial(alpha=0.2, eta=(1.5,) * 3, k=(0.0,) * 3),
    )
    wi, wo = _directions(4000, 7)
    f = mitsuba_brdf(material, wi, wo)[:, 1]
    best = best_approximation(_table(wi, wo, f, REL_NOISE * f + FLOOR_SR), OPTIONS)
    # blendbsdf weight 0.5: kd = 0.5 · 0.4 (albedo of the diffuse half), ks = 0.5.
    assert best["kd_G"] == pytest.approx(0.2, rel=1e-3)
    assert best["ks_G"] == pytest.approx(0.5, rel=1e-3)
    assert best["m"] == pytest.approx(0.2, rel=1e-3)
    assert best["discrepancy"] < 1e-3  # no model error on exact data


def test_sandwich_equals_the_one_parameter_formula() -> None:
    """The widening against an independent computation where it has a closed form: only kd free
    (f̂ = kd/π + a fixed Torrance-Sparrow lobe, so g = ∂f̂/∂kd = 1/π) and the model error held
    at s = 5 % (``--fix discrepancy=0.05``), on a diffuse part that is not Lambertian. ln L is
    then exactly quadratic in kd, its information Σ g²/v, each row's score g r/v, and the HC3
    sandwich variance Σ g² e²/v² / (Σ g²/v)², e = r/(1 − h), h = g²/(v Σ g²/v). Their ratio λ
    — computed here with plain numpy — must be the one the code reports, and the draws' sd must
    grow by √max(λ, 1) (one parameter: the map is a scalar). 1e-6 relative: the code takes the
    information by second differences at a twentieth of the posterior sd, exact for a
    quadratic up to round-off ≈ 1e-16 · |ln L| / step² ≈ 1e-9 of it."""
    from fitting import models

    wi, wo = _directions(800, 11)
    lobe = {"ks": 0.5, "m": 0.15, "ior": 1.5}
    ts = models.get("torrance-sparrow", **OPTIONS.model_options)
    cos_o = wo[:, 2]
    f = ts.evaluate({"kd": 0.0, **lobe}, wi, wo) + 0.3 * (0.6 + 0.8 * cos_o**3) / np.pi
    sigma = REL_NOISE * f + FLOOR_SR
    rng = np.random.default_rng(3)
    fit = fit_samples(
        _table(wi, wo, f + sigma * rng.standard_normal(f.size), sigma),
        OPTIONS.replace(fix={**lobe, "discrepancy": 0.05}, seed=1).with_mcmc(
            walkers=16, max_steps=2000
        ),
    )
    lik, space = fit.extras["likelihood"], fit.extras["space"]
    raw = fit.extras["raw_draws"]
    assert space.names == ["kd_G"]
    kd = float(np.median(raw[:, 0]))
    v = sigma**2 + (0.05 * lik.discrepancy_reference[0]) ** 2
    g = np.full(f.size, 1.0 / np.pi)
    r = lik.data[0].f - ts.evaluate({"kd": kd, **lobe}, wi, wo)
    info_h = np.sum(g * g / v)
    h = g * g / v / info_h
    ratio = np.sum(g * g * (r / (1 - h)) ** 2 / v**2) / info_h
    _draws, info = sandwich_adjust(lik, raw)
    assert info["applied"], info
    assert info["raw_variance_ratio"][0] == pytest.approx(ratio, rel=1e-6), (info, ratio)
    assert info["sd_factor"]["kd_G"] == pytest.approx(max(1.0, np.sqrt(ratio)), rel=1e-6)
    assert ratio > 1.5, ratio  # a real widening is checked, not only the clip at 1


def test_matched_model_is_not_widened() -> None:
    """Where the model is exact the residuals are the noise, J ≈ H, and the widening stays
    within its estimation noise: each eigenvalue of the sandwich ratio has relative sd ≈ √(2/N)
    ≈ 4.5 % at N = 1000, so the largest of three sd factors stays below 1.15 (≈ 3 sd of the
    largest of three)."""
    from simulator.scene import BlendMaterial, DiffuseMaterial, RoughConductorMaterial
    from simulator.truth import mitsuba_brdf

    material = BlendMaterial(
        weight=0.5,
        first=DiffuseMaterial(reflectance=(0.5, 0.4, 0.3)),
        second=RoughConductorMaterial(alpha=0.2, eta=(1.5,) * 3, k=(0.0,) * 3),
    )
    wi, wo = _directions(N_MEASURED, 21)
    f = mitsuba_brdf(material, wi, wo)[:, 1]
    sigma = REL_NOISE * f + FLOOR_SR
    rng = np.random.default_rng(5)
    fit = fit_samples(_table(wi, wo, f + sigma * rng.standard_normal(f.size), sigma), OPTIONS)
    factors = fit.diagnostics["mismatch"]["sd_factor"]
    assert max(factors.values()) < 1.15, factors
    verdict = next(v for v in fit.verdicts if v["name"] == "discrepancy")
    assert verdict["status"] == "ok", verdict


def test_region_index_in_blocks_is_the_direct_binning() -> None:
    """region_index works in blocks of rows (bounded temporaries); across a block boundary,
    and for (k, n, 3) input, it equals the θ_h, θ_d bands read directly off the half/difference
    angles of the whole set (brdfdata.rusinkiewicz), bin edges from the module's constants."""
    from brdfdata.directions import uniform_hemisphere
    from brdfdata.rusinkiewicz import to_half_diff
    from fitting.mismatch import _REGION_BLOCK, REGION_THETA_D, REGION_THETA_H

    rng = np.random.default_rng(4)
    n = _REGION_BLOCK + 777  # two blocks, the second partial
    wi, wo = uniform_hemisphere(n, rng), uniform_hemisphere(n, rng)
    th, td, _ = to_half_diff(wi, wo)
    h_band = np.searchsorted(REGION_THETA_H[1:-1], th, side="right")
    d_band = np.searchsorted(REGION_THETA_D[1:-1], td, side="right")
    direct = 3 * h_band + d_band
    assert np.array_equal(region_index(wi, wo), direct)
    assert np.bincount(direct, minlength=9).min() > 0  # every region is exercised
    half = n // 2 * 2
    stacked = region_index(wi[:half].reshape(2, -1, 3), wo[:half].reshape(2, -1, 3))
    assert np.array_equal(stacked.ravel(), direct[:half])

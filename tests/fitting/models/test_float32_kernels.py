"""The single-precision kernels (issue 23: within 1.2× of Mitsuba's float32 BSDFs) and how the
MCMC uses them: the float32 exp, float32 values against the independent numpy reference where
the maths bounds their rounding, and the likelihood choosing float32 only where its rounding is
negligible — and sampling the same posterior then."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from brdfdata.directions import spherical_to_vector, uniform_hemisphere
from brdfdata.samples import SampleTable
from fitting import models
from fitting.likelihood import F32_LNL_LIMIT, Likelihood
from fitting.lsq import fit_least_squares
from fitting.mcmc import ConvergenceTarget, McmcOptions, run_mcmc
from fitting.models import kernel_math
from fitting.priors import ParameterSpace

# Scheduled first (tests/conftest.py: the longest files start first, so both workers end together).
pytestmark = pytest.mark.heavy(35)

U32 = 2.0**-24  # float32's unit roundoff: a correctly rounded operation errs by ≤ U32 relative


def test_float32_exp_neg_accuracy():
    """exp(−x) in float32 for x ∈ [0, 86). Bound, in units of U32: r = (k ln2_hi − x) + k ln2_lo
    is exact but for its last addition (k ln2_hi exact: k ≤ 124 has 7 bits, ln2_hi 15; the
    subtraction exact by Sterbenz) — 1 U32 of |r| ≤ 0.35, so ≤ 0.35 U32 in e^r; the degree-7
    Horner evaluation rounds 14 times on positive terms of size ≤ 1.42: ≤ 14·1.42/0.7 ≈ 28 U32
    worst case (Higham γ₁₄ scaled by max p / min p), its truncation 0.08 U32; ×2^−k is exact.
    So 32 U32 bounds it, against numpy's float64 exp of the same float32 x."""
    x = np.concatenate([np.linspace(0.0, 85.99, 200_001), [0.0, 1e-30, 0.5 * np.log(2)]])
    x32 = x.astype(np.float32)
    got = kernel_math.exp_neg(x32)
    assert got.dtype == np.float32
    ref = np.exp(-x32.astype(np.float64))
    rel = np.abs(got.astype(np.float64) - ref) / ref
    assert rel.max() <= 32 * U32, rel.max() / U32
    assert np.all(got > 0)  # p·2^−k with k ≤ 124 stays a normal float32 (no denormal assists)
    # from 86 on it is 0, as the kernels take it (and never garbage beyond the polynomial's range)
    far = kernel_math.exp_neg(np.array([86.0, 100.0, 1e6, np.inf], np.float32))
    assert np.all(far == 0)


def _draw(p, shape, rng, lo=None, hi=None):
    lo = max(p.lower, 1e-6) if lo is None else lo
    hi = p.upper if hi is None else hi
    if p.log:
        return np.exp(rng.uniform(np.log(lo), np.log(hi), shape))
    return rng.uniform(lo, hi, shape)


# The isotropic configurations whose float32 rounding the maths bounds (no cancellation): every
# distribution and shadowing with F ≡ 1, Schlick, or a dielectric of η ≥ 1.2 (at η → 1 the
# Fresnel numerator c − u cancels). The conductor's a² = (√(t² + 4η²k²) + t)/2 cancels for
# t = η² − k² − sin²θ ≪ 0 (noble metals): left to the likelihood's measured check (tests below).
WELL_CONDITIONED = [
    dict(distribution=d, shadowing=s, fresnel=f)
    for d, s, f in itertools.product(
        ("beckmann", "ggx"),
        ("v-cavity", "smith", "smith-rational", "smith-correlated"),
        ("none", "schlick", "dielectric"),
    )
]


@pytest.mark.parametrize("options", WELL_CONDITIONED, ids=lambda o: "-".join(o.values()))
def test_float32_within_rounding_of_the_numpy_reference(options):
    """|f32 − f| ≤ (64 + 3x)·U32·f against the numpy backend (fitting.models.microfacet/fresnel,
    float64) over the priors' box (m ≥ 0.02), where x = tan²θ_h/m² is Beckmann's exponent (0 for
    GGX). Why that bound: ≤ 40 rounded float32 operations on positive quantities, each ≤ U32
    relative (≤ 40 U32, Higham's γ_n); the nine geometry values and the parameter table rounded
    once each to float32, entering f with condition numbers ≤ 2 (G, F, D_GGX; ≤ 18 U32 in all);
    Beckmann's exp(−x) turns x's relative error (t², 1/m² and their product: 3 U32) into 3x U32
    of e^−x. Rows with x ≥ 80 are left out: there e^−x < 2e-35 nears float32's smallest normal,
    and the kernels cut it to 0 from 86 (documented)."""
    rng = np.random.default_rng(7)
    n, w = 3000, 40
    wi = uniform_hemisphere(n, rng)
    wo = uniform_hemisphere(n, rng)
    wi[:40, 2] *= -1  # below the horizon: exactly 0 in both
    model = models.get("torrance-sparrow", **options)
    params = {}
    for p in model.parameters:
        lo = {"m": 0.02, "ior": 1.2}.get(p.name)
        params[p.name] = _draw(p, (w, 1), rng, lo=lo)
    f32 = model.evaluate(params, wi, wo, precision="float32")
    ref = model.evaluate(params, wi, wo, backend="numpy")
    assert f32.dtype == np.float32 and f32.shape == ref.shape
    assert np.all(f32[:, :40] == 0) and np.all(ref[:, :40] == 0)
    s = wi + wo
    t2 = (s[:, 0] ** 2 + s[:, 1] ** 2) / s[:, 2] ** 2
    x = t2[None, :] / params["m"] ** 2 if options["distribution"] == "beckmann" else 0 * ref
    keep = (ref > 0) & (x < 80)
    rel = np.abs(f32.astype(np.float64) - ref)[keep] / ref[keep]
    bound = (64 + 3 * x[keep]) * U32
    assert np.all(rel <= bound), (rel / U32)[rel > bound][:5]
    assert np.isfinite(f32).all()


@pytest.mark.parametrize(
    "name",
    ["lambert", "torrance-sparrow", "torrance-sparrow-anisotropic"],
    ids=["lambert", "iso", "aniso"],
)
def test_float32_every_configuration_is_sound(name):
    """Every configuration with float32 kernels, at parameters across the priors' whole box:
    a float32 array, finite wherever float64 is, 0 exactly where float64 is (below the
    horizon), and agreeing with float64 to a few ulps on most values (the rounding of a
    computation of ~40 operations is a sum of independent errors ≤ U32 each: its median is
    a few U32; 64 U32 is the well-conditioned bound above). An unconverted float64 constant
    would not fail this, a wrong float32 constant, branch or threshold on many values would (the
    anisotropic test below bounds every value)."""
    rng = np.random.default_rng(8)
    n, w = 2000, 30
    wi = uniform_hemisphere(n, rng)
    wo = uniform_hemisphere(n, rng)
    wi[:25, 2] *= -1
    entry = models.entry(name)
    for combo in itertools.product(*[[(o.name, v) for v in o.allowed] for o in entry.options]):
        model = models.get(name, **dict(combo))
        params = {p.name: _draw(p, (w, 1), rng) for p in model.parameters}
        f32 = model.evaluate(params, wi, wo, precision="float32")
        f64 = model.evaluate(params, wi, wo)
        assert f32.dtype == np.float32, combo
        assert np.all(f32[:, :25] == 0), combo  # below the horizon
        # 0 wherever float64 is; float32 may be 0 where float64 is not only in exp's cut-off
        assert np.all((f64 == 0) <= (f32 == 0)), combo
        assert np.all((f32 == 0) <= (f64 < 1e-30)), combo
        assert np.all(np.isfinite(f32) == np.isfinite(f64)), combo
        big = f64 > 1e-30
        rel = np.abs(f32.astype(np.float64) - f64)[big] / f64[big]
        assert np.median(rel) <= 64 * U32, (combo, np.median(rel) / U32)


# the same option sets (none of them is a conductor); the anisotropic rotation's cancellation is
# in the bound
@pytest.mark.parametrize("options", WELL_CONDITIONED, ids=lambda o: "-".join(o.values()))
def test_anisotropic_float32_within_its_rounding_bound(options):
    """Every value of the anisotropic model in float32 against the numpy reference, α from 0.02
    to 2 and φ₀ across its box, within a bound that adds to the isotropic one (64 U32 + 3q U32
    for Beckmann's exponent q) the two cancellations float32 meets here:
    - the rotation x' = c s_x + s s_y (with the stored s_x, s_y: ≤ 3 U32 |s| absolute), squared
      over α² in Q: D ∝ (s_z² + Q)^−2 moves by 2δQ/(s_z² + Q) ≤ 6 U32 (|s|/s_z)(1/α_x + 1/α_y)
      (|x'|/α²/(s_z² + x'²/α²) ≤ 1/(2 α s_z)), |s|/s_z = √(1 + tan²θ_h);
    - u² = |M ω|² per direction (M = rotation × α, ≤ 3 U32 α |ω_t| absolute per component):
      G₁ ∝ 1/(c + √(c² + u²)) moves by ≤ δ(u²)/(4c²) ≤ 3 U32 α_max² tan²θ per side.
    Rows with q ≥ 80 are left out as in the isotropic test."""
    rng = np.random.default_rng(11)
    n, w = 3000, 40
    wi = uniform_hemisphere(n, rng)
    wo = uniform_hemisphere(n, rng)
    wi[:40, 2] *= -1
    model = models.get("torrance-sparrow-anisotropic", **options)
    params = {}
    for p in model.parameters:
        lo = {"alpha_x": 0.02, "alpha_y": 0.02, "ior": 1.2}.get(p.name)
        params[p.name] = _draw(p, (w, 1), rng, lo=lo)
    f32 = model.evaluate(params, wi, wo, precision="float32")
    ref = model.evaluate(params, wi, wo, backend="numpy")
    assert f32.dtype == np.float32 and np.all(f32[:, :40] == 0) and np.all(ref[:, :40] == 0)
    ax, ay, phi = params["alpha_x"], params["alpha_y"], params["phi0"]
    s = wi + wo
    c, sn = np.cos(phi), np.sin(phi)
    xr = c * s[None, :, 0] + sn * s[None, :, 1]
    yr = -sn * s[None, :, 0] + c * s[None, :, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        q = ((xr / ax) ** 2 + (yr / ay) ** 2) / s[None, :, 2] ** 2
        t2 = (s[:, 0] ** 2 + s[:, 1] ** 2) / s[:, 2] ** 2
        tan2_i = (wi[:, 0] ** 2 + wi[:, 1] ** 2) / wi[:, 2] ** 2
        tan2_o = (wo[:, 0] ** 2 + wo[:, 1] ** 2) / wo[:, 2] ** 2
    amax2 = np.maximum(ax, ay) ** 2
    bound = (
        64
        + (3 * q if options["distribution"] == "beckmann" else 0)
        + 6 * np.sqrt(1 + t2)[None, :] * (1 / ax + 1 / ay)
        + 3 * amax2 * (tan2_i + tan2_o)[None, :]
    ) * U32
    keep = (ref > 0) & (q < 80)
    rel = np.abs(f32.astype(np.float64) - ref)[keep] / ref[keep]
    assert np.all(rel <= bound[keep]), (rel / bound[keep]).max()
    assert np.isfinite(f32).all()


def test_float32_grazing_pairs_stay_finite():
    """Both directions within 1e-20 of the horizon, 90° apart in azimuth (off the specular peak,
    whose f itself exceeds float32's range there): tan²θ_h ≈ 5e39 overflows float32; the table
    holds it at 1e30, where every D has reached its limit, so f is float64's to float32
    precision."""
    z = 1e-20
    wi = np.array([[np.sqrt(1 - z * z), 0.0, z]])
    wo = np.array([[0.0, np.sqrt(1 - z * z), z]])
    for dist in ("ggx", "beckmann"):
        model = models.get("torrance-sparrow", distribution=dist, shadowing="v-cavity")
        p = {"kd": 0.1, "ks": 0.5, "m": np.full((2, 1), 0.3), "ior": 1.5}
        f32 = model.evaluate(p, wi, wo, precision="float32")
        f64 = model.evaluate(p, wi, wo)
        assert np.all(np.isfinite(f32)), (dist, f32)
        np.testing.assert_allclose(f32, f64, rtol=64 * U32)


def test_float32_is_only_for_what_has_kernels():
    """float32 is a request: per-sample parameters, log f and the other models stay float64."""
    rng = np.random.default_rng(9)
    wi, wo = uniform_hemisphere(50, rng), uniform_hemisphere(50, rng)
    ts = models.get("torrance-sparrow", distribution="ggx", fresnel="conductor")
    p = {"kd": 0.1, "ks": 0.5, "m": np.full((3, 1), 0.2), "eta": 0.2, "k": 3.0}
    assert ts.evaluate(p, wi, wo, precision="float32").dtype == np.float32
    per_sample = dict(p, m=rng.uniform(0.1, 0.3, (3, 50)))
    assert ts.evaluate(per_sample, wi, wo, precision="float32").dtype == np.float64
    phong = models.get("phong")
    phong_params = {"kd": 0.5, "ks": 0.3, "n": 20.0}
    assert phong.evaluate(phong_params, wi, wo, precision="float32").dtype == np.float64
    with pytest.raises(ValueError, match="precision"):
        ts.evaluate(p, wi, wo, precision="half")


# -- the likelihood's choice and the posterior it samples ---------------------------------------
def _table(model, truth, n, rel_noise, rng):
    """Samples of ``model`` (numpy backend: the float64 reference) at ``truth``, half of them near
    the specular plane, with relative Gaussian noise; one channel."""
    ti = rng.uniform(0.05, 1.3, n)
    to = rng.uniform(0.05, 1.3, n)
    po = np.where(
        np.arange(n) % 2 == 0, np.pi + rng.normal(0, 0.1, n), rng.uniform(0, 2 * np.pi, n)
    )
    wi = spherical_to_vector(ti, np.zeros(n))
    wo = spherical_to_vector(to, po)
    f = model.evaluate(truth, wi, wo, backend="numpy")
    sig = rel_noise * f + 1e-4
    return SampleTable(
        ti,
        np.zeros(n),
        to,
        po,
        np.full(n, "R"),
        f + sig * rng.standard_normal(n),
        sig,
        np.zeros(n, np.int32),
    )


def _setup(rel_noise, seed, alpha=0.05):
    model = models.get(
        "torrance-sparrow", distribution="ggx", shadowing="smith", fresnel="conductor"
    )
    truth = {"kd": 0.05, "ks": 0.8, "m": alpha, "eta": 1.5, "k": 3.5}
    rng = np.random.default_rng(seed)
    table = _table(model, truth, 1500, rel_noise, rng)
    space = ParameterSpace.build(model, ["R"], discrepancy=False)
    lik = Likelihood(model, table, space)
    lsq = fit_least_squares(lik, n_starts=4, seed=seed)
    probes = np.vstack([lsq.x, np.clip(rng.multivariate_normal(lsq.x, lsq.cov, 16), *space.bounds)])
    return lik, lsq, probes


def test_likelihood_takes_float32_only_where_its_rounding_is_negligible():
    # 3 % noise on 1500 rows: float32's ~1e-7 relative rounding moves ln L by ~1e-4
    lik, _lsq, probes = _setup(0.03, 1)
    choice, diff = lik.choose_precision(probes)
    assert choice == "float32" and lik.precision == "float32", diff
    assert diff < F32_LNL_LIMIT and "points checked" in lik.precision_reason
    # The same material measured to 1e-7: rounding is as large as the noise → float64
    lik, _lsq, probes = _setup(1e-7, 1)
    choice, diff = lik.choose_precision(probes)
    assert choice == "float64" and lik.precision == "float64" and diff >= F32_LNL_LIMIT
    assert "would move ln L" in lik.precision_reason
    # no float32 kernels: float64, and no difference measured
    phong = models.get("phong")
    table = SampleTable(
        np.full(5, 0.3), np.zeros(5), np.full(5, 0.4), np.zeros(5), np.full(5, "R"),
        np.full(5, 0.1), np.full(5, 0.01), np.zeros(5, np.int32),
    )  # fmt: skip
    space = ParameterSpace.build(phong, ["R"], discrepancy=False)
    lik = Likelihood(phong, table, space)
    choice, diff = lik.choose_precision(np.mean(space.bounds, axis=0))
    assert choice == "float64" and np.isnan(diff) and "no float32 kernels" in lik.precision_reason


def test_sampling_precision_is_float64_again_after_the_block_whatever_happens():
    lik, _lsq, probes = _setup(0.03, 1)
    with pytest.raises(RuntimeError, match="sampler failed"):
        with lik.sampling_precision(probes) as (choice, _diff):
            assert choice == "float32" and lik.precision == "float32"
            raise RuntimeError("sampler failed")
    assert lik.precision == "float64"  # least squares and the verdicts after it stay float64


def test_float32_samples_the_float64_posterior():
    """A sharp lobe (α = 0.02) at 3 % noise: the posterior sampled with the model in float32 has
    the float64 one's means and sds within Monte-Carlo error (4 combined MC sds: with 5
    parameters × 2 moments the family-wise false-alarm rate is ≈ 10·6e-5)."""
    lik, lsq, probes = _setup(0.03, 2, alpha=0.02)
    assert lik.choose_precision(probes)[0] == "float32"
    # Each chain runs until its bulk and tail ESS (fitting.convergence, which counts the walkers'
    # differences) reach 250 and R̂ < 1.01, the bounds below then have an ESS > 200 to stand on:
    # a fixed 6000 steps passed 200 on one machine and gave 192 on another (an AMD Zen 3: its
    # kernels' float32 rounding, and so the chain, differ), a precondition failing, not the test.
    opt = McmcOptions(
        walkers=32, max_steps=12000, moves="de", target=ConvergenceTarget(ess_min=250.0)
    )
    runs = {}
    for precision in ("float64", "float32"):
        lik.precision = precision
        res = run_mcmc(
            lik.log_prob, lsq.x, lik.space.bounds, opt, rng=np.random.default_rng(5),
            scale=lsq.cov,
        )  # fmt: skip
        runs[precision] = res
    a, b = runs["float64"], runs["float32"]
    ess = np.minimum(a.ess, b.ess)
    assert np.all(ess > 200), ess
    ma, mb = a.flat.mean(axis=0), b.flat.mean(axis=0)
    sa, sb = a.flat.std(axis=0), b.flat.std(axis=0)
    # MC sd of a mean: sd/√ESS; of an sd: sd/√(2·ESS) (Gaussian posterior)
    assert np.all(np.abs(ma - mb) <= 4 * sa * np.sqrt(1 / a.ess + 1 / b.ess)), (ma - mb) / sa
    assert np.all(np.abs(sb / sa - 1) <= 4 * np.sqrt(1 / (2 * a.ess) + 1 / (2 * b.ess)))

"""Hard cases of docs/design.md §5: grazing angles, the pole, retro and opposite directions, m from
1e-4 to 3, Phong n up to 1e6, η = 1, η < 1, large k. Hypothesis over the domain plus explicit
limits computed independently of the model code."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.special import erfc

from brdfdata.directions import spherical_to_vector
from fitting import models
from fitting.models import fresnel

SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)

TS_VARIANTS = [
    {"distribution": d, "shadowing": s, "fresnel": f}
    for d in ("beckmann", "ggx")
    for s in ("v-cavity", "smith", "smith-rational", "smith-correlated")
    for f in ("dielectric", "conductor")
]

# θ: anywhere, exactly 0, or within 1e-12…1e-3 of the horizon (either side is tested by φ)
theta_st = st.one_of(
    st.floats(0.0, np.pi / 2),
    st.just(0.0),
    st.floats(-12, -3).map(lambda e: np.pi / 2 - 10.0**e),
)
phi_st = st.floats(0.0, 2 * np.pi)
dir_st = st.tuples(theta_st, phi_st).map(lambda tp: spherical_to_vector(*tp))
m_st = st.floats(-4, np.log10(3.0)).map(lambda e: 10.0**e)


def _check(model, params, wi, wo):
    wi, wo = np.atleast_2d(wi), np.atleast_2d(wo)
    f = model.evaluate(params, wi, wo)
    lf = model.log_evaluate(params, wi, wo)
    assert np.all(np.isfinite(f)) and np.all(f >= 0), (f, params)
    assert not np.any(np.isnan(lf))
    # log f = −inf only where f = 0; f = 0 elsewhere only by underflow (log f < −700)
    assert np.all(f[lf == -np.inf] == 0), (f, lf)
    assert np.all((lf[f == 0] == -np.inf) | (lf[f == 0] < -700)), (f, lf)
    ok = f > 1e-250
    np.testing.assert_allclose(lf[ok], np.log(f[ok]), rtol=1e-14, atol=1e-12)
    # Helmholtz reciprocity to 1e-12 relative (the formulas are symmetric in ω_i, ω_o)
    fr = model.evaluate(params, wo, wi)
    np.testing.assert_allclose(fr, f, rtol=1e-12, atol=0)
    return f


@pytest.mark.parametrize("options", TS_VARIANTS, ids=lambda o: "-".join(o.values()))
@SETTINGS
@given(
    wi=dir_st,
    wo=dir_st,
    m=m_st,
    ior=st.floats(0.6, 3.0),
    eta=st.floats(0.05, 5.0),
    k=st.floats(0.0, 50.0),
    kd=st.sampled_from([0.0, 0.3]),
)
def test_torrance_sparrow_stays_finite(options, wi, wo, m, ior, eta, k, kd):
    model = models.get("torrance-sparrow", **options)
    p = {"kd": kd, "ks": 1.0, "m": m, "ior": ior, "eta": eta, "k": k}
    p = {n: p[n] for n in model.parameter_names}
    _check(model, p, wi, wo)
    # the same point as one of W = 2 parameter sets (kernel path with a table)
    both = {n: np.array([[v], [v]]) for n, v in p.items()}
    f2 = model.evaluate(both, np.atleast_2d(wi), np.atleast_2d(wo))
    np.testing.assert_array_equal(f2[0], f2[1])


@pytest.mark.parametrize("name", ["phong", "phong-normalized", "blinn-phong"])
@SETTINGS
@given(wi=dir_st, wo=dir_st, n=st.floats(0, 6).map(lambda e: 10.0**e), kd=st.sampled_from([0, 0.2]))
def test_phong_family_stays_finite(name, wi, wo, n, kd):
    _check(models.get(name), {"kd": kd, "ks": 1.0, "n": n}, wi, wo)


# --- explicit limits, computed independently ---------------------------------------------


def test_normal_incidence_and_retro_at_the_pole():
    # θ_i = θ_o = 0 (φ undefined): h = n̂, tan θ_h = 0, D = 1/(π m²), G = 1, F = F(1)
    z = np.array([[0.0, 0.0, 1.0]])
    for m in (1e-4, 0.3, 3.0):
        for opts in TS_VARIANTS:
            model = models.get("torrance-sparrow", **opts)
            p = {"kd": 0.0, "ks": 1.0, "m": m, "ior": 1.5, "eta": 0.2, "k": 3.0}
            p = {n: p[n] for n in model.parameter_names}
            f0 = (
                ((1.5 - 1) / 2.5) ** 2
                if opts["fresnel"] == "dielectric"
                else ((0.2 - 1) ** 2 + 9.0) / ((0.2 + 1) ** 2 + 9.0)
            )
            expected = f0 / (np.pi * m**2) / 4
            assert model.evaluate(p, z, z)[0] == pytest.approx(expected, rel=1e-13)


def test_opposite_directions():
    g = spherical_to_vector(np.pi / 2 - 1e-6, 0.4)
    model = models.get("torrance-sparrow", shadowing="smith")
    p = {"kd": 0.3, "ks": 1.0, "m": 0.2}
    # ω_i = −ω_o: one of them is below the horizon → exactly 0 and log −inf
    assert model.evaluate(p, g, -g) == 0.0
    assert model.log_evaluate(p, g, -g) == -np.inf
    # both grazing at opposite azimuths (the mirror pair at the horizon): h = n̂, D = 1/(π m²),
    # and with Smith each G₁/cos θ → 2√π/m, so f → kd/π + F(ω·h)/(π m²)·(2√π/m)²/4
    # = kd/π + F/m⁴: finite although cos θ_i cos θ_o = 1e-12. Relative corrections are
    # O(cos θ · 2√π/m) ≈ 2e-5 per direction, hence rel=1e-4.
    g2 = g * np.array([-1, -1, 1])
    f = model.evaluate(p, g, g2)
    c = np.cos(np.pi / 2 - 1e-6)  # ω·h
    assert f == pytest.approx(0.3 / np.pi + fresnel.dielectric(c, 1.5) / 0.2**4, rel=1e-4)


def test_retro_reflection_grazing():
    for theta in (0.3, np.pi / 2 - 1e-6, np.pi / 2 - 1e-12):
        w = spherical_to_vector(theta, 1.0)
        for opts in TS_VARIANTS:
            model = models.get("torrance-sparrow", **opts)
            p = {"kd": 0.0, "ks": 1.0, "m": 0.5, "ior": 1.5, "eta": 0.2, "k": 3.0}
            f = model.evaluate({n: p[n] for n in model.parameter_names}, w, w)
            assert np.isfinite(f) and f >= 0


def test_smith_grazing_limit_is_finite_and_correct():
    # As θ_o → 90°, G₁(ω_o)/cos θ_o → 2√π/(m sin θ_o) (exact Beckmann Λ). So f tends to
    # ks D(h) F G₁(ω_i)/(4 cos θ_i) · 2√π/m with h the half vector of the limiting pair.
    m, theta_i = 0.3, 0.9
    wi = spherical_to_vector(theta_i, 0.0)[None]
    model = models.get("torrance-sparrow", shadowing="smith", fresnel="none")
    p = {"kd": 0.0, "ks": 1.0, "m": m}
    wo_lim = np.array([[-1.0, 0.0, 0.0]])  # exactly on the horizon
    h = (wi + wo_lim) / np.linalg.norm(wi + wo_lim)
    t2 = (h[0, 0] ** 2 + h[0, 1] ** 2) / h[0, 2] ** 2
    d = np.exp(-t2 / m**2) / (np.pi * m**2 * h[0, 2] ** 4)
    a = 1 / (m * np.tan(theta_i))
    lam = (-erfc(a) + np.exp(-a * a) / (a * np.sqrt(np.pi))) / 2
    g1_i = 1 / (1 + lam)
    limit = d * g1_i / (4 * np.cos(theta_i)) * 2 * np.sqrt(np.pi) / m
    for eps in (1e-6, 1e-9, 1e-12):
        wo = spherical_to_vector(np.pi / 2 - eps, np.pi)[None]
        # the relative change of f is O(ε) (first-order in cos θ_o), so 1e-5 is generous
        assert model.evaluate(p, wi, wo)[0] == pytest.approx(limit, rel=1e-5)
    # exactly at the horizon: zero by definition (below-the-horizon rule)
    assert model.evaluate(p, wi, wo_lim)[0] == 0.0


def test_v_cavity_grazing_limit():
    # V-cavity: G/(4 ci co) → ch/(2 vh ci) as co → 0 (the third term of the min vanishes less
    # fast); with ω_o grazing toward the mirror side f stays finite and converges.
    wi = spherical_to_vector(0.9, 0.0)[None]
    model = models.get("torrance-sparrow", fresnel="none")
    p = {"kd": 0.0, "ks": 1.0, "m": 0.3}
    vals = [
        model.evaluate(p, wi, spherical_to_vector(np.pi / 2 - e, np.pi)[None])[0]
        for e in (1e-6, 1e-9, 1e-12)
    ]
    assert np.all(np.isfinite(vals))
    assert vals[1] == pytest.approx(vals[2], rel=1e-8)


def test_near_mirror_roughness():
    # m = 1e-4: at the exact mirror direction D = 1/(π m²); 1e-2 rad off it f underflows, but
    # log f is the analytic −tan²θ_h/m² + ... (no −inf from underflow, no NaN)
    model = models.get("torrance-sparrow", shadowing="smith-correlated", fresnel="none")
    p = {"kd": 0.0, "ks": 1.0, "m": 1e-4}
    wi = spherical_to_vector(0.5, 0.0)[None]
    wo = spherical_to_vector(0.5, np.pi)[None]
    assert model.evaluate(p, wi, wo)[0] == pytest.approx(
        1 / (np.pi * 1e-8) / (4 * np.cos(0.5) ** 2), rel=1e-9
    )  # G ≈ 1 at this m and angle (Λ ~ e^(−a²), a ≈ 1.8e4)
    wo_off = spherical_to_vector(0.5 + 2e-2, np.pi)[None]  # tan²θ_h/m² ≈ 1e4: exp underflows
    assert model.evaluate(p, wi, wo_off)[0] == 0.0
    lf = model.log_evaluate(p, wi, wo_off)[0]
    h = wi + wo_off
    t2 = (h[0, 0] ** 2 + h[0, 1] ** 2) / h[0, 2] ** 2
    assert np.isfinite(lf)
    # log f = −t2/m² + log((1 + t2)²/(π m²)) − log(4 cos θ_i cos θ_o); G = 1 (a ~ 1e4)
    expected = (
        -t2 / 1e-8 + 2 * np.log1p(t2) - np.log(np.pi * 1e-8) - np.log(4 * wi[0, 2] * wo_off[0, 2])
    )
    assert lf == pytest.approx(expected, rel=1e-12)


def test_huge_phong_exponent():
    n = 1e6
    model = models.get("phong")
    wi = spherical_to_vector(0.4, 0.0)[None]
    for alpha in (0.0, 1e-4, 1e-3, 0.05):
        wo = spherical_to_vector(0.4 + alpha, np.pi)[None]  # α = angle between ω_i and r̂
        # (l̂·r̂)^n = cos(α)^n = exp(n log1p(−2 sin²(α/2))), evaluated independently
        expected = np.exp(n * np.log1p(-2 * np.sin(alpha / 2) ** 2))
        f = model.evaluate({"kd": 0.0, "ks": 1.0, "n": n}, wi, wo)[0]
        assert f == pytest.approx(expected, rel=1e-9, abs=1e-300)
        lf = model.log_evaluate({"kd": 0.0, "ks": 1.0, "n": n}, wi, wo)[0]
        assert lf == pytest.approx(n * np.log1p(-2 * np.sin(alpha / 2) ** 2), rel=1e-9, abs=1e-9)
    # l̂·r̂ < 0: the clamped base gives exactly the diffuse part
    wo = spherical_to_vector(1.4, 0.0)[None]
    assert model.evaluate({"kd": 0.5, "ks": 1.0, "n": 3.0}, wi, wo)[0] == 0.5 / np.pi


def test_fresnel_edge_cases_inside_the_model():
    rng = np.random.default_rng(0)
    wi = spherical_to_vector(rng.uniform(0, 1.5, 500), rng.uniform(0, 6.3, 500))
    wo = spherical_to_vector(rng.uniform(0, 1.5, 500), rng.uniform(0, 6.3, 500))
    ts = models.get("torrance-sparrow")
    # η = 1: no interface, F = 0, only the diffuse term remains
    np.testing.assert_array_equal(
        ts.evaluate({"kd": 0.4, "ks": 1, "m": 0.3, "ior": 1.0}, wi, wo), 0.4 / np.pi
    )
    assert np.all(ts.log_evaluate({"kd": 0.0, "ks": 1, "m": 0.3, "ior": 1.0}, wi, wo) == -np.inf)
    # η = 0.6: F = 1 where ω·h is below the critical cosine sqrt(1 − η²) = 0.8 (TIR)
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    tir = np.sum(wi * h, axis=1) < 0.8 - 1e-9
    assert 50 < tir.sum() < tir.size
    none = models.get("torrance-sparrow", fresnel="none")
    f_tir = ts.evaluate({"kd": 0.0, "ks": 1, "m": 0.3, "ior": 0.6}, wi, wo)
    np.testing.assert_allclose(
        f_tir[tir], none.evaluate({"kd": 0.0, "ks": 1, "m": 0.3}, wi, wo)[tir], rtol=1e-14
    )
    # k = 50: F within [0.97, 1], so f between 0.97 and 1 times the F = 1 model
    cond = models.get("torrance-sparrow", fresnel="conductor")
    f_k = cond.evaluate({"kd": 0.0, "ks": 1, "m": 0.3, "eta": 1.0, "k": 50.0}, wi, wo)
    f_1 = none.evaluate({"kd": 0.0, "ks": 1, "m": 0.3}, wi, wo)
    vh = np.sum(wi * h, axis=1)
    np.testing.assert_allclose(f_k, f_1 * fresnel.conductor(vh, 1.0, 50.0), rtol=1e-12)
    assert np.all(f_k <= f_1) and np.all(f_k >= 0.97 * f_1)
    # Brewster: for the seed form at ω·h = cos θ_B only R_s remains
    brewster = np.arctan(1.5)
    wi_b = spherical_to_vector(brewster, 0.0)[None]
    wo_b = spherical_to_vector(brewster, np.pi)[None]  # specular: h = n̂, ω·h = cos θ_B
    f_b = ts.evaluate({"kd": 0.0, "ks": 1, "m": 0.2, "ior": 1.5}, wi_b, wo_b)[0]
    rs, rp = fresnel.dielectric_sp(np.cos(brewster), 1.5)
    assert rp < 1e-28
    g1 = none.evaluate({"kd": 0.0, "ks": 1, "m": 0.2}, wi_b, wo_b)[0]
    assert f_b == pytest.approx(g1 * rs / 2, rel=1e-12)


# --- every registered model (fitting.models), on the parameter sets its entry declares --------


def _registry_cases():
    from fitting import models

    out = []
    for name in models.names():
        for options, sets in models.entry(name).checks:
            for i, p in enumerate(sets):
                out.append(pytest.param(name, dict(options), dict(p), id=f"{name}-{i}-{options}"))
    return out


@pytest.mark.parametrize(("name", "options", "params"), _registry_cases())
@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)
@given(wi=dir_st, wo=dir_st, kd=st.sampled_from([0.0, 0.3]))
def test_every_registered_model_stays_finite(name, options, params, wi, wo, kd):
    # finite, non-negative, log f consistent, reciprocal to 1e-12 — for each model the registry
    # holds, so a new model is covered by registering it
    model = models.get(name, **options)
    _check(model, dict(params, kd=kd) if "kd" in params else params, wi, wo)

"""Microfacet D and G against normalisation integrals and docs/design.md §6 reference values."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import dblquad, quad

from fitting.models import microfacet as mf


@pytest.mark.parametrize("m", [0.05, 0.1, 0.3, 0.5, 1.0])
@pytest.mark.parametrize("dist", ["beckmann", "ggx"])
def test_projected_area_normalisation(dist, m):
    # ∫ D cos θ_h dω = 2π ∫ D(θ) cos θ sin θ dθ; with t = tan θ, cos θ sin θ dθ = t cos⁴θ dt,
    # so the integrand is D(t)·t/(1 + t²)² on [0, ∞). Split at a few multiples of m so quad
    # resolves the peak; the GGX tail decays like t⁻³.
    d = mf.beckmann if dist == "beckmann" else mf.ggx

    def integrand(t):
        return 2 * np.pi * d(t * t, m) * t / (1 + t * t) ** 2

    pts = [0.0, m, 3 * m, 10 * m, 100 * m]
    total = sum(
        quad(integrand, a, b, epsabs=1e-13, epsrel=1e-12, limit=200)[0]
        for a, b in zip(pts[:-1], pts[1:], strict=True)
    )
    total += quad(integrand, pts[-1], np.inf, epsabs=1e-13, limit=200)[0]
    assert abs(total - 1.0) <= 1e-6


def test_seed_beckmann_is_normalised_beckmann_times_pi_over_4():
    c = np.linspace(0.05, 1.0, 50)
    for m in (0.05, 0.3, 1.0):
        t2 = (1 - c * c) / (c * c)
        # atol: where exp underflows into denormals only ~1e-320 absolute is left
        np.testing.assert_allclose(
            mf.beckmann_seed(c, m) / np.pi, mf.beckmann(t2, m) / 4, rtol=1e-12, atol=1e-300
        )


# docs/design.md §6: G1(a=0.5) = 0.83358 (rational 0.83125), G1(a=1) = 0.97549 (0.97659), 5
# decimals.
@pytest.mark.parametrize(
    ("a", "exact", "rational"), [(0.5, 0.83358, 0.83125), (1.0, 0.97549, 0.97659)]
)
def test_smith_g1_reference_values(a, exact, rational):
    assert abs(mf.smith_g1_beckmann(a) - exact) <= 1e-5
    assert abs(mf.smith_g1_beckmann_rational(a) - rational) <= 1e-5
    # the same through the /cos form used by the models (θ with 1/(m tan θ) = a, m = 0.4)
    m = 0.4
    theta = np.arctan(1 / (a * m))
    g = mf.g1_over_cos(np.cos(theta), np.sin(theta), m) * np.cos(theta)
    assert abs(g - exact) <= 1e-5
    g = mf.g1_over_cos(np.cos(theta), np.sin(theta), m, rational=True) * np.cos(theta)
    assert abs(g - rational) <= 1e-5


def test_smith_g1_from_its_definition():
    # Smith G1(ω) = cos θ / ∫ max(0, ω·h) D(h) dω_h (Heitz 2014 eq. 43), integrated directly.
    for dist, m, theta in [("beckmann", 0.4, 1.2), ("ggx", 0.5, 1.3), ("beckmann", 0.8, 0.7)]:
        d = mf.beckmann if dist == "beckmann" else mf.ggx
        wo = np.array([np.sin(theta), 0.0, np.cos(theta)])

        def integrand(t, phi, d=d, m=m, wo=wo):
            h = np.array([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)])
            return max(0.0, wo @ h) * d(np.tan(t) ** 2, m) * np.sin(t)

        proj = dblquad(integrand, 0, 2 * np.pi, 0, np.pi / 2, epsabs=1e-10, epsrel=1e-10)[0]
        expected = np.cos(theta) / proj
        got = mf.g1_over_cos(np.cos(theta), np.sin(theta), m, dist) * np.cos(theta)
        assert got == pytest.approx(expected, rel=1e-6)
        if dist == "ggx":
            assert mf.smith_g1_ggx(np.cos(theta), m) == pytest.approx(expected, rel=1e-6)


def test_g1_over_cos_has_finite_grazing_limit():
    # G1/cos θ → 2√π/(m sin θ) (exact Beckmann), 3.535/(m sin θ) (rational), 2/(α sin θ) (GGX)
    m = 0.3
    for eps in (1e-6, 1e-9, 0.0):
        c, s = np.sin(eps), np.cos(eps)
        assert mf.g1_over_cos(c, s, m) == pytest.approx(2 * np.sqrt(np.pi) / m, rel=1e-5)
        assert mf.g1_over_cos(c, s, m, rational=True) == pytest.approx(3.535 / m, rel=1e-5)
        assert mf.g1_over_cos(c, s, m, "ggx") == pytest.approx(2 / m, rel=1e-5)


def test_g1_at_normal_incidence_is_one():
    for kind in ("beckmann", "ggx"):
        assert mf.g1_over_cos(1.0, 0.0, 0.5, kind) == 1.0
    assert mf.g1_over_cos(1.0, 0.0, 0.5, rational=True) == 1.0


def test_correlated_is_at_least_separable():
    rng = np.random.default_rng(3)
    ci, co = rng.uniform(0.01, 1, (2, 200))
    si, so = np.sqrt(1 - ci**2), np.sqrt(1 - co**2)
    for dist in ("beckmann", "ggx"):
        sep = mf.g2_over_cos_cos(ci, si, co, so, 0.5, dist, "separable")
        cor = mf.g2_over_cos_cos(ci, si, co, so, 0.5, dist, "correlated")
        # 1/(1+Λi+Λo) ≥ 1/((1+Λi)(1+Λo)), equality only if a Λ vanishes
        assert np.all(cor >= sep * (1 - 1e-14))


def test_v_cavity_matches_seed_formula():
    rng = np.random.default_rng(4)
    ch, ci, co, vh = rng.uniform(0.05, 1, (4, 100))
    seed = np.minimum(1, np.minimum(2 * ch * co / vh, 2 * ch * ci / vh))
    np.testing.assert_array_equal(mf.v_cavity(ch, ci, co, vh), seed)

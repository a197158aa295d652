"""Microfacet distributions and shadowing-masking terms (docs/design.md §5), pure numpy.

These are the *reference* implementations: :mod:`fitting.models.microfacet_kernels` evaluates the
same formulas in a fused numba loop and the tests hold the two together. Angles are those of the
sample frame (+z normal). ``m`` is the RMS slope (Beckmann) or the GGX α — both the Mitsuba
``alpha``.

Shadowing terms are returned *divided by the cosines* they multiply in the BRDF, because G → 0 and
cos θ → 0 together at grazing angles and only the ratio has a finite, accurate limit
(docs/design.md §5 "hard cases"): e.g. for Smith G₁(ω)/cos θ → 2√π/(m sin θ) as θ → 90°.

References
----------
Beckmann & Spizzichino 1963; Torrance & Sparrow, JOSA 57(9), 1967; Blinn, SIGGRAPH 1977;
Walter, Marschner, Li, Torrance, "Microfacet models for refraction through rough surfaces",
EGSR 2007 (eqs. 25–27, 33–34); Heitz, "Understanding the masking-shadowing function in
microfacet-based BRDFs", JCGT 3(2), 2014 (eqs. 72, 86, 99).
"""

from __future__ import annotations

import numpy as np
from scipy.special import betainc, erfc, gammaln

__all__ = [
    "tan2_theta",
    "beckmann_seed",
    "beckmann",
    "ggx",
    "smith_lambda_beckmann",
    "smith_g1_beckmann",
    "smith_g1_beckmann_rational",
    "smith_g1_ggx",
    "g1_over_cos",
    "g2_over_cos_cos",
    "v_cavity",
    "anisotropic_d",
    "student_t",
    "smith_lambda_student_t",
    "projected_roughness",
    "rotate_tangent",
]

_SQRT_PI = np.sqrt(np.pi)


def tan2_theta(v: np.ndarray) -> np.ndarray:
    """tan²θ of vectors (..., 3) from their components: accurate at the pole, +inf at z = 0."""
    v = np.asarray(v, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return (v[..., 0] ** 2 + v[..., 1] ** 2) / v[..., 2] ** 2


def beckmann_seed(cos_beta, m) -> np.ndarray:
    """The seed lecture's Beckmann term D = exp(−(tan β/m)²) / (4 m² cos⁴ β) (not normalised).

    Used with f = D G F / (π cos θ_i cos θ_o); note D_seed/π ≡ D_norm/4 (docs/design.md §5).
    """
    c = np.asarray(cos_beta, dtype=np.float64)
    m = np.asarray(m, dtype=np.float64)
    t2 = (1.0 - c * c) / (c * c)
    return np.exp(-t2 / (m * m)) / (4.0 * m * m * c**4)


def beckmann(tan2_beta, m) -> np.ndarray:
    """π-normalised Beckmann D = exp(−tan²β/m²) / (π m² cos⁴β), sr⁻¹ (Walter et al. 2007, eq. 25).

    Written with cos⁻⁴β = (1 + tan²β)² so that it needs only tan²β; ∫ D cos β dω = 1.
    Returns 0 where the exponential underflows (also for tan²β = ∞).
    """
    t2 = np.asarray(tan2_beta, dtype=np.float64)
    m2 = np.asarray(m, dtype=np.float64) ** 2
    e = np.exp(-t2 / m2)
    with np.errstate(invalid="ignore", over="ignore"):
        d = e * (1.0 + t2) ** 2 / (np.pi * m2)
    return np.where(e > 0.0, d, 0.0)


def ggx(tan2_beta, alpha) -> np.ndarray:
    """GGX / Trowbridge-Reitz D = α² / (π cos⁴β (α² + tan²β)²), sr⁻¹ (Walter et al. 2007, eq. 33).

    Written as α² ((1 + tan²β)/(α² + tan²β))² / π, which needs only tan²β and stays finite
    for tan²β → ∞ (limit α²/π, the heavy GGX tail).
    """
    t2 = np.asarray(tan2_beta, dtype=np.float64)
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    with np.errstate(invalid="ignore"):
        r = np.where(np.isinf(t2), 1.0, (1.0 + t2) / (a2 + t2))
    return a2 * r * r / np.pi


def _a(cos_theta, sin_theta, m):
    # a = 1/(m tan θ) = cos θ/(m sin θ), +inf at the pole.
    with np.errstate(divide="ignore"):
        return np.asarray(cos_theta, float) / (np.asarray(m, float) * np.asarray(sin_theta, float))


def smith_lambda_beckmann(a) -> np.ndarray:
    """Exact Smith Λ for Beckmann: Λ(a) = (erf a − 1)/2 + e^(−a²)/(2 a √π) (Walter 2007, eq. 27)."""
    a = np.asarray(a, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -0.5 * erfc(a) + np.exp(-a * a) / (2.0 * a * _SQRT_PI)
    return np.where(np.isinf(a), 0.0, lam)


def smith_g1_beckmann(a) -> np.ndarray:
    """Exact Smith G₁ = 1/(1 + Λ(a)), a = 1/(m tan θ) (Walter 2007, eq. 27)."""
    return 1.0 / (1.0 + smith_lambda_beckmann(a))


def smith_g1_beckmann_rational(a) -> np.ndarray:
    """Walter et al. 2007 eq. 27 rational fit of the Beckmann G₁ (≤ 0.35 % error), used by Mitsuba.

    G₁ = (3.535 a + 2.181 a²)/(1 + 2.276 a + 2.577 a²) for a < 1.6, else 1.
    """
    a = np.asarray(a, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        g = (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
    return np.where(a < 1.6, g, 1.0)


def smith_g1_ggx(cos_theta, alpha) -> np.ndarray:
    """Exact GGX Smith G₁ = 2/(1 + sqrt(1 + α² tan²θ)) (Walter 2007, eq. 34)."""
    c = np.asarray(cos_theta, dtype=np.float64)
    s2 = np.maximum(1.0 - c * c, 0.0)
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    return 2.0 * c / (c + np.sqrt(c * c + a2 * s2))


def _c_lambda(cos_theta, sin_theta, m, distribution, rational, gamma=None):
    """cos θ · Λ(θ), finite at the horizon (where Λ → ∞ but cos θ Λ → m sin θ/(2√π))."""
    c = np.asarray(cos_theta, dtype=np.float64)
    s = np.asarray(sin_theta, dtype=np.float64)
    m = np.asarray(m, dtype=np.float64)
    if distribution == "student-t":
        return _c_lambda_student_t(c, m * s, gamma)
    if distribution == "ggx":
        # (R − c)/2 with R = sqrt(c² + α²s²), written as α²s²/(2(R + c)): no cancellation
        q = np.sqrt(c * c + m * m * s * s) + c
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(q > 0, 0.5 * m * m * s * s / q, 0.0)
    a = _a(c, s, m)
    if rational:
        # 1/G1 − 1 = Λ, so cosΛ = cos/G1 − cos; cos/G1 = m s (1 + 2.276a + 2.577a²)/(3.535 + 2.181a)
        with np.errstate(invalid="ignore"):
            cg = m * s * (1.0 + 2.276 * a + 2.577 * a * a) / (3.535 + 2.181 * a)
        return np.where(a < 1.6, cg - c, 0.0)
    # a Λ(a) = (e^(−a²)/√π − a erfc a)/2, and cos θ = a m sin θ.
    with np.errstate(invalid="ignore"):
        al = 0.5 * (np.exp(-a * a) / _SQRT_PI - a * erfc(a))
        out = m * s * al
    return np.where(np.isinf(a), 0.0, out)


def g1_over_cos(
    cos_theta, sin_theta, m, distribution="beckmann", rational=False, gamma=None
) -> np.ndarray:
    """Smith G₁(ω)/cos θ, computed as 1/(cos θ + cos θ·Λ) so that it stays finite at θ = 90°.

    ``distribution`` is "beckmann", "ggx" or "student-t" (with ``gamma``); ``rational`` selects
    Walter's rational G₁ (Beckmann). Only the product m·sin θ enters, so an anisotropic
    distribution passes m = 1 and sin θ → :func:`projected_roughness` · sin θ.
    """
    return 1.0 / (cos_theta + _c_lambda(cos_theta, sin_theta, m, distribution, rational, gamma))


def g2_over_cos_cos(
    cos_i, sin_i, cos_o, sin_o, m, distribution="beckmann", kind="separable", gamma=None
) -> np.ndarray:
    """Smith G₂/(cos θ_i cos θ_o) for the separable or height-correlated form (Heitz 2014).

    separable:   G₂ = G₁(ω_i) G₁(ω_o)           (eq. 98; Mitsuba's choice)
    correlated:  G₂ = 1/(1 + Λ(ω_i) + Λ(ω_o))   (eq. 99)
    kind "rational" is the separable form with the rational Beckmann G₁.
    """
    if kind == "correlated":
        li = _c_lambda(cos_i, sin_i, m, distribution, False, gamma)
        lo = _c_lambda(cos_o, sin_o, m, distribution, False, gamma)
        return 1.0 / (cos_i * cos_o + cos_o * li + cos_i * lo)
    rational = kind == "rational"
    return g1_over_cos(cos_i, sin_i, m, distribution, rational, gamma) * g1_over_cos(
        cos_o, sin_o, m, distribution, rational, gamma
    )


def v_cavity(cos_h, cos_i, cos_o, v_dot_h) -> np.ndarray:
    """The seed's V-cavity G = min{1, 2(n·h)(n·v)/(v·h), 2(n·h)(n·l)/(v·h)}.

    Torrance & Sparrow 1967; Blinn 1977. Here v = ω_o, l = ω_i, v·h = l·h.
    """
    return np.minimum(1.0, np.minimum(2.0 * cos_h * cos_o / v_dot_h, 2.0 * cos_h * cos_i / v_dot_h))


# -- anisotropic and heavy-tailed distributions ---------------------------------------------------


def rotate_tangent(v: np.ndarray, phi0) -> tuple[np.ndarray, np.ndarray]:
    """Tangential components (x', y') of vectors (..., 3) in the frame whose x' axis is the
    sample-frame direction (cos φ₀, sin φ₀, 0):
    x' = x cos φ₀ + y sin φ₀,  y' = −x sin φ₀ + y cos φ₀."""
    v = np.asarray(v, dtype=np.float64)
    c, s = np.cos(phi0), np.sin(phi0)
    return v[..., 0] * c + v[..., 1] * s, -v[..., 0] * s + v[..., 1] * c


def projected_roughness(xt, yt, alpha_x, alpha_y) -> np.ndarray:
    """u = sqrt((α_x x')² + (α_y y')²) = α(φ) sin θ for a unit direction with tangent-frame
    components (x', y'): the roughness projected on its azimuth, times sin θ (Heitz 2014,
    eq. 80; Mitsuba's ``project_roughness_2``). Smith's Λ of an anisotropic distribution is the
    isotropic one with m sin θ → u."""
    return np.hypot(np.asarray(alpha_x) * xt, np.asarray(alpha_y) * yt)


def anisotropic_d(sx, sy, sz, alpha_x, alpha_y, distribution="beckmann", gamma=None):
    """Anisotropic D(h), sr⁻¹, from the tangent-frame components of any positive multiple s of
    the half vector (s = ω_i + ω_o; h = s/|s|), with q = (s_x²/α_x² + s_y²/α_y²)/s_z² and
    cos⁻⁴θ_h = (1 + (s_x² + s_y²)/s_z²)²:

    beckmann   D = exp(−q) / (π α_x α_y cos⁴θ_h)            (Walter et al. 2007 eq. 25 with
                                                              α_x ≠ α_y; Heitz 2014 eq. 82)
    ggx        D = 1 / (π α_x α_y cos⁴θ_h (1 + q)²)          (Heitz 2014, eq. 85)
    student-t  D = 1 / (π α_x α_y cos⁴θ_h (1 + q/(γ−1))^γ)   (Ribardière et al. 2017, eq. 6)

    Each satisfies ∫ D cos θ_h dω_h = 1. Student-t interpolates GGX (γ = 2) and Beckmann
    (γ → ∞); its tail falls as tan^(−2γ)θ_h (GGX: tan⁻⁴).
    """
    sx, sy, sz = (np.asarray(a, dtype=np.float64) for a in (sx, sy, sz))
    ax, ay = np.asarray(alpha_x, dtype=np.float64), np.asarray(alpha_y, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t2 = (sx * sx + sy * sy) / (sz * sz)
        q = ((sx / ax) ** 2 + (sy / ay) ** 2) / (sz * sz)
        inv_c4 = (1.0 + t2) ** 2
        norm = 1.0 / (np.pi * ax * ay)
        if distribution == "beckmann":
            e = np.exp(-q)
            return np.where(e > 0.0, e * inv_c4 * norm, 0.0)
        if distribution == "ggx":
            r = (1.0 + t2) / (1.0 + q)
            return np.where(np.isfinite(r), r * r * norm, norm * np.square(ax * ay) / ax**2)
        g = np.asarray(gamma, dtype=np.float64)
        return inv_c4 * norm * np.exp(-g * np.log1p(q / (g - 1.0)))


def student_t(tan2_beta, alpha, gamma) -> np.ndarray:
    """Isotropic Student-t ("STD") D = 1/(π α² cos⁴β (1 + tan²β/((γ−1)α²))^γ), sr⁻¹
    (Ribardière, Bringier, Meneveaux, Simonot, CGF 36(2), 2017, eq. 6). γ > 1.5."""
    t2 = np.asarray(tan2_beta, dtype=np.float64)
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    g = np.asarray(gamma, dtype=np.float64)
    return (1.0 + t2) ** 2 / (np.pi * a2) * np.exp(-g * np.log1p(t2 / ((g - 1.0) * a2)))


def smith_lambda_student_t(mu, gamma) -> np.ndarray:
    """Exact Smith Λ of the Student-t distribution, μ = cot θ/α (γ > 3/2).

    Derived here from Smith's Λ(μ) = (1/μ)∫_μ^∞ (q − μ) P₂(q) dq (Heitz 2014, eq. 72) with the
    1-D slope marginal P₂(q) = K (1 + q²/ν)^(½−γ), ν = γ − 1, K = √(ν/π) Γ(γ−½)/Γ(γ) (a
    Student-t with 2ν degrees of freedom scaled by 1/√2):

        Λ = K ν (1 + μ²/ν)^(3/2−γ) / ((2γ − 3) μ)  −  ½ I_{ν/(ν+μ²)}(ν, ½)

    with I the regularised incomplete beta function. γ = 2 gives GGX's (√(1 + 1/μ²) − 1)/2
    exactly. (Ribardière et al. publish a rational fit of the second term; this is exact.)
    """
    mu = np.asarray(mu, dtype=np.float64)
    g = np.asarray(gamma, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = _c_lambda_student_t(mu, np.ones_like(mu), g) / mu
    return np.where(np.isinf(mu), 0.0, lam)


def _c_lambda_student_t(c, u, gamma):
    """cos θ · Λ with μ = c/u, written so that c → 0 stays finite: u·I₁ − c·I₀ (see above)."""
    c = np.asarray(c, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    g = np.asarray(gamma, dtype=np.float64)
    nu = g - 1.0
    log_k = 0.5 * np.log(nu / np.pi) + gammaln(g - 0.5) - gammaln(g)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        mu2 = (c / u) ** 2
        first = u * np.exp(log_k + (1.5 - g) * np.log1p(mu2 / nu)) * nu / (2.0 * g - 3.0)
        second = 0.5 * c * betainc(nu, 0.5, nu / (nu + mu2))
        out = first - second
    return np.where(u > 0.0, np.maximum(out, 0.0), 0.0)

"""jax.jit float64 versions of gonio's BRDF models: the peer of benchmarks/bench_peers_models.py
(issue 23, item 1).

Each function is the same equations as gonio's numpy reference (``backend="numpy"``), written the
way a JAX user would write them: jnp operations on whole arrays, parameters of shape (W, 1)
broadcast against per-pair quantities of shape (N,), masks by ``jnp.where``, one ``jax.jit`` per
model (options are static arguments, so each option set is its own compiled executable).

Signature of every model: ``f(params: dict[str, (W, 1) array], wi (N, 3), wo (N, 3)) -> (W, N)``,
f_r in sr⁻¹ (not times cos θ_o), 0 below the horizon. Importing this module switches JAX to
float64 (``jax_enable_x64``); the caller sets XLA_FLAGS and the CPU affinity before importing it.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

__all__ = ["lambert", "phong", "blinn_phong", "torrance_sparrow", "torrance_sparrow_anisotropic"]

_UP = (0.0, 0.0, 1.0)


# -- shared pieces --------------------------------------------------------------------------------


def _above(wi, wo):
    return (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)


def _safe_pairs(wi, wo):
    """The horizon mask and the pairs with the normal substituted below the horizon (the
    reference evaluates on safe directions and masks afterwards)."""
    above = _above(wi, wo)
    up = jnp.asarray(_UP)
    return above, jnp.where(above[:, None], wi, up), jnp.where(above[:, None], wo, up)


def _half_vector_parts(wi, wo):
    """s = ω_i + ω_o, |s| and ω·h (the mean of ω_i·h and ω_o·h, clipped to [0, 1])."""
    s = wi + wo
    norm = jnp.linalg.norm(s, axis=1)
    vh = jnp.clip(0.5 * (jnp.sum(wi * s, axis=1) + jnp.sum(wo * s, axis=1)) / norm, 0.0, 1.0)
    return s, norm, vh


def _fresnel_dielectric(cos_theta, ior):
    """Mirrors fitting.models.fresnel.dielectric (via dielectric_sp): F = (R_s + R_p)/2, TIR → 1."""
    c = jnp.clip(cos_theta, 0.0, 1.0)
    eta2 = ior * ior
    u2 = (eta2 - 1.0) + c * c
    tir = u2 <= 0.0
    u = jnp.sqrt(jnp.where(tir, 0.0, u2))
    rs = ((c - u) / (c + u)) ** 2
    rp = ((eta2 * c - u) / (eta2 * c + u)) ** 2
    degenerate = tir | ~jnp.isfinite(rs) | ~jnp.isfinite(rp)
    return jnp.where(degenerate, 1.0, 0.5 * (rs + rp))


def _fresnel_conductor(cos_theta, eta, k):
    """Conductor Fresnel for η + ik in real arithmetic (K. D. Möller, *Optics*, 1988; the form
    Mitsuba and gonio's kernel `fitting.models.microfacet_kernels.stage_fresnel` use), algebraically
    equal to the complex form of fitting.models.fresnel.conductor. The peer gets the fastest formula
    a JAX user would pick: the complex form measured ~4× slower here, which would compare formulas,
    not compilers. F = (r_s + r_p)/2 = (t1 − t2) t3 / ((t1 + t2)(t3 + t4)), clipped at 1; 0/0 → 1.
    """
    c = jnp.clip(cos_theta, 0.0, 1.0)
    c2 = c * c
    s2 = 1.0 - c2
    tmp = (eta * eta - k * k - 1.0) + c2  # η² − k² − sin²θ
    a2pb2 = jnp.sqrt(tmp * tmp + 4.0 * eta * eta * k * k)
    a = jnp.sqrt(jnp.maximum(0.5 * (a2pb2 + tmp), 0.0))
    t1 = a2pb2 + c2
    t2 = 2.0 * c * a
    t3 = a2pb2 * c2 + s2 * s2
    t4 = t2 * s2
    den = (t1 + t2) * (t3 + t4)
    return jnp.where(den > 0.0, jnp.minimum((t1 - t2) * t3 / den, 1.0), 1.0)


def _fresnel(params, vh, fresnel):
    if fresnel == "dielectric":
        return _fresnel_dielectric(vh, params["ior"])
    if fresnel == "conductor":
        return _fresnel_conductor(vh, params["eta"], params["k"])
    raise ValueError(f"fresnel={fresnel!r} is not in the JAX peer (dielectric, conductor)")


def _c_lambda(c, s, m, distribution, rational):
    """cos θ · Λ(θ), finite at the horizon; mirrors fitting.models.microfacet._c_lambda (GGX exact,
    or Beckmann with Walter's rational G₁)."""
    if distribution == "ggx":
        q = jnp.sqrt(c * c + m * m * s * s) + c
        return jnp.where(q > 0, 0.5 * m * m * s * s / q, 0.0)
    if not rational:
        raise ValueError("exact Beckmann Smith (erfc) is not in the JAX peer")
    a = c / (m * s)
    cg = m * s * (1.0 + 2.276 * a + 2.577 * a * a) / (3.535 + 2.181 * a)
    return jnp.where(a < 1.6, cg - c, 0.0)


def _smith_over_4cc(ci, si, co, so, m, distribution, shadowing):
    """Separable Smith G₂/(4 cos θ_i cos θ_o) = ¼ G₁/cos · G₁/cos; mirrors
    0.25 · fitting.models.microfacet.g2_over_cos_cos (kind "separable" or "rational"; the rational
    fit is Beckmann-only, so GGX uses its exact G₁ either way, as the reference does)."""
    if shadowing not in ("smith", "smith-rational"):
        raise ValueError(f"shadowing={shadowing!r} is not in the JAX peer")
    rational = shadowing == "smith-rational" and distribution == "beckmann"
    g1_i = 1.0 / (ci + _c_lambda(ci, si, m, distribution, rational))
    g1_o = 1.0 / (co + _c_lambda(co, so, m, distribution, rational))
    return 0.25 * g1_i * g1_o


def _v_cavity_over_4cc(ch, ci, co, vh):
    """Mirrors fitting.models.microfacet.v_cavity(...) / (4 cos θ_i cos θ_o) (the seed's V-cavity
    G)."""
    g = jnp.minimum(1.0, jnp.minimum(2.0 * ch * co / vh, 2.0 * ch * ci / vh))
    return g / (4.0 * (ci * co))


# -- models ---------------------------------------------------------------------------------------


@jax.jit
def lambert(params, wi, wo):
    """f = kd/π; mirrors fitting.models.seed.Lambert._numpy."""
    return jnp.where(_above(wi, wo), params["kd"] / jnp.pi, 0.0)


def _phong_family(params, wi, wo, base, log_norm):
    """f = kd/π + ks N(n) base^n above the horizon, the lobe as exp(log ks + log N + n log base)
    (log base per pair, shared by the W sets); mirrors fitting.models.seed.PhongFamily._numpy."""
    above = _above(wi, wo)
    base = jnp.where(above, jnp.clip(base, 0.0, 1.0), 0.0)
    ks = params["ks"]
    spec = jnp.exp(jnp.log(ks) + log_norm + params["n"] * jnp.log(base))
    spec = jnp.where((base > 0.0) & (ks > 0.0), spec, 0.0)
    return jnp.where(above, params["kd"] / jnp.pi + spec, 0.0)


@jax.jit
def phong(params, wi, wo):
    """The seed's Phong, base l̂·r̂ = 2 cos θ_i cos θ_o − ω_i·ω_o; mirrors
    fitting.models.seed.PhongFamily._numpy / _base with name "phong" (no normalisation)."""
    base = 2.0 * (wi[:, 2] * wo[:, 2]) - jnp.sum(wi * wo, axis=1)
    return _phong_family(params, wi, wo, base, 0.0)


@jax.jit
def blinn_phong(params, wi, wo):
    """Normalised Blinn-Phong, base cos θ_h, N(n) = (n+2)(n+4)/(8π(2^(−n/2) + n)); mirrors
    fitting.models.seed.PhongFamily._numpy with name "blinn-phong" and
    fitting.models.seed.blinn_phong_normalization."""
    s = wi + wo
    base = s[:, 2] / jnp.linalg.norm(s, axis=1)
    n = params["n"]
    norm = (n + 2.0) * (n + 4.0) / (8.0 * jnp.pi * (jnp.exp2(-0.5 * n) + n))
    return _phong_family(params, wi, wo, base, jnp.log(norm))


@functools.partial(jax.jit, static_argnames=("distribution", "shadowing", "fresnel"))
def torrance_sparrow(
    params, wi, wo, *, distribution="beckmann", shadowing="v-cavity", fresnel="dielectric"
):
    """f = kd/π + ks D G F/(4 cos θ_i cos θ_o) with the π-normalised Beckmann or GGX D; mirrors
    fitting.models.seed.TorranceSparrow._numpy (D: fitting.models.microfacet.beckmann / ggx; G:
    v_cavity or g2_over_cos_cos; F: fitting.models.fresnel.dielectric / conductor)."""
    above, wi, wo = _safe_pairs(wi, wo)
    s, norm, vh = _half_vector_parts(wi, wo)
    t2 = (s[:, 0] ** 2 + s[:, 1] ** 2) / s[:, 2] ** 2
    ci, co = wi[:, 2], wo[:, 2]
    m = params["m"]
    m2 = m * m
    if distribution == "beckmann":
        e = jnp.exp(-t2 / m2)
        d = jnp.where(e > 0.0, e * (1.0 + t2) ** 2 / (jnp.pi * m2), 0.0)
    else:
        r = jnp.where(jnp.isinf(t2), 1.0, (1.0 + t2) / (m2 + t2))
        d = m2 * r * r / jnp.pi
    if shadowing == "v-cavity":
        g = _v_cavity_over_4cc(s[:, 2] / norm, ci, co, vh)
    else:
        si, so = jnp.hypot(wi[:, 0], wi[:, 1]), jnp.hypot(wo[:, 0], wo[:, 1])
        g = _smith_over_4cc(ci, si, co, so, m, distribution, shadowing)
    f = params["kd"] / jnp.pi + params["ks"] * d * g * _fresnel(params, vh, fresnel)
    return jnp.where(above, f, 0.0)


@functools.partial(jax.jit, static_argnames=("distribution", "shadowing", "fresnel"))
def torrance_sparrow_anisotropic(
    params, wi, wo, *, distribution="beckmann", shadowing="smith", fresnel="dielectric"
):
    """Anisotropic Torrance-Sparrow with axes rotated by φ₀; mirrors
    fitting.models.anisotropic.TorranceSparrowAnisotropic._numpy (D:
    fitting.models.microfacet.anisotropic_d; G: Smith with the projected roughness u = |(α_x x', α_y
    y')| of fitting.models.microfacet.projected_roughness, or the V-cavity)."""
    above, wi, wo = _safe_pairs(wi, wo)
    ax, ay, phi0 = params["alpha_x"], params["alpha_y"], params["phi0"]
    cos_phi, sin_phi = jnp.cos(phi0), jnp.sin(phi0)

    def rotate(v):  # tangent-frame components (W, N): fitting.models.microfacet.rotate_tangent
        return v[:, 0] * cos_phi + v[:, 1] * sin_phi, -v[:, 0] * sin_phi + v[:, 1] * cos_phi

    s, norm, vh = _half_vector_parts(wi, wo)
    sx, sy = rotate(s)
    sz = s[:, 2]
    ci, co = wi[:, 2], wo[:, 2]
    t2 = (sx * sx + sy * sy) / (sz * sz)
    q = ((sx / ax) ** 2 + (sy / ay) ** 2) / (sz * sz)
    d_norm = 1.0 / (jnp.pi * ax * ay)
    if distribution == "beckmann":
        e = jnp.exp(-q)
        d = jnp.where(e > 0.0, e * (1.0 + t2) ** 2 * d_norm, 0.0)
    else:
        r = (1.0 + t2) / (1.0 + q)
        d = jnp.where(jnp.isfinite(r), r * r * d_norm, d_norm * (ax * ay) ** 2 / ax**2)
    if shadowing == "v-cavity":
        g = _v_cavity_over_4cc(sz / norm, ci, co, vh)
    else:
        xi, yi = rotate(wi)
        xo, yo = rotate(wo)
        ui, uo = jnp.hypot(ax * xi, ay * yi), jnp.hypot(ax * xo, ay * yo)
        g = _smith_over_4cc(ci, ui, co, uo, 1.0, distribution, shadowing)
    f = params["kd"] / jnp.pi + params["ks"] * d * g * _fresnel(params, vh, fresnel)
    return jnp.where(above, f, 0.0)


_MODELS = {
    "lambert": lambert,
    "phong": phong,
    "blinn-phong": blinn_phong,
    "torrance-sparrow": torrance_sparrow,
    "torrance-sparrow-anisotropic": torrance_sparrow_anisotropic,
}


def get(name: str, **options):
    """The JAX peer of gonio's ``models.get(name, **options)``: ``f(params, wi, wo) -> (W, N)``."""
    fn = _MODELS[name]
    return functools.partial(fn, **options) if options else fn

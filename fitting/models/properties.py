"""Measured properties of BRDF models (docs/design.md §5): albedo, reciprocity, isotropy, energy.

The directional albedo ρ(ω_o) = ∫ f_r(ω_i, ω_o) cos θ_i dω_i (seed lecture, "Energy
conservation"; by reciprocity the same as ∫ f cos θ_o dω_o at fixed ω_i) is computed by
quadrature over the *half vector* h: ω_i = 2(ω_o·h)h − ω_o, dω_i = 4 (ω_o·h) dω_h (Walter et
al. 2007, eq. 14). Every lobe here (Phong about the mirror direction, Blinn-Phong, microfacet)
peaks at h = n̂ whatever ω_o is, so one grid resolves them all: Gauss-Legendre panels in θ_h
with geometrically shrinking widths toward θ_h = 0 (down to 1e-6 of the range, enough for
m = 1e-4 and Phong n = 1e6), ending exactly where ω_i meets the horizon, and the trapezoid
rule in φ_h (periodic integrand).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from brdfdata.directions import spherical_to_vector, uniform_hemisphere
from fitting import models

__all__ = [
    "directional_albedo",
    "check_reciprocity",
    "check_isotropy",
    "check_energy",
    "check_finite",
    "property_table",
]


def _half_vector_nodes(theta_o: float, phi_o: float, n: int, theta_min: float = 1e-6):
    """Half vectors h (M, 3) and weights (M,) for ∫ g(h) dω_h over the h that map to ω_i
    above the horizon.

    For h at azimuth φ (Δ = φ − φ_o), ω_i·ẑ = 2(ω_o·h) cos θ − cos θ_o is positive exactly for
    2θ < ψ + π/2 with ψ = atan2(sin θ_o cos Δ, cos θ_o) (write ω_i·ẑ = cos θ_o cos 2θ +
    sin θ_o cos Δ sin 2θ). Integrating θ ∈ [0, θ_max(φ)] keeps the horizon off the interior
    of the panels, so the integrand is smooth in θ and smooth and periodic in φ (trapezoid rule
    converges geometrically).
    """
    n_phi = 2 * n
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    psi = np.arctan2(np.sin(theta_o) * np.cos(phi - phi_o), np.cos(theta_o))
    theta_max = 0.5 * (psi + 0.5 * np.pi)
    frac = np.concatenate(
        [[0.0], np.geomspace(theta_min, 1.0, 1 + int(np.ceil(np.log2(1 / theta_min))))]
    )
    x, w = np.polynomial.legendre.leggauss(max(8, n // 8))
    a, b = frac[:-1, None], frac[1:, None]
    u = (0.5 * (b - a) * x + 0.5 * (b + a)).ravel()  # nodes on [0, 1]
    wu = (0.5 * (b - a) * w).ravel()
    theta = theta_max[:, None] * u[None, :]
    weight = (2.0 * np.pi / n_phi) * theta_max[:, None] * wu[None, :] * np.sin(theta)
    h = spherical_to_vector(theta, np.broadcast_to(phi[:, None], theta.shape))
    return h.reshape(-1, 3), weight.ravel()


def directional_albedo(
    model: models.Model, params: Mapping, theta_o, n: int = 128, phi_o: float = 0.0
) -> np.ndarray:
    """ρ(θ_o) = ∫ f_r(ω_i, ω_o) cos θ_i dω_i by half-vector quadrature (see module docstring).

    ``theta_o`` (rad, < π/2) scalar or 1-D; parameters scalars (result shape of theta_o) or
    (W, 1) arrays (result (W,) + shape of theta_o). ``n`` sets the grid: 2n φ nodes and n/8
    Gauss points on each of ~21 θ panels. Dimensionless.
    """
    theta_o_arr = np.atleast_1d(np.asarray(theta_o, dtype=np.float64))
    out = []
    for t in theta_o_arr:
        wo = spherical_to_vector(t, phi_o)
        h, w_h = _half_vector_nodes(float(t), phi_o, n)
        oh = h @ wo
        wi = 2.0 * oh[:, None] * h - wo
        f = model.evaluate(params, wi, np.broadcast_to(wo, wi.shape))
        integrand = f * np.maximum(wi[:, 2], 0.0) * 4.0 * np.maximum(oh, 0.0)
        out.append(integrand @ w_h)
    res = np.stack(out, axis=-1)
    return res.reshape(res.shape[:-1] + np.shape(theta_o))


def _rel(a, b):
    scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), np.finfo(float).tiny)
    return np.abs(a - b) / scale


def check_reciprocity(model, params, n: int = 2000, rng=0) -> float:
    """Largest relative |f(ω_i, ω_o) − f(ω_o, ω_i)| over ``n`` random pairs (Helmholtz)."""
    rng = np.random.default_rng(rng)
    wi, wo = uniform_hemisphere(n, rng), uniform_hemisphere(n, rng)
    return float(np.max(_rel(model.evaluate(params, wi, wo), model.evaluate(params, wo, wi))))


def check_isotropy(model, params, n: int = 2000, rng=0) -> float:
    """Largest relative change of f when both directions rotate by a random angle about +z."""
    rng = np.random.default_rng(rng)
    wi, wo = uniform_hemisphere(n, rng), uniform_hemisphere(n, rng)
    ang = rng.uniform(0.0, 2.0 * np.pi, n)
    c, s = np.cos(ang), np.sin(ang)

    def rot(v):
        return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], -1)

    return float(
        np.max(_rel(model.evaluate(params, wi, wo), model.evaluate(params, rot(wi), rot(wo))))
    )


def check_energy(model, params, theta_o=None, n: int = 128) -> float:
    """Largest directional albedo over θ_o (default 0…89.9°); ≤ 1 for energy conservation."""
    if theta_o is None:
        theta_o = np.radians(np.array([0.0, 15.0, 30.0, 45.0, 60.0, 70.0, 80.0, 85.0, 89.0, 89.9]))
    return float(np.max(directional_albedo(model, params, theta_o, n=n)))


def check_finite(model, params, n: int = 2000, rng=0) -> bool:
    """f finite and ≥ 0, log f never NaN, on random pairs plus the hard geometries of docs/design.md
    §5 (normal incidence, retro-reflection, grazing within 1e-6 rad, opposite directions)."""
    rng = np.random.default_rng(rng)
    wi, wo = uniform_hemisphere(n, rng), uniform_hemisphere(n, rng)
    eps = 1e-6
    g = spherical_to_vector(np.pi / 2 - eps, 0.3)
    hard_i = np.array([[0, 0, 1.0], [0, 0, 1.0], g, g, g, [0.6, 0, 0.8]])
    hard_o = np.array([[0, 0, 1.0], g, g, g * [-1, -1, 1], -g, [-0.6, 0, -0.8]])
    wi, wo = np.concatenate([wi, hard_i]), np.concatenate([wo, hard_o])
    f = model.evaluate(params, wi, wo)
    lf = model.log_evaluate(params, wi, wo)
    return bool(np.all(np.isfinite(f)) and np.all(f >= 0) and not np.any(np.isnan(lf)))


def _table_cases(names=None):
    """(name, options, parameter sets) of every registered model's ``checks``: lobes with all the
    weight (kd = 0, ks = 1) and F ≡ 1 where the model allows, so the albedo measures the lobe's
    normalisation itself (:mod:`fitting.models.catalogue`)."""
    out = []
    for name in names if names is not None else models.names():
        for options, cases in models.entry(name).checks:
            out.append((name, dict(options), [dict(c) for c in cases]))
    return out


def property_table(n: int = 64, tolerance: float = 2e-3, names=None) -> list[dict]:
    """Measured properties of every registered model (for ``gonio models --check``), or of
    ``names`` only.

    One row per (model, options): ``reciprocal`` (max relative error ≤ 1e-12), ``isotropic``
    (≤ 1e-9: rotating the vectors perturbs them by rounding, which a narrow lobe amplifies),
    ``energy_conserving`` (max albedo ≤ 1 + ``tolerance``, the quadrature error at
    this ``n``), ``finite`` (see :func:`check_finite`), the measured numbers behind them, the
    parameter sets used, and the model's declared flags for comparison.
    """
    rows = []
    for name, options, cases in _table_cases(names):
        model = models.get(name, **options)
        recip = max(check_reciprocity(model, p, n=500) for p in cases)
        iso = max(check_isotropy(model, p, n=500) for p in cases)
        albedo = max(check_energy(model, p, n=n) for p in cases)
        finite = all(check_finite(model, p, n=500) for p in cases)
        rows.append(
            {
                "model": name,
                "options": dict(model.options),
                "reciprocal": recip <= 1e-12,
                "energy_conserving": albedo <= 1.0 + tolerance,
                "isotropic": iso <= 1e-9,
                "finite": finite,
                "max_reciprocity_error": recip,
                "max_isotropy_error": iso,
                "max_albedo": albedo,
                "parameters": cases,
                "declared": dict(model.flags),
            }
        )
    return rows

"""Tabulate an analytic BRDF as an RGL tensor file that plain Mitsuba 3 loads with its ``measured``
plugin — the export fallback for models no Mitsuba built-in reproduces (e.g. the seed's V-cavity
Torrance-Sparrow).

The file follows the adaptive parameterization of Dupuy & Jakob (2018) (field layout in
:mod:`brdfdata.formats.rgl`), with choices that suit a known analytic lobe:

* ``jacobian`` = 0: the table holds f_r·cos θ_o itself (no D/(4σ) factor), so ``ndf`` and
  ``sigma`` are not used by evaluation (they are written — D of the hint roughness, σ = 1 — only
  because the plugin requires them);
* ``vndf``: per θ_i, the density over u_m = (√(θ_m/(π/2)), (φ_m − φ_i + π)/(2π)) of a half-vector
  mixture ½·D_wi(ω_m) + ½·(2/π)(ω_i·ω_m)·[cos θ_o(ω_m) > 0]: the visible normals of a microfacet
  lobe of the fit's roughness (Heitz 2014, D_wi = G₁(ω_i) max(0, ω_i·ω_m) D(ω_m)/cos θ_i) and
  the half vectors of ω_o uniform over the hemisphere (the broad part), times the Jacobian
  |dω_m/du_m| = 2π² u_θ sin θ_m. Table nodes therefore crowd where the lobe is, while the
  diffuse part keeps half of them;
* ``rgb``: f_r(ω_i, ω_o)·cos θ_o at the nodes (k, l)/(n − 1) of the sample square mapped through
  that warp (ω_o the mirror of ω_i about ω_m); at nodes whose ω_o falls below the horizon the
  continuation f_r(ω_i, ω_o mirrored to the upper side)·cos θ_o (negative), so that bilinear
  interpolation crosses zero at the horizon; ``luminance`` the clamped channel mean (sampling
  only).

How close Mitsuba's evaluation of the file comes to the model is measured, not assumed:
:func:`closeness` evaluates the file with our reader (which matches Mitsuba's ``measured`` to
float32 rounding, tests/brdfdata/test_import_rgl.py) on random direction pairs.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.special import erf

from brdfdata.directions import spherical_to_vector
from brdfdata.formats.rgl import Warp2D, load_rgl, u2phi, u2theta
from brdfdata.formats.tensor_file import write_tensor_file

__all__ = ["TabulateOptions", "tabulate_rgl", "write_tabulated", "closeness", "Closeness"]

Evaluate = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class TabulateOptions:
    """Resolution: ``n_theta_i`` incidence slices over [0, π/2] (``spacing``), an
    ``n_grid``² table per slice, a ``n_vndf``² warp; ``m`` and ``distribution`` the lobe that
    shapes the warp (the fit's roughness); ``description`` goes into the file."""

    n_theta_i: int = 32
    n_grid: int = 64
    n_vndf: int = 128
    m: float = 0.3
    distribution: str = "beckmann"
    description: str = "gonio tabulated model"
    spacing: str = "cos"


def _theta_nodes(n: int, spacing: str) -> np.ndarray:
    """θ_i slices: uniform in cos θ_i ("cos", denser towards grazing, where a lobe's f·cos θ_o
    changes fastest with θ_i) or uniform in θ_i ("uniform")."""
    t = np.linspace(0.0, 1.0, n)
    return np.arccos(1 - t) if spacing == "cos" else t * np.pi / 2


def _ndf(cos_m: np.ndarray, m: float, distribution: str) -> np.ndarray:
    """Normalised D(ω_m) (∫ D cos θ_m dω = 1), Beckmann or GGX, 0 below the horizon."""
    c2 = np.clip(cos_m, 1e-12, 1.0) ** 2
    t2 = (1 - c2) / c2
    if distribution == "ggx":
        d = m * m / (np.pi * c2 * c2 * (m * m + t2) ** 2)
    else:
        d = np.exp(-t2 / (m * m)) / (np.pi * m * m * c2 * c2)
    return np.where(cos_m > 0, d, 0.0)


def _g1(cos_i: float, m: float, distribution: str) -> float:
    """Smith G₁ of the lobe (exact Λ) at incidence cos θ_i."""
    if cos_i >= 1.0:
        return 1.0
    tan_i = np.sqrt(1 - cos_i * cos_i) / max(cos_i, 1e-12)
    if distribution == "ggx":
        return 2.0 / (1.0 + np.sqrt(1.0 + (m * tan_i) ** 2))
    a = 1.0 / (m * tan_i)
    lam = (erf(a) - 1) / 2 + np.exp(-a * a) / (2 * a * np.sqrt(np.pi))
    return 1.0 / (1.0 + lam)


def _vndf_slice(theta_i: float, opts: TabulateOptions) -> np.ndarray:
    """The warp density (n_vndf, n_vndf) over (u_φ rows, u_θ columns) for one incidence."""
    u = np.linspace(0.0, 1.0, opts.n_vndf)
    ut, up = np.meshgrid(u, u, indexing="xy")
    theta_m, phi_m = u2theta(ut), u2phi(up)  # φ relative to φ_i = 0
    wm = spherical_to_vector(theta_m, phi_m)
    wi = spherical_to_vector(theta_i, 0.0)
    dot = wm @ wi
    cos_i = max(float(wi[2]), 1e-6)
    lobe = _g1(cos_i, opts.m, opts.distribution) * np.maximum(dot, 0.0)
    lobe *= _ndf(wm[..., 2], opts.m, opts.distribution) / cos_i
    cos_o = 2 * dot * wm[..., 2] - wi[2]
    # Uniform ω_o over the hemisphere (p = 1/2π, so p(ω_m) = 4(ω_i·ω_m)/2π): unlike a cosine
    # law it keeps nodes near the horizon, where f = (f·cos θ_o)/cos θ_o is most sensitive.
    diffuse = (2 / np.pi) * np.maximum(dot, 0.0) * (cos_o > 0)
    jac = 2 * np.pi**2 * ut * np.sin(theta_m)
    density = (0.5 * lobe + 0.5 * diffuse) * jac
    # A floor keeps every cell reachable (the inverse warp needs a positive density).
    return density + 1e-6 * density.max()


def tabulate_rgl(evaluate: Evaluate, opts: TabulateOptions | None = None) -> dict[str, np.ndarray]:
    """The fields of an RGL tensor file tabulating ``evaluate(wi, wo)`` → f_r (N, 3) in sr⁻¹
    (module docstring), in the order Mitsuba's loader expects none of (it reads by name)."""
    opts = opts or TabulateOptions()
    theta_i = _theta_nodes(opts.n_theta_i, opts.spacing)
    phi_i = np.zeros(1)
    vndf = np.stack([_vndf_slice(t, opts) for t in theta_i])[None]
    warp = Warp2D(vndf, [phi_i, theta_i], normalize=True)
    n = opts.n_grid
    g = np.linspace(0.0, 1.0, n)
    sx, sy = np.meshgrid(g, g, indexing="xy")
    s = np.stack([sx.ravel(), sy.ravel()], axis=1)
    rgb = np.zeros((1, theta_i.size, 3, n, n))
    for j, t in enumerate(theta_i):
        u_m, _ = warp.sample(s, [np.zeros(len(s)), np.full(len(s), t)])
        wm = spherical_to_vector(u2theta(u_m[:, 0]), u2phi(u_m[:, 1]))
        wi = np.repeat(spherical_to_vector(t, 0.0)[None], len(s), axis=0)
        wo = 2 * np.sum(wm * wi, axis=1, keepdims=True) * wm - wi
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        # Below the horizon Mitsuba never evaluates, but bilinear interpolation reads those
        # nodes: store the smooth continuation f(ω_i, ω_o mirrored above) · cos θ_o (< 0), so
        # f·cos θ_o crosses zero at the horizon instead of dropping to 0 a cell early.
        mirrored = wo * np.where(wo[:, 2:3] < 0, [1.0, 1.0, -1.0], 1.0)
        mirrored[:, 2] = np.maximum(mirrored[:, 2], 1e-9)
        with np.errstate(all="ignore"):
            f = np.asarray(evaluate(wi, mirrored), np.float64)
        vals = np.nan_to_num(f, nan=0.0, posinf=0.0, neginf=0.0) * wo[:, 2:3]
        rgb[0, j] = vals.T.reshape(3, n, n)
    lum = np.maximum(rgb.mean(axis=2), 0.0)
    lum = lum + 1e-6 * max(float(lum.max()), 1e-12)
    uu = np.linspace(0.0, 1.0, 128)
    ndf = np.tile(_ndf(np.cos(u2theta(uu)), opts.m, opts.distribution), (2, 1))
    return {
        "description": np.frombuffer(opts.description.encode("utf-8"), np.uint8).copy(),
        "phi_i": phi_i.astype(np.float32),
        "theta_i": theta_i.astype(np.float32),
        "sigma": np.ones((2, 128), np.float32),
        "ndf": ndf.astype(np.float32),
        "vndf": vndf.astype(np.float32),
        "luminance": lum.astype(np.float32),
        "rgb": rgb.astype(np.float32),
        "jacobian": np.zeros(1, np.uint8),
    }


def write_tabulated(path: str | os.PathLike, evaluate: Evaluate, opts=None) -> Path:
    """Write :func:`tabulate_rgl` as a tensor file at ``path``."""
    return write_tensor_file(path, tabulate_rgl(evaluate, opts))


@dataclass(frozen=True)
class Closeness:
    """|f_table − f_model|/f_model over random pairs where f·cos θ_o > 1 % of its maximum."""

    median: float
    p95: float
    n: int

    def line(self) -> str:
        return (
            f"median relative difference {100 * self.median:.2g} %, 95th percentile "
            f"{100 * self.p95:.2g} % over {self.n} random direction pairs"
        )


def closeness(path: str | os.PathLike, evaluate: Evaluate, n: int = 20000, seed: int = 0):
    """Measure how close the tabulated file at ``path`` evaluates to ``evaluate``."""
    rng = np.random.default_rng(seed)

    def dirs(k):
        ct = rng.uniform(0.05, 1.0, k)  # θ ≤ 87°: away from where f·cos θ_o → 0
        ph = rng.uniform(0, 2 * np.pi, k)
        st = np.sqrt(1 - ct**2)
        return np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=1)

    wi, wo = dirs(n), dirs(n)
    got = load_rgl(path).eval(wi, wo)
    want = np.asarray(evaluate(wi, wo), np.float64)
    fc = want * wo[:, 2:3]
    big = fc > 0.01 * fc.max(axis=0)
    rel = np.abs(got - want)[big] / want[big]
    return Closeness(float(np.median(rel)), float(np.percentile(rel, 95)), int(big.sum()))

"""Robust multi-start least squares in the sampled parameter space (issue 7 §3).

Torrance-Sparrow fits have local minima in m (a narrow lobe started wide, or the reverse), so
the fit is started from a deterministic set of points: every log parameter named ``m`` on the
grid {0.03, 0.1, 0.3, 0.6} (in bounds), other parameters at the middle of their box (geometric
middle for log parameters), plus seeded uniform draws from the box up to ``n_starts``.
Each start runs ``scipy.optimize.least_squares`` (trust-region reflective, bounds) with a robust
loss; the lowest cost wins.

The covariance is the Gauss-Newton estimate C = (JᵀJ)⁻¹ of the *plain* residuals at the optimum
(central differences). least_squares' own ``jac`` is scaled by the robust loss ρ′ and would
understate or overstate the width, so it is not used. With ``sigma`` weighting the residuals
are already normalised; with ``ngan`` weighting (no error model) C is scaled by the residual
variance 2·cost/(n − k).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from fitting.likelihood import Likelihood

__all__ = ["LsqResult", "fit_least_squares", "start_points", "M_GRID"]

M_GRID = (0.03, 0.1, 0.3, 0.6)


@dataclass
class LsqResult:
    """Best point ``x`` (sampled space), its ``cost`` ½Σr², covariance ``cov`` (sampled space,
    None when JᵀJ is singular), all start costs, and the residual count ``n``."""

    x: np.ndarray
    cost: float
    cov: np.ndarray | None
    costs: list[float]
    n: int
    weighting: str
    success: bool


def _inside(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    # least_squares needs strictly feasible starts.
    span = hi - lo
    return np.clip(x, lo + 1e-6 * span, hi - 1e-6 * span)


def start_points(lik: Likelihood, n_starts: int = 8, seed: int = 0) -> np.ndarray:
    """Deterministic seeded start points (S, D) in the sampled space."""
    space = lik.space
    lo, hi = space.bounds
    centre = 0.5 * (lo + hi)
    # A data-driven start for the diffuse albedo: the median of π f (what a Lambertian would be).
    f_all = np.concatenate([d.f for d in lik.data])
    kd0 = float(np.clip(np.pi * np.median(f_all), 0.0, 1.0)) if f_all.size else 0.5
    for i, s in enumerate(space.specs):
        if s.base == "kd":
            centre[i] = kd0 if not s.log else np.log(max(kd0, 1e-6))
        if s.base == "discrepancy":
            centre[i] = np.log(1e-2)
    centre = _inside(centre, lo, hi)
    m_idx = [i for i, s in enumerate(space.specs) if s.base == "m"]
    starts = []
    if m_idx:
        for m in M_GRID:
            x = centre.copy()
            for i in m_idx:
                x[i] = np.log(m) if space.specs[i].log else m
            starts.append(_inside(x, lo, hi))
    else:
        starts.append(centre)
    rng = np.random.default_rng(seed)
    while len(starts) < n_starts:
        starts.append(_inside(rng.uniform(lo, hi), lo, hi))
    return np.unique(np.array(starts), axis=0)


def _jacobian(fun, x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Central-difference Jacobian; one-sided at a bound."""
    r0 = fun(x)
    jac = np.empty((r0.size, x.size))
    for k in range(x.size):
        h = 1e-6 * max(1.0, abs(x[k]))
        xp, xm = x.copy(), x.copy()
        xp[k] = min(x[k] + h, hi[k])
        xm[k] = max(x[k] - h, lo[k])
        jac[:, k] = (fun(xp) - fun(xm)) / (xp[k] - xm[k])
    return jac


def fit_least_squares(
    lik: Likelihood,
    *,
    weighting: str = "sigma",
    loss: str | None = None,
    f_scale: float | None = None,
    n_starts: int = 8,
    seed: int = 0,
    starts: np.ndarray | None = None,
    max_nfev: int | None = None,
) -> LsqResult:
    """Multi-start bounded least squares of ``lik.residuals``. The discrepancy parameter (if
    any) is held at its start value: residuals do not depend on it. Nuisance parameters start
    at their prior's centre and carry their prior as residuals (σ weighting) or stay there.

    ``loss`` defaults to soft_l1 (f_scale 3: only residuals beyond ~3σ are down-weighted, so
    Gaussian data are fitted nearly as by plain L2) for ``sigma`` weighting and to linear for
    ``ngan`` (their published metric is plain L2).
    """
    space = lik.space
    lo, hi = space.bounds
    # The shared errors' nuisance parameters (fitting.nuisance) start at their prior's centre
    # and, with σ weighting, are fitted with their Gaussian prior as extra residuals x/σ_prior
    # (the posterior mode: without it the data alone cannot tell a scale from the amplitudes,
    # and the MCMC's first walkers need the angles' data-given width, often ≪ their prior's).
    # The discrepancy is held: residuals do not depend on it.
    nuisance = np.array([s.prior_sigma is not None for s in space.specs], dtype=bool)
    free = np.array([s.base != "discrepancy" for s in space.specs])
    if weighting != "sigma":
        free &= ~nuisance
    prior_sd = np.array([s.prior_sigma or 1.0 for s in space.specs])[free & nuisance]
    centre = np.array([s.prior_center for s in space.specs])
    prior_c = centre[free & nuisance]
    prior_cols = np.flatnonzero(nuisance[free])
    if loss is None:
        loss = "soft_l1" if weighting == "sigma" else "linear"
    if f_scale is None:
        f_scale = 3.0 if weighting == "sigma" else 1.0
    if starts is None:
        starts = start_points(lik, n_starts, seed)
    starts = np.array(starts, dtype=np.float64)
    starts[:, nuisance] = centre[nuisance]

    def make_fun(base: np.ndarray):
        def fun(xf: np.ndarray) -> np.ndarray:
            x = base.copy()
            x[free] = xf
            r = lik.residuals(x, weighting)
            if not prior_cols.size:
                return r
            return np.concatenate([r, (xf[prior_cols] - prior_c) / prior_sd])

        return fun

    best = None
    costs = []
    for x0 in starts:
        fun = make_fun(x0)
        res = least_squares(
            fun,
            x0[free],
            bounds=(lo[free], hi[free]),
            loss=loss,
            f_scale=f_scale,
            x_scale="jac",
            method="trf",
            max_nfev=max_nfev,
        )
        # Compare starts on the plain cost so different robust losses are comparable.
        plain = 0.5 * float(np.sum(fun(res.x) ** 2)) if loss == "linear" else float(res.cost)
        costs.append(plain)
        if best is None or plain < best[0]:
            x = x0.copy()
            x[free] = res.x
            best = (plain, x, res.success, fun)
    cost, x, success, fun = best
    n = lik.n_exact
    jac = _jacobian(fun, x[free], lo[free], hi[free])
    cov = None
    try:
        cf = np.linalg.inv(jac.T @ jac)
        r = fun(x[free])
        if weighting != "sigma":
            cf *= float(np.sum(r**2)) / max(n - int(free.sum()), 1)
        cov = np.zeros((x.size, x.size))
        cov[np.ix_(free, free)] = cf
    except np.linalg.LinAlgError:
        cov = None
    return LsqResult(x, cost, cov, costs, n, weighting, bool(success))

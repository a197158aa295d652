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

Large tables (:func:`polish_in_blocks`): from a start already in the optimum's basin, the same
objective is minimised by Levenberg–Marquardt on normal equations summed over blocks of rows,
so neither the Jacobian (n × k) nor any per-row array of the solver is ever held whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from fitting.likelihood import Likelihood

__all__ = ["LsqResult", "fit_least_squares", "polish_in_blocks", "start_points", "M_GRID"]

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


@dataclass(frozen=True)
class _Problem:
    """What the least squares of a likelihood fits: its free parameters (the discrepancy is
    held: residuals do not depend on it), the nuisances' prior residuals and the loss."""

    lo: np.ndarray
    hi: np.ndarray
    free: np.ndarray
    nuisance: np.ndarray
    centre: np.ndarray
    prior_cols: np.ndarray
    prior_c: np.ndarray
    prior_sd: np.ndarray
    #: Every parameter's prior σ (1 where it has none), for a subset of the free columns.
    prior_sd_all: np.ndarray
    loss: str
    f_scale: float

    @classmethod
    def of(cls, lik: Likelihood, weighting: str, loss: str | None, f_scale: float | None):
        space = lik.space
        lo, hi = space.bounds
        # The shared errors' nuisance parameters (fitting.nuisance) start at their prior's
        # centre and, with σ weighting, are fitted with their Gaussian prior as extra residuals
        # x/σ_prior (the posterior mode: without it the data alone cannot tell a scale from the
        # amplitudes, and the MCMC's first walkers need the angles' data-given width, often ≪
        # their prior's). The discrepancy is held: residuals do not depend on it.
        nuisance = np.array([s.prior_sigma is not None for s in space.specs], dtype=bool)
        free = np.array([s.base != "discrepancy" for s in space.specs])
        if weighting != "sigma":
            free &= ~nuisance
        centre = np.array([s.prior_center for s in space.specs])
        if loss is None:
            loss = "soft_l1" if weighting == "sigma" else "linear"
        if f_scale is None:
            f_scale = 3.0 if weighting == "sigma" else 1.0
        sd_all = np.array([s.prior_sigma or 1.0 for s in space.specs])
        return cls(
            lo,
            hi,
            free,
            nuisance,
            centre,
            np.flatnonzero(nuisance[free]),
            centre[free & nuisance],
            sd_all[free & nuisance],
            sd_all,
            loss,
            float(f_scale),
        )

    def prior_residuals(self, xf: np.ndarray) -> np.ndarray:
        return (xf[..., self.prior_cols] - self.prior_c) / self.prior_sd

    def rho(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ρ, ρ′) of scipy's loss at z = (r/f_scale)², so cost = ½ f_scale² Σ ρ and the
        gradient Σ ρ′ r ∂r/∂x: ``linear`` ρ = z; ``soft_l1`` ρ = 2(√(1 + z) − 1)."""
        z = (r / self.f_scale) ** 2
        if self.loss == "linear":
            return z, np.ones_like(z)
        if self.loss == "soft_l1":
            t = np.sqrt(1.0 + z)
            return 2.0 * (t - 1.0), 1.0 / t
        raise ValueError(f"the blockwise polish supports linear and soft_l1, not {self.loss!r}")


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
    prob = _Problem.of(lik, weighting, loss, f_scale)
    lo, hi, free, nuisance, centre = prob.lo, prob.hi, prob.free, prob.nuisance, prob.centre
    loss, f_scale = prob.loss, prob.f_scale
    if starts is None:
        starts = start_points(lik, n_starts, seed)
    starts = np.array(starts, dtype=np.float64)
    starts[:, nuisance] = centre[nuisance]

    def make_fun(base: np.ndarray, cols: np.ndarray = free):
        prior = np.flatnonzero(nuisance[cols])  # the free nuisances among `cols`
        c, sd = centre[cols][prior], prob.prior_sd_all[cols][prior]

        def fun(xf: np.ndarray) -> np.ndarray:
            x = base.copy()
            x[cols] = xf
            r = lik.residuals(x, weighting)
            if not prior.size:
                return r
            return np.concatenate([r, (xf[prior] - c) / sd])

        return fun

    def solve(x0: np.ndarray, cols: np.ndarray):
        fun = make_fun(x0, cols)
        res = least_squares(
            fun,
            x0[cols],
            bounds=(lo[cols], hi[cols]),
            loss=loss,
            f_scale=f_scale,
            x_scale="jac",
            method="trf",
            max_nfev=max_nfev,
        )
        # Compare starts on the plain cost so different robust losses are comparable.
        plain = 0.5 * float(np.sum(fun(res.x) ** 2)) if loss == "linear" else float(res.cost)
        x = x0.copy()
        x[cols] = res.x
        return plain, x, res.success

    # With the shared errors' nuisances free, the starts search the model's parameters alone,
    # the nuisances held at their prior's centre, and the best start is then polished with
    # everything free: the starts are there to find the model's basin (the m grid), and the
    # nuisances, a prior's width from their centre, do not move it — a realistic rig's 19
    # parameters fitted from all 4 starts reached one optimum in each repeat tried, at ~1 s a
    # start, where the 3 model parameters take 0.02 s (measured).
    search = free & ~nuisance if (nuisance & free).any() and len(starts) > 1 else free
    best = None
    costs = []
    for x0 in starts:
        plain, x, success = solve(x0, search)
        costs.append(plain)
        if best is None or plain < best[0]:
            best = (plain, x, success)
    if search is not free:
        best = solve(best[1], free)
    cost, x, success = best
    fun = make_fun(x)
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


#: Rows per block of the blockwise polish: a block's k + 1 (forward differences) or 2k (the
#: covariance's central ones) residual vectors stay a few MB whatever the table's size.
BLOCK_ROWS = 1 << 16


def _accumulate(lik: Likelihood, prob: _Problem, x: np.ndarray, steps: np.ndarray,
                weighting: str, central: bool):  # fmt: skip
    """Over every block of rows: (cost at x, gradient g, Gauss–Newton matrix H) with the loss's
    weights ρ′, by forward differences of signed ``steps`` (k,) per free parameter; or, with
    ``central``, (Σr² at x, 0, JᵀJ of the plain residuals) by differences between x + steps[0]
    and x − steps[1] ((2, k), one-sided where a step is 0 at a bound)."""
    cols = np.flatnonzero(prob.free)
    k = cols.size
    if central:
        batch = np.repeat(x[None, :], 2 * k + 1, axis=0)  # x + h_j, x − h_j, then x
        batch[np.arange(k), cols] += steps[0]
        batch[k + np.arange(k), cols] -= steps[1]
        width = steps[0] + steps[1]
    else:
        batch = np.repeat(x[None, :], k + 1, axis=0)  # x, then x + h_j
        batch[1 + np.arange(k), cols] += steps
    h_mat = np.zeros((k, k))
    grad = np.zeros(k)
    cost = 0.0

    def add(r: np.ndarray) -> None:
        nonlocal cost
        if central:
            jac = (r[:k] - r[k : 2 * k]) / width[:, None]
            cost += float(np.sum(r[2 * k] ** 2))
            h_mat[...] += jac @ jac.T
            return
        r0 = r[0]
        jac = (r[1:] - r0) / steps[:, None]
        rho, w = prob.rho(r0)
        cost += 0.5 * prob.f_scale**2 * float(np.sum(rho))
        grad[...] += (jac * w) @ r0
        h_mat[...] += (jac * w) @ jac.T

    for block in lik.exact_blocks(BLOCK_ROWS):
        add(lik.block_residuals(batch, block, weighting))
    if prob.prior_cols.size:
        add(prob.prior_residuals(batch[:, cols]))
    return cost, grad, h_mat


def polish_in_blocks(
    lik: Likelihood,
    x0: np.ndarray,
    *,
    weighting: str = "sigma",
    loss: str | None = None,
    f_scale: float | None = None,
    max_iter: int = 100,
) -> LsqResult:
    """:func:`fit_least_squares` from the single start ``x0`` (in the optimum's basin), in
    memory that does not grow with the rows beyond the data: Levenberg–Marquardt on the
    normal equations (Σ ρ′ JᵀJ) δ = −Σ ρ′ Jᵀr of the same residuals and loss, each sum taken
    over blocks of BLOCK_ROWS rows (:meth:`Likelihood.exact_blocks`), the block's Jacobian by
    forward differences with its k + 1 parameter vectors in one model call. Its stationary
    point is least_squares' (the same gradient vanishes; the ρ″ term least_squares adds only
    changes the path). Bounds: a step is clipped into the box and a parameter at a bound the
    gradient pushes outward is held for that step. The covariance is fit_least_squares': the
    plain residuals' central-difference (JᵀJ)⁻¹, summed the same way."""
    prob = _Problem.of(lik, weighting, loss, f_scale)
    free, lo, hi = prob.free, prob.lo[prob.free], prob.hi[prob.free]
    x = np.array(x0, dtype=np.float64)
    x[prob.nuisance & ~free] = prob.centre[prob.nuisance & ~free]

    def forward_steps(xf: np.ndarray) -> np.ndarray:
        h = np.sqrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(xf))  # scipy's 2-point step
        return np.where(xf + h > hi, -h, h)

    def at(xf: np.ndarray) -> np.ndarray:
        full = x.copy()
        full[free] = xf
        return full

    xf = np.clip(x[free], lo, hi)
    cost, grad, h_mat = _accumulate(lik, prob, at(xf), forward_steps(xf), weighting, False)
    lam, success = 1e-3, False
    for _ in range(max_iter):
        held = ((xf <= lo) & (grad > 0)) | ((xf >= hi) & (grad < 0))
        a = h_mat + lam * np.diag(np.diag(h_mat))
        a[held, :] = a[:, held] = 0.0
        a[held, held] = 1.0
        try:
            step = np.linalg.solve(a, -np.where(held, 0.0, grad))
        except np.linalg.LinAlgError:
            lam *= 10.0
            continue
        trial = np.clip(xf + step, lo, hi)
        new = _accumulate(lik, prob, at(trial), forward_steps(trial), weighting, False)
        if np.isfinite(new[0]) and new[0] <= cost:
            done = cost - new[0] <= 1e-12 * max(cost, 1e-300) or np.all(
                np.abs(trial - xf) <= 1e-10 * (np.abs(xf) + 1e-8)
            )
            xf, (cost, grad, h_mat) = trial, new
            lam = max(lam / 10.0, 1e-12)
            if done:
                success = True
                break
        else:
            lam *= 10.0
            if lam > 1e12:
                success = True  # no step lowers the cost: a minimum to the rounding of the sums
                break
    h = 1e-6 * np.maximum(1.0, np.abs(xf))  # _jacobian's steps, one-sided at a bound
    central = np.stack([np.minimum(xf + h, hi) - xf, xf - np.maximum(xf - h, lo)])
    r2, _, jtj = _accumulate(lik, prob, at(xf), central, weighting, True)
    cov = None
    try:
        cf = np.linalg.inv(jtj)
        if weighting != "sigma":
            cf *= r2 / max(lik.n_exact - int(free.sum()), 1)
        cov = np.zeros((x.size, x.size))
        cov[np.ix_(free, free)] = cf
    except np.linalg.LinAlgError:
        cov = None
    return LsqResult(at(xf), cost, cov, [cost], lik.n_exact, weighting, success)

"""Parallel tempering over an ensemble, and the modes a posterior's chain visited (issue 44 item 1:
the sampler and its mode accounting).

Why. An ensemble sampler's moves (stretch, differential evolution) propose from the spread of
the other walkers: walkers split between two modes propose jumps between them that land in the
valley and are refused, so the split stays as the start made it, and a mode no walker started in
is never found. Parallel tempering (Swendsen & Wang 1986; Earl & Deem, PCCP 7, 2005) runs copies
of the ensemble on tempered posteriors p_β(x) ∝ L(x)^β π(x), 0 < β ≤ 1: the hot copies see a
flattened likelihood and cross valleys, and swaps between neighbouring temperatures carry what
they find down to β = 1, whose chain alone is the posterior.

What. ``T`` temperatures × ``W`` walkers. Each step updates every temperature's ensemble with the
affine-invariant stretch move in two halves (Goodman & Weare 2010, the red-blue scheme emcee
uses: a = 2), then proposes a swap between each pair of neighbouring temperatures for every walker
(walker i of β_t with a random walker of β_{t−1}), accepted with probability
min(1, exp((β_{t−1} − β_t)(ln L_t − ln L_{t−1}))). The ladder starts geometric from β = 1 to
``beta_min`` and adapts during burn-in so that neighbouring swap rates even out (Vousden, Farr &
Mandel, MNRAS 455, 1919 (2016), eq. 11–13: log spacings move by κ(t)(A_i − A_{i+1}), κ decaying
as ν⁻¹ t₀/(t + t₀)); it is frozen for the kept half, so the kept chain is a Markov chain with a
fixed target. `gonio fit --sampler tempered` runs it as the fit's chain (fitting.tempered_run).
ptemcee is that paper's implementation but is not maintained for emcee 3 or numpy 2; this module
follows it.

Modes. :func:`mode_masses` assigns each kept draw of β = 1 to the nearest of the distinct optima
a multi-start search found (in the metric of each optimum's own covariance) and reports each
mode's share of the posterior mass, in words by :func:`describe_modes`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fitting.differences import stencil_hessian

__all__ = [
    "TemperingOptions",
    "TemperedChain",
    "parallel_tempering",
    "distinct_optima",
    "mode_masses",
    "describe_modes",
]

_STRETCH_A = 2.0

Optimum = tuple[np.ndarray, np.ndarray, float]  # (x̂, covariance, −ln p at x̂)


@dataclass(frozen=True)
class TemperingOptions:
    temperatures: int = 8
    walkers: int = 32  # per temperature (even: the two halves of the red-blue update)
    steps: int = 2000  # at most: the burn-in adapts the ladder and is discarded
    #: Steps of burn-in (the ladder adapts; then frozen). None: half of ``steps``.
    adapt_steps: int | None = None
    #: Steps between two calls of parallel_tempering's ``stop`` (after the burn-in).
    check_every: int = 100
    #: The hottest β: the likelihood's weight there. 1e-4 flattens a valley of 9000 nats to 1.
    beta_min: float = 1e-4
    #: Vousden et al.'s adaptation constants (their defaults: ν = 100 steps, t₀ = 1000).
    adapt_nu: float = 100.0
    adapt_t0: float = 1000.0
    seed: int = 0


@dataclass
class TemperedChain:
    """The β = 1 chain of every step, (S, W, D), its log-likelihoods (S, W), the burn-in (the
    first ``burn`` steps, while the ladder adapted), the final ladder and the swap acceptance
    between neighbours (T − 1,) over the kept steps."""

    history: np.ndarray
    history_log_like: np.ndarray
    burn: int
    betas: np.ndarray
    swap_acceptance: np.ndarray
    move_acceptance: float

    @property
    def chain(self) -> np.ndarray:
        """The kept β = 1 chain (N, W, D): the posterior's draws."""
        return self.history[self.burn :]

    @property
    def log_like(self) -> np.ndarray:
        return self.history_log_like[self.burn :]


def parallel_tempering(
    log_like: Callable[[np.ndarray], np.ndarray],
    log_prior: Callable[[np.ndarray], np.ndarray],
    start: np.ndarray,
    options: TemperingOptions | None = None,
    on_step: Callable[[int], None] | None = None,
    stop: Callable[[np.ndarray], bool] | None = None,
) -> TemperedChain:
    """Sample p(x) ∝ L(x) π(x). ``log_like`` and ``log_prior`` take (M, D) points and return
    (M,) values (−inf outside the prior); ``start`` is (T, W, D) or (W, D) (then every
    temperature starts from it). ``on_step(k)`` after step k (a progress bar); ``stop(chain)``
    with the kept β = 1 chain so far (N, W, D), every ``check_every`` steps after the burn-in:
    True ends the run there (a stopping rule), else it runs ``steps``."""
    opt = options or TemperingOptions()
    rng = np.random.default_rng(opt.seed)
    T, W = opt.temperatures, opt.walkers
    if W % 2 or W < 4:
        raise ValueError(f"walkers per temperature must be even and ≥ 4, not {W}")
    x = np.array(np.broadcast_to(start, (T, W, np.shape(start)[-1])), dtype=np.float64)
    D = x.shape[2]
    betas = np.geomspace(1.0, opt.beta_min, T) if T > 1 else np.ones(1)
    lp = log_prior(x.reshape(-1, D)).reshape(T, W)
    ll = np.where(np.isfinite(lp), log_like(x.reshape(-1, D)).reshape(T, W), -np.inf)
    burn = opt.steps // 2 if opt.adapt_steps is None else min(int(opt.adapt_steps), opt.steps - 1)
    hist_x = np.empty((opt.steps, W, D))
    hist_ll = np.empty((opt.steps, W))
    swaps_tried = np.zeros(max(T - 1, 0))
    swaps_done = np.zeros(max(T - 1, 0))
    moves_done = 0
    done = opt.steps
    for step in range(opt.steps):
        for half in (0, 1):
            moves_done += _stretch_half(x, ll, lp, betas, half, log_like, log_prior, rng)
        accepted = _swap(x, ll, lp, betas, rng)
        hist_x[step], hist_ll[step] = x[0], ll[0]
        if step >= burn:
            swaps_tried += W
            swaps_done += accepted
        elif T > 2:
            betas = _adapt_ladder(betas, accepted / W, step, opt)
        if on_step is not None:
            on_step(step)
        kept = step + 1 - burn
        if stop is not None and kept > 0 and kept % opt.check_every == 0:
            if stop(hist_x[burn : step + 1]):
                done = step + 1
                break
    return TemperedChain(
        history=hist_x[:done],
        history_log_like=hist_ll[:done],
        burn=burn,
        betas=betas,
        swap_acceptance=swaps_done / np.maximum(swaps_tried, 1),
        move_acceptance=moves_done / (done * T * W),
    )


def _stretch_half(x, ll, lp, betas, half, log_like, log_prior, rng) -> int:
    """Goodman & Weare's stretch move for one half of every temperature's walkers, the other
    half held (in place); returns how many moves were accepted."""
    T, W, D = x.shape
    n = W // 2
    mine = slice(half * n, (half + 1) * n)
    other = slice((1 - half) * n, (2 - half) * n)
    z = ((_STRETCH_A - 1.0) * rng.random((T, n)) + 1.0) ** 2 / _STRETCH_A
    partner = x[:, other][np.arange(T)[:, None], rng.integers(0, n, (T, n))]
    proposal = partner + z[:, :, None] * (x[:, mine] - partner)
    lp_new = log_prior(proposal.reshape(-1, D)).reshape(T, n)
    ll_new = np.full((T, n), -np.inf)
    ok = np.isfinite(lp_new)
    if ok.any():
        ll_new[ok] = log_like(proposal[ok])
    with np.errstate(invalid="ignore"):
        log_ratio = (
            (D - 1) * np.log(z) + betas[:, None] * (ll_new - ll[:, mine]) + lp_new - lp[:, mine]
        )
    accept = np.log(rng.random((T, n))) < np.where(np.isfinite(log_ratio), log_ratio, -np.inf)
    x[:, mine] = np.where(accept[:, :, None], proposal, x[:, mine])
    ll[:, mine] = np.where(accept, ll_new, ll[:, mine])
    lp[:, mine] = np.where(accept, lp_new, lp[:, mine])
    return int(accept.sum())


def _swap(x, ll, lp, betas, rng) -> np.ndarray:
    """One swap proposal per walker between each pair of neighbouring temperatures, hottest
    pair first (as ptemcee); returns accepted swaps per pair, (T − 1,)."""
    T, W, _ = x.shape
    accepted = np.zeros(max(T - 1, 0))
    for t in range(T - 1, 0, -1):
        cold = rng.permutation(W)
        d_beta = betas[t - 1] - betas[t]
        with np.errstate(invalid="ignore"):
            log_ratio = d_beta * (ll[t] - ll[t - 1, cold])
        acc = np.log(rng.random(W)) < np.where(np.isnan(log_ratio), -np.inf, log_ratio)
        hot_i, cold_i = np.nonzero(acc)[0], cold[acc]
        for arr in (x, ll, lp):
            hot_vals = arr[t, hot_i].copy()
            arr[t, hot_i] = arr[t - 1, cold_i]
            arr[t - 1, cold_i] = hot_vals
        accepted[t - 1] = acc.sum()
    return accepted


def _adapt_ladder(betas, rates, step, opt: TemperingOptions) -> np.ndarray:
    """Vousden et al. (2016) eq. 11–13: with T_i = 1/β_i and S_i = ln(T_i − T_{i−1}) for the
    inner temperatures, S_i += κ (A_{i−1,i} − A_{i,i+1}), κ = t₀/(ν (t + t₀)); β_1 = 1 and the
    hottest stay fixed."""
    kappa = opt.adapt_t0 / (opt.adapt_nu * (step + opt.adapt_t0))
    temps = 1.0 / betas
    log_gaps = np.log(np.diff(temps))
    log_gaps[:-1] += kappa * (rates[:-1] - rates[1:])
    gaps = np.exp(log_gaps)
    inner = temps[0] + np.cumsum(gaps)[:-1]
    # the hottest stays where it was: rescale the inner ones into (1, T_max)
    inner = 1.0 + (inner - 1.0) * (temps[-1] - 1.0) / (temps[0] + gaps.sum() - 1.0)
    return 1.0 / np.concatenate([[temps[0]], inner, [temps[-1]]])


def distinct_optima(
    neg_log_post: Callable[[np.ndarray], np.ndarray],
    starts: np.ndarray,
    bounds: list[tuple[float, float]],
    tol_sigma: float = 3.0,
) -> list[Optimum]:
    """Minimise −ln p (batched: (M, D) → (M,)) from every start (L-BFGS-B in the prior box)
    and keep every distinct optimum: (x̂, covariance from the inverse Hessian, −ln p at x̂),
    best first. Two optima are one when either lies within ``tol_sigma`` standard deviations
    of the other."""
    from scipy.optimize import minimize

    def scalar(x: np.ndarray) -> float:
        return float(neg_log_post(x[None])[0])

    lo, hi = np.array(bounds, dtype=np.float64).T

    def in_box(x: np.ndarray) -> np.ndarray:
        # The Hessian's stencil stays in the prior box: at an optimum on a bound a step out of it
        # reads −ln p = ∞ (NaN curvature); clipped, that axis reads flat and pinv ignores it.
        return neg_log_post(np.clip(x, lo, hi))

    found: list[Optimum] = []
    for s in starts:
        res = minimize(scalar, s, method="L-BFGS-B", bounds=bounds)
        if not np.isfinite(res.fun):
            continue
        step = 1e-4 * np.maximum(np.abs(res.x), 1.0)
        cov = _covariance(stencil_hessian(in_box, res.x, step))
        same = False
        for x_old, cov_old, _ in found:
            d = res.x - x_old
            if _mahalanobis(d, cov_old) < tol_sigma or _mahalanobis(d, cov) < tol_sigma:
                same = True
                break
        if not same:
            found.append((res.x, cov, float(res.fun)))
    return sorted(found, key=lambda t: t[2])


def _covariance(hess: np.ndarray) -> np.ndarray:
    """The inverse Hessian with every flat or downhill direction (an optimum on the box's edge, a
    saddle) given a huge variance instead of none: such a mode is unconstrained along it, and
    its Gaussian must not claim draws by a vanishing determinant (mode_masses)."""
    h = np.nan_to_num(0.5 * (hess + hess.T), nan=0.0, posinf=0.0, neginf=0.0)
    w, v = np.linalg.eigh(h)
    w = np.maximum(w, 1e-12 * max(float(np.max(np.abs(w))), 1.0))
    return (v / w) @ v.T


def _mahalanobis(d: np.ndarray, cov: np.ndarray) -> float:
    return float(math.sqrt(max(d @ np.linalg.pinv(cov) @ d, 0.0)))


def mode_masses(
    draws: np.ndarray, optima: list[tuple[np.ndarray, np.ndarray, float]]
) -> np.ndarray:
    """Each draw (M, D) to the optimum whose Gaussian (its x̂ and covariance) makes it likeliest;
    the share of draws per optimum, in the order given."""
    if not optima:
        return np.zeros(0)
    dist = np.column_stack(
        [
            np.einsum("md,de,me->m", draws - x, np.linalg.pinv(cov), draws - x)
            + np.linalg.slogdet(cov)[1]  # a wide mode claims the draws it is the likelier for
            for x, cov, _ in optima
        ]
    )
    nearest = np.argmin(dist, axis=1)
    return np.bincount(nearest, minlength=len(optima)) / max(len(draws), 1)


def describe_modes(masses: np.ndarray, names: list[str], optima) -> str:
    """One sentence: how many modes, the mass of each and where it is."""
    if len(masses) <= 1:
        return "one mode: the posterior's draws all lie around one optimum"
    parts = []
    for k, (m, (x, _, _)) in enumerate(zip(masses, optima, strict=True)):
        where = ", ".join(f"{n} {v:.4g}" for n, v in zip(names, x, strict=True))
        parts.append(f"mode {k + 1} holds {100 * m:.0f} % ({where})")
    held = int(np.sum(masses >= 0.01))
    return f"{len(masses)} modes found, {held} with ≥ 1 % of the mass: " + "; ".join(parts)

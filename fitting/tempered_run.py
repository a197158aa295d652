"""The fit's chain by parallel tempering (issue 44 item 1: `gonio fit --sampler tempered`).

fitting.tempering's sampler run as the fit's MCMC. Its walkers start as the ensemble's do
(fitting.mcmc.initial_ball: around the least-squares point, drawn from its covariance), every
temperature from the same ball; the β = 1 chain after the ladder's adaptation comes back as a
fitting.mcmc.McmcResult with the same diagnostics (τ, ArviZ's R̂ and ESS), so everything after
the sampler — the verdicts, the intervals, the report — reads it as it reads the ensemble's.
The β = 1 chain is saved in the chain file (``fit-<model>.h5``) as the report reads it: the kept
steps after as many of the burn-in's last steps (the report draws a chain's first half as burn-in
and its second as the posterior).

The run stops early where it can: the ladder adapts over the first half of the steps, at most
ADAPT_MAX, and from then on the ensemble's stopping rule (R̂, bulk and tail ESS at the target on
a chain ≥ MIN_TAU_LENGTHS τ) is checked every CHECK_EVERY steps.

A tempered run is not resumed: its burn-in adapts the ladder, which is no Markov chain to
continue, so a stored chain is replaced (the fingerprint names the sampler: an ensemble fit never
continues a tempered chain either, and says so when it replaces one).

The modes (:func:`posterior_modes`): the distinct optima of ln p found from the least-squares
point, the chain's best draw and the least-squares start grid (fitting.tempering.distinct_optima),
and each one's share of the chain's draws (fitting.tempering.mode_masses), in one sentence.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import emcee
import numpy as np

from fitting.chain_file import save_chain
from fitting.mcmc import (
    MIN_TAU_LENGTHS,
    ChainFile,
    McmcOptions,
    McmcResult,
    chain_diagnostics,
    initial_ball,
)
from fitting.tempering import (
    TemperingOptions,
    describe_modes,
    distinct_optima,
    mode_masses,
    parallel_tempering,
)
from plumbing.progress import Progress

__all__ = ["run_tempered", "posterior_modes", "default_beta_min"]

#: The fewest steps a tempered run takes: half of them adapt the ladder.
MIN_STEPS = 20
#: The ladder adapts for half the steps, at most this many (Vousden et al.'s rate κ has fallen
#: to 2/3 of its start by then, and the default ladder already swaps: default_beta_min); then
#: the stopping rule is checked every CHECK_EVERY steps.
ADAPT_MAX = 500
CHECK_EVERY = 100
#: A mode holds at least this share of the draws (below it, an optimum is said apart).
MIN_MASS = 0.01


def run_tempered(
    posterior: tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray]],
    x0: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray],
    options: McmcOptions,
    *,
    rng: np.random.Generator | int | None = 0,
    scale: np.ndarray | None = None,
    store: ChainFile | None = None,
    progress: bool = False,
) -> McmcResult:
    """Sample L(x) π(x) by parallel tempering from a ball around ``x0`` (as fitting.mcmc.run_mcmc
    places the ensemble's walkers): ``options.temperatures`` ensembles of ``options.walkers``
    (raised to ≥ 2D + 2, even), at most ``options.max_steps`` steps: the first half (at most
    ADAPT_MAX) adapt the ladder, then the ensemble's stopping rule ends the run once it holds
    (``options.time_budget_s`` and ``target_ess`` are the ensemble's only). ``posterior`` =
    (ln L, ln π), each taking (M, D) and returning (M,)."""
    log_like, log_prior = posterior
    opt = options
    t0 = time.perf_counter()
    rng = np.random.default_rng(rng)
    x0 = np.asarray(x0, dtype=np.float64)
    ndim = x0.size
    walkers = max(int(opt.walkers), 2 * ndim + 2)
    walkers += walkers % 2

    def log_prob(x: np.ndarray) -> np.ndarray:
        lp = np.asarray(log_prior(x), dtype=np.float64).copy()
        ok = np.isfinite(lp)
        if ok.any():
            lp[ok] += log_like(x[ok])
        return lp

    start = initial_ball(log_prob, x0, walkers, bounds, rng, scale)
    temps = int(opt.temperatures)
    topt = TemperingOptions(
        temperatures=temps,
        walkers=walkers,
        steps=max(int(opt.max_steps), MIN_STEPS),
        adapt_steps=min(max(int(opt.max_steps), MIN_STEPS) // 2, ADAPT_MAX),
        check_every=CHECK_EVERY,
        beta_min=float(opt.beta_min if opt.beta_min is not None else default_beta_min(temps, ndim)),
        seed=int(rng.integers(0, 2**63 - 1)),
    )
    rule = _StoppingRule(opt)
    with Progress("MCMC (tempered)", topt.steps, enabled=progress, transient=True) as bar:
        tc = parallel_tempering(
            log_like,
            log_prior,
            start,
            topt,
            on_step=lambda k: bar.update(completed=k + 1),
            stop=rule,
        )
    chain = tc.chain
    log_p = tc.log_like + log_prior(chain.reshape(-1, ndim)).reshape(chain.shape[:2])
    if store is not None:
        _save(store, tc, log_prior)
    tau, d = rule.judged(chain)
    res = McmcResult(
        chain=chain,
        log_prob=log_p,
        tau=tau,
        ess=d.ess_bulk,
        rhat=d.rhat,
        acceptance=float(tc.move_acceptance),
        burn=tc.burn,
        iterations=len(tc.history),
        converged=False,
        stop_reason="max_steps",
        wall_time_s=time.perf_counter() - t0,
        ess_tail=d.ess_tail,
        tempering={
            "temperatures": topt.temperatures,
            "betas": tc.betas.tolist(),
            "swap_acceptance": tc.swap_acceptance.tolist(),
        },
    )
    if rule(chain):
        res.converged, res.stop_reason = True, "converged"
    else:
        needed = d.steps_to(opt.target, len(chain))
        res.steps_needed = None if needed is None else tc.burn + needed
    return res


class _StoppingRule:
    """The ensemble's stopping rule (fitting.mcmc) on the kept β = 1 chain: R̂ and bulk / tail
    ESS at their target, on a chain at least MIN_TAU_LENGTHS τ long — ArviZ's R̂ and ESS only
    once τ says the chain is long enough (as fitting.mcmc does), and the last chain's judged
    so that the result does not compute them again."""

    def __init__(self, opt: McmcOptions):
        self.target = opt.target
        self.last: tuple[int, tuple] | None = None

    def judged(self, kept: np.ndarray) -> tuple[np.ndarray, object]:
        """(τ, Diagnostics) of ``kept``."""
        if self.last is None or self.last[0] != len(kept):
            self.last = (len(kept), chain_diagnostics(kept))
        return self.last[1]

    def __call__(self, kept: np.ndarray) -> bool:
        tau = np.asarray(emcee.autocorr.integrated_time(kept, tol=0), dtype=np.float64)
        if not (np.all(np.isfinite(tau)) and len(kept) >= MIN_TAU_LENGTHS * np.max(tau)):
            return False
        _, d = self.judged(kept)
        return self.target.met(d.rhat, d.ess_bulk, d.ess_tail)


def default_beta_min(temperatures: int, ndim: int) -> float:
    """The hottest β of a geometric ladder whose neighbours swap: Δ ln β = √(2/D). Why: near
    a mode ln L is about its peak less a χ²_D/2, whose sd at β is √(D/2)/β; a swap between β and
    β' is taken with probability exp(−|Δβ| · ΔlnL), which stays order one while |Δβ| times that
    sd is about one, i.e. Δβ/β ≈ √(2/D). A ladder much wider than that (1 to 1e-4 in 4 steps on a
    7-parameter fit: swaps 0.07 %, measured) passes nothing down; more temperatures reach
    hotter."""
    return math.exp(-(temperatures - 1) * math.sqrt(2.0 / max(ndim, 1)))


def _save(store: ChainFile, tc, log_prior) -> None:
    """The β = 1 chain into the chain file, in emcee's layout: its kept steps after as many of the
    burn-in's last ones, so that the file's second half is the kept chain (module docstring)."""
    kept = len(tc.history) - tc.burn
    first = max(tc.burn - kept, 0)
    chain, log_like = tc.history[first:], tc.history_log_like[first:]
    steps, walkers, ndim = chain.shape
    backend = emcee.backends.Backend()
    backend.reset(walkers, ndim)
    backend.chain = chain.copy()
    backend.log_prob = log_like + log_prior(chain.reshape(-1, ndim)).reshape(steps, walkers)
    backend.accepted = np.full(walkers, tc.move_acceptance * steps)
    backend.iteration = steps
    save_chain(Path(store.path), store.name, backend, store.fingerprint)


def posterior_modes(
    neg_log_post: Callable[[np.ndarray], np.ndarray],
    draws: np.ndarray,
    starts: np.ndarray,
    space,
) -> dict:
    """The modes of the posterior whose draws (S, D) are given: the distinct optima of −ln p
    (batched (M, D) → (M,)) found from ``starts`` (the chain's best draw among them) that hold
    at least MIN_MASS of the draws, and each one's share: {"count", "masses", "optima" (natural
    values by name), "words"}. Optima more than 3 σ apart (in either one's covariance) are
    distinct; an optimum that holds fewer draws (a flat corner of the prior box where a start
    stopped) is counted apart, in the words. ``space``: the fit's parameter space (bounds,
    names, natural values)."""
    lo, hi = space.bounds
    optima = distinct_optima(neg_log_post, np.asarray(starts, dtype=np.float64),
                             list(zip(lo, hi, strict=True)))  # fmt: skip
    masses = mode_masses(draws, optima)
    held = [k for k, m in enumerate(masses) if m >= MIN_MASS]
    natural = [(space.to_natural(optima[k][0]), *optima[k][1:]) for k in held]
    words = describe_modes(masses[held], space.names, natural)
    others = len(optima) - len(held)
    if others:
        words += (
            f"; {others} further optim{'um' if others == 1 else 'a'} of ln p hold"
            f"{'s' if others == 1 else ''} less than {MIN_MASS:.0%} of the draws"
        )
    return {
        "count": len(held),
        "masses": [float(masses[k]) for k in held],
        "optima": [dict(zip(space.names, map(float, x), strict=True)) for x, _, _ in natural],
        "words": words,
    }

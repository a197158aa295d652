"""Convergence of an ensemble sampler's chain: rank-normalised R̂ and bulk / tail ESS as Vehtari,
Gelman, Simpson, Carpenter & Bürkner define them ("Rank-normalization, folding, and
localization: an improved R̂ for assessing convergence of MCMC", Bayesian Analysis 16(2), 2021),
computed by ArviZ (arviz-stats' array functions, the reference implementation the paper's
authors maintain) — not written again here.

The paper's unit is a *chain*: one Markov chain's draws in order. An affine-invariant ensemble
(emcee) is one Markov chain on W walkers at once; its walkers are not independent chains (each
move uses the others), so treating them as W chains (as arviz.from_emcee does) asks every
walker's short trace to agree with every other's — R̂ − 1 ≈ 1/(2 n_eff per walker), which at
32 walkers crosses 1.01 until the chain is ~100 τ long even when the posterior is sampled well
(the issue 43 demo: R̂ 1.011–1.017 at ESS ≥ 2773). Here each *ensemble* is a chain, its draws
its walkers' traces end to end (`ensemble_draws`), each ensemble's first and second halves in
time given as two chains: the autocorrelation along them is each walker's (a junction every
N/2 ≫ τ draws is negligible), so the bulk ESS is ≈ N·W/τ, emcee's; and the split R̂ compares
the halves in time of every ensemble (and, ArviZ splitting each again, its two halves of
walkers), and the ensembles with each other. Independent ensembles (`gonio fit --ensembles K`)
make R̂ the paper's between-chain check; with one, R̂ checks the chain's halves against each
other (stationarity), which the paper's split R̂ does for a single chain.

Targets (`ConvergenceTarget`): R̂ < 1.01 and bulk and tail ESS ≥ 400 for every parameter, the
paper's recommendation (R̂ < 1.01; ESS > 400 so that R̂ itself and the 5 %/95 % quantiles are
estimated well).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "ConvergenceTarget",
    "Diagnostics",
    "ensemble_draws",
    "diagnose",
    "TAIL_PROB",
    "TAU_LENGTHS",
]

#: Tail ESS: the smaller of the ESS of the 5 % and 95 % quantiles' indicators (the paper's).
TAIL_PROB = 0.05

#: The chain must be this many (largest) τ long before its R̂ and ESS are judged, τ being
#: emcee's integrated autocorrelation time (Sokal's window). What τ decides is the burn-in
#: (3 τ) and the steps a capped chain still needs; the ESS judged is ArviZ's, from its own
#: autocorrelation estimate across the chains, not from τ. Shorter than ~15 τ emcee's estimate
#: reads far low (a 100-step chain: τ ≈ 8 where the long run's is 30, benchmarks/
#: bench_peers_sampler.py --quick); at 20 τ it reads ~20 % low (the quick demo's chain: 24.6–
#: 28.6 at 760 steps against 27–37 at 1500), which moves a 3 τ burn-in by < τ. emcee's own
#: advice, 50 τ, is for τ itself to be accurate; held as a gate, it doubled the demo's chain
#: (≈ 1900 steps, where R̂ < 1.01 and ESS ≥ 400 held from ≈ 1000) without changing a verdict.
TAU_LENGTHS = 20


@dataclass(frozen=True)
class ConvergenceTarget:
    """R̂ < `rhat_max` and bulk and tail ESS ≥ `ess_min` for every parameter (module docstring:
    Vehtari et al. 2021's R̂ < 1.01 and ESS ≥ 400)."""

    rhat_max: float = 1.01
    ess_min: float = 400.0

    def met(self, rhat, ess, ess_tail=None) -> bool:
        rhat, ess = np.asarray(rhat, float), np.asarray(ess, float)
        tail = ess if ess_tail is None else np.asarray(ess_tail, float)
        return bool(
            np.all(rhat < self.rhat_max) and np.all(ess >= self.ess_min)
            and np.all(tail >= self.ess_min)
        )  # fmt: skip


@dataclass(frozen=True)
class Diagnostics:
    """Per parameter (D,): rank-normalised split R̂, bulk ESS and tail ESS."""

    rhat: np.ndarray
    ess_bulk: np.ndarray
    ess_tail: np.ndarray

    def steps_to(self, target: ConvergenceTarget, steps: int) -> int | None:
        """Roughly how many steps in all the chain needs for `target` (ESS grows with length,
        R̂ − 1 falls like 1/length), from a chain `steps` long; None when it holds."""
        if target.met(self.rhat, self.ess_bulk, self.ess_tail):
            return None
        ess = np.minimum(self.ess_bulk, self.ess_tail)
        need = [target.ess_min / e if e > 0 else math.inf for e in ess]
        need += [(r - 1.0) / (target.rhat_max - 1.0) for r in self.rhat if math.isfinite(r)]
        if any(not math.isfinite(r) for r in self.rhat):
            need.append(math.inf)
        factor = max(need)
        return None if not math.isfinite(factor) else int(math.ceil(steps * max(factor, 1.0)))


def ensemble_draws(ensembles: list[np.ndarray]) -> np.ndarray:
    """(2K, W·N'/2, D) chains for ArviZ from K ensembles' post-burn chains (N, W, D) (the last
    N' steps of each, N' the shortest and even): each ensemble's first and second halves in
    time, each half its walkers' traces end to end (module docstring). ArviZ's split R̂ then
    also splits each half between its first and second half of the walkers."""
    n = min(c.shape[0] for c in ensembles)
    n -= n % 2
    out = []
    for c in ensembles:
        c = np.asarray(c[c.shape[0] - n :], dtype=np.float64)  # (n, W, D)
        for half in (c[: n // 2], c[n // 2 :]):
            # (n/2, W, D) → (W·n/2, D): walker by walker, each walker's steps in order
            out.append(half.transpose(1, 0, 2).reshape(-1, c.shape[2]))
    return np.stack(out, axis=0)


def diagnose(ensembles: list[np.ndarray]) -> Diagnostics:
    """R̂ and bulk / tail ESS of one or more independent ensembles' chains (N, W, D) (module
    docstring). A chain too short for ArviZ (fewer than 4 draws a half) gives NaN."""
    draws = ensemble_draws(ensembles)  # (2K, M, D)
    d = draws.shape[2]
    if draws.shape[1] < 8:
        nan = np.full(d, np.nan)
        return Diagnostics(nan, nan, nan)
    # Imported here, not with the module: arviz-stats pulls in scipy.signal and scipy.stats
    # (1.5 CPU-s), which every `gonio fit` paid — a --no-mcmc fit or a bad input too.
    from arviz_stats.base import array_stats

    x = np.moveaxis(draws, 2, 0)  # (D, K, M): ArviZ's chain and draw axes last
    with np.errstate(invalid="ignore", divide="ignore"):
        rhat = array_stats.rhat(x, chain_axis=-2, draw_axis=-1, method="rank")
        bulk = array_stats.ess(x, chain_axis=-2, draw_axis=-1, method="bulk")
        tail = array_stats.ess(x, chain_axis=-2, draw_axis=-1, method="tail", prob=TAIL_PROB)
    return Diagnostics(
        np.asarray(rhat, dtype=np.float64).reshape(d),
        np.asarray(bulk, dtype=np.float64).reshape(d),
        np.asarray(tail, dtype=np.float64).reshape(d),
    )

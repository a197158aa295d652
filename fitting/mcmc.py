"""emcee sampling with autocorrelation-based burn-in and stopping (issue 7 §4, docs/design.md §7).

* Moves: differential evolution by default (fitting.moves: why not emcee's snooker mix).
* The ensemble starts in a small ball around the least-squares optimum (scaled by the LSQ
  standard errors when known), clipped inside the prior box; walkers with ln p = −∞ are
  redrawn closer to the optimum.
* It runs in chunks until its own stopping rule holds, with ``max_steps`` and the time budget
  as caps. After each chunk the integrated autocorrelation time τ_k of every parameter is
  estimated with ``get_autocorr_time(tol=0)`` (Sokal's automatic window). Once the chain is
  at least ``MIN_TAU_LENGTHS`` = 20 τ_k long for every k (fitting.convergence.TAU_LENGTHS: from
  then on τ and the burn-in can be trusted; emcee's stricter 50 τ is for τ's own accuracy and
  doubled the demo's chain), the post-burn chain's
  rank-normalised R̂ and bulk and tail ESS (fitting.convergence: Vehtari et al. 2021, by
  ArviZ) are checked against ``target`` (R̂ < 1.01, ESS ≥ 400): it stops as *converged* when
  they hold, and runs on otherwise. ``stop_reason`` says why it stopped ("converged",
  "max_steps", "time_budget", or "target_ess" when ``target_ess`` is given and every
  parameter's ESS reached it first — counted only on a chain at least ``MIN_TAU_LENGTHS`` τ
  long, since a short chain's τ reads low).
* Burn-in = ⌈3·max τ⌉ (capped at half the chain); R̂, bulk and tail ESS of the post-burn chain
  as fitting.convergence defines them for an ensemble (its walkers are not independent chains;
  several independent ensembles, `FitOptions.ensembles`, make R̂ a between-chain check).
* Resumable: with a ``ChainFile`` the chain is saved (fitting.chain_file: emcee's HDF5
  layout, written whole and atomically after every chunk); a file that holds
  a chain of the same (W, D) shape is continued (its random state too) up to ``max_steps``
  total iterations; otherwise it is reset. ``fingerprint`` (e.g. a hash of data, model and
  parameter names) is stored with the chain and must match for a resume, so a chain of a
  different problem is never continued.
* Seeding: emcee 3.1.6 draws from a legacy ``RandomState`` that it seeds from numpy's global
  state; we overwrite it from the caller's ``numpy.random.Generator`` so runs are reproducible
  without touching global state.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import emcee
import numpy as np

from fitting.chain_file import load_chain, save_chain
from fitting.convergence import TAU_LENGTHS, ConvergenceTarget, Diagnostics, diagnose
from fitting.moves import MOVES, named_moves
from plumbing.errors import UserError
from plumbing.progress import Progress

__all__ = [
    "MOVES",
    "ChainFileError",
    "McmcResult",
    "run_mcmc",
    "McmcOptions",
    "ChainFile",
    "Diagnostics",
    "initial_ball",
    "ConvergenceTarget",
    "convergence_verdict",
    "chain_diagnostics",
    "MIN_TAU_LENGTHS",
    "SAMPLERS",
]

#: Every stop by the chain's own rule needs a chain at least this many (largest) τ long
#: (fitting.convergence.TAU_LENGTHS says why 20): emcee's τ from shorter chains is biased low,
#: and the burn-in and a ``target_ess`` count with it.
MIN_TAU_LENGTHS = TAU_LENGTHS


class ChainFileError(UserError, ValueError):
    """A stored chain (``fit-<model>.h5``) cannot be read for a resume. One-line message.

    It is never overwritten in that case: a damaged file may still be someone's only copy of
    a long chain, so the user decides whether to delete it."""


@dataclass
class McmcResult:
    """Post-burn chain (N_kept, W, D) and its ln p, diagnostics per parameter (D,) arrays."""

    chain: np.ndarray
    log_prob: np.ndarray
    tau: np.ndarray
    ess: np.ndarray
    rhat: np.ndarray
    acceptance: float
    burn: int
    iterations: int
    converged: bool
    stop_reason: str
    wall_time_s: float
    #: Steps of a stored chain of *another* problem (fingerprint or shape differ) that this run
    #: replaced in its chain file (0: none) — said so, never silently (issue 18).
    replaced_steps: int = 0
    #: Tail ESS per parameter (fitting.convergence); ``ess`` is the bulk ESS.
    ess_tail: np.ndarray | None = None
    #: The steps the rule would need in all when a cap stopped the chain first (None: met).
    steps_needed: int | None = None
    #: A tempered run's ladder and swap rates (fitting.tempered_run); None for the ensemble.
    tempering: dict | None = None

    def set_diagnostics(self, d: Diagnostics) -> None:
        self.rhat, self.ess, self.ess_tail = d.rhat, d.ess_bulk, d.ess_tail

    @property
    def flat(self) -> np.ndarray:
        return self.chain.reshape(-1, self.chain.shape[-1])


def initial_ball(
    log_prob: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    walkers: int,
    bounds: tuple[np.ndarray, np.ndarray],
    rng: np.random.Generator,
    scale: np.ndarray | None = None,
) -> np.ndarray:
    """Walkers (W, D) around x0: N(x0, C) for a covariance ``scale`` (D, D), N(x0, diag
    scale²) for standard errors (D,), else a 1e-3 ball.

    Walkers drawn from the Laplace approximation N(x̂, C) start in the typical set; a tiny
    ball must first expand, and 3τ of burn-in does not always cover that (it under-covered 68 %
    intervals in short runs). With its correlations: on a posterior whose parameters are
    strongly correlated (an arm's zero and the sample's tilt about the same axis, which the data
    see nearly only as their sum), axis-wise draws with the marginal sds put most walkers far
    off the ridge, and a short chain still holds that spread (it over-covered 68 % intervals)."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    x0 = np.asarray(x0, dtype=np.float64)
    span = hi - lo
    chol = None
    if scale is not None and np.ndim(scale) == 2:
        try:
            chol = np.linalg.cholesky(np.asarray(scale, dtype=np.float64))
        except np.linalg.LinAlgError:
            chol = None
        scale = None if chol is None else np.sqrt(np.diag(scale))
    if scale is None or not np.all(np.isfinite(scale)) or np.any(np.asarray(scale) <= 0):
        scale, chol = np.full_like(x0, 1e-3), None
    step = np.minimum(np.asarray(scale, dtype=np.float64), 0.1 * span)
    step = np.maximum(step, 1e-8 * np.maximum(1.0, np.abs(x0)))
    if chol is not None:  # the correlations of C with the sds capped as the axis-wise ball's
        chol = chol * (step / np.sqrt(np.sum(chol**2, axis=1)))[:, None]
    pad = 1e-9 * span

    def draw(n: int, shrink: float) -> np.ndarray:
        z = rng.standard_normal((n, x0.size))
        dev = z @ chol.T if chol is not None else z * step
        return np.clip(x0 + shrink * dev, lo + pad, hi - pad)

    p = draw(walkers, 1.0)
    shrink = 1.0
    for _ in range(30):
        bad = ~np.isfinite(log_prob(p))
        if not bad.any():
            break
        shrink *= 0.5
        p[bad] = draw(int(bad.sum()), shrink)
    else:
        raise RuntimeError("could not place walkers where the log-probability is finite")
    return p


def _chain_error(path, exc: BaseException) -> str:
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return (
        f"{path}: not a readable MCMC chain ({first}); delete or move it to start a new "
        "chain, or fit with another --out"
    )


def _check_chain_file(path: Path) -> None:
    """Refuse an existing chain file that is not readable HDF5 (truncated, overwritten).

    emcee's ``HDFBackend.initialized`` reports such a file as "not initialised", and its
    ``reset`` then fails deep inside h5py; checking first gives one line naming the file."""
    if not path.exists():
        return
    import h5py

    try:
        with h5py.File(path, "r"):
            pass
    except OSError as exc:
        raise ChainFileError(_chain_error(path, exc)) from None


#: The samplers a fit can run (McmcOptions.sampler).
SAMPLERS = ("ensemble", "tempered")


@dataclass(frozen=True)
class McmcOptions:
    """How an ensemble runs: `walkers` (raised to ≥ 2D + 2, even), `max_steps` (a cap), a
    wall-time budget (a cap), `target` (the stopping rule's R̂ and ESS), `target_ess` (stop
    early once every ESS reaches it), the emcee `moves` (a name of MOVES or a list),
    `vectorize` (log_prob takes all walkers at once), `chunk` steps between convergence
    checks (grows with the chain). `sampler`: "ensemble" (emcee, the default: a unimodal
    posterior's speed) or "tempered" (fitting.tempered_run: `temperatures` copies of the
    ensemble down to β = `beta_min` — by default the ladder whose neighbours swap on a
    D-dimensional posterior, Δ ln β = √(2/D) — `max_steps` steps of which the first half adapts
    the ladder; for posteriors with several modes or long ridges, at `temperatures` × the
    cost)."""

    walkers: int = 32
    max_steps: int = 2000
    time_budget_s: float | None = None
    target_ess: float | None = None
    moves: Any = "de"
    vectorize: bool = True
    chunk: int = 100
    target: ConvergenceTarget = ConvergenceTarget()
    sampler: str = "ensemble"
    temperatures: int = 8
    beta_min: float | None = None


@dataclass(frozen=True)
class ChainFile:
    """Where the chain is kept (emcee's HDF backend, group `name`) and the fingerprint of the
    problem it samples: a stored chain is continued only for the same fingerprint."""

    path: str | Path
    name: str = "mcmc"
    fingerprint: str | None = None


def run_mcmc(
    log_prob: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray],
    options: McmcOptions | None = None,
    *,
    rng: np.random.Generator | int | None = 0,
    scale: np.ndarray | None = None,
    store: ChainFile | None = None,
    progress: bool = False,
) -> McmcResult:
    """Sample ``log_prob`` ((W, D) → (W,) when vectorised) with emcee from a ball around
    ``x0`` (initial_ball) until the stopping rule holds (module docstring), the ESS target,
    the step cap or the time budget — whichever comes first."""
    opt = options or McmcOptions()
    t0 = time.perf_counter()
    rng = np.random.default_rng(rng)
    x0 = np.asarray(x0, dtype=np.float64)
    ndim = x0.size
    walkers = max(int(opt.walkers), 2 * ndim + 2)
    walkers += walkers % 2  # the stretch move splits the ensemble in two halves
    backend, resume, replaced = _open_chain(store, walkers, ndim)
    moves = named_moves(opt.moves) if isinstance(opt.moves, str) else opt.moves
    fn = log_prob if opt.vectorize else (lambda x: float(np.asarray(log_prob(x))))
    sampler = emcee.EnsembleSampler(
        walkers, ndim, fn, vectorize=opt.vectorize, backend=backend, moves=moves
    )
    if resume:
        start = None  # emcee continues from the stored last sample and random state
    else:
        sampler.random_state = np.random.RandomState(
            rng.integers(0, 2**32 - 1, dtype=np.uint64)
        ).get_state()
        start = initial_ball(
            log_prob if opt.vectorize else np.vectorize(fn, signature="(d)->()"),
            x0,
            walkers,
            bounds,
            rng,
            scale,
        )
    tau, stop_reason, judged = _sample(sampler, start, opt, t0, progress, store)
    res = _result(sampler, tau, stop_reason, t0, opt.target, judged)
    res.replaced_steps = replaced
    return res


def _open_chain(store: ChainFile | None, walkers: int, ndim: int):
    """(emcee backend or None, whether it holds this problem's chain to continue, the steps of
    another problem's chain that were reset). The backend is in memory; fitting.chain_file
    saves it whole and atomically at checkpoints."""
    if store is None:
        return None, False, 0
    path = Path(store.path)
    _check_chain_file(path)
    try:
        stored = load_chain(path, store.name)
    except (OSError, KeyError, ValueError, TypeError) as exc:
        # KeyError/ValueError: an HDF5 file whose chain group is damaged.
        raise ChainFileError(_chain_error(store.path, exc)) from None
    if stored is not None:
        backend, fingerprint = stored
        if (
            backend.shape == (walkers, ndim)
            and backend.iteration > 0
            and fingerprint == store.fingerprint
        ):
            return backend, True, 0
    replaced = int(stored[0].iteration) if stored is not None else 0
    backend = emcee.backends.Backend()
    backend.reset(walkers, ndim)
    return backend, False, replaced


def _sample(sampler, start, opt: McmcOptions, t0: float, progress: bool, store=None):
    """Run in chunks until a stop rule holds; (τ, stop reason, the last R̂ and ESS judged with
    the (burn, iterations) they were judged at, or None). With ``store`` the chain is saved after
    every chunk and when the run is interrupted or fails (a later fit continues it); a save that
    fails (a full disk) leaves the previous one and stops the run."""
    walkers = sampler.nwalkers
    max_steps, chunk = opt.max_steps, opt.chunk
    bar = Progress("MCMC", max_steps, completed=sampler.iteration, enabled=progress, transient=True)
    stop_reason = "max_steps"
    tau = np.full(sampler.ndim, np.nan)
    saved = sampler.iteration
    judged = None

    def checkpoint() -> None:
        nonlocal saved
        if store is not None and sampler.iteration > saved:
            save_chain(Path(store.path), store.name, sampler.backend, store.fingerprint)
            saved = sampler.iteration

    try:
        while sampler.iteration < max_steps:
            n = min(chunk, max_steps - sampler.iteration)
            try:
                sampler.run_mcmc(start, n, skip_initial_state_check=True)
            except BaseException:
                checkpoint()  # the steps taken so far are kept for the next fit
                raise
            start = None
            checkpoint()
            bar.update(completed=sampler.iteration)
            tau = sampler.get_autocorr_time(tol=0)
            it = sampler.iteration
            if np.all(np.isfinite(tau)) and it >= MIN_TAU_LENGTHS * np.max(tau):
                # τ is trusted now: the rule's R̂ and ESS on the post-burn chain (fitting.
                # convergence; checked only from here, so most fits compute them once).
                d = diagnose([sampler.get_chain(discard=_burn(tau, it))])
                judged = (_burn(tau, it), it, d)
                if opt.target.met(d.rhat, d.ess_bulk, d.ess_tail):
                    stop_reason = "converged"
                    break
            # The ESS is only as good as τ: from a chain a few τ long emcee's estimate reads low
            # (a 100-step chain gave τ ≈ 8 where the long run's is 30, so "ESS 256" was 46 by
            # NumPyro's estimator, R̂ 1.47: benchmarks/bench_peers_sampler.py --quick). So the
            # target counts only on a chain ≥ MIN_TAU_LENGTHS τ long.
            if (
                opt.target_ess is not None
                and np.all(np.isfinite(tau))
                and it >= MIN_TAU_LENGTHS * np.max(tau)
            ):
                burn_now = min(int(math.ceil(3 * np.max(tau))), it // 2)
                if np.min((it - burn_now) * walkers / tau) >= opt.target_ess:
                    stop_reason = "target_ess"
                    break
            # Checked after a chunk so even a tiny budget yields a (short) chain.
            if opt.time_budget_s is not None and time.perf_counter() - t0 > opt.time_budget_s:
                stop_reason = "time_budget"
                break
            # Longer chunks as the chain grows keep the τ estimates' cost a small fraction.
            chunk = max(chunk, it // 4)
    finally:
        bar.close()
    return tau, stop_reason, judged


def _burn(tau: np.ndarray, iterations: int) -> int:
    """Burn-in: 3 τ_max steps, at most half the chain."""
    finite = np.isfinite(tau)
    tau_max = float(np.max(tau[finite])) if np.any(finite) else float(iterations) / 2
    return min(int(math.ceil(3 * tau_max)), iterations // 2)


def _result(
    sampler, tau, stop_reason: str, t0: float, target: ConvergenceTarget, judged=None
) -> McmcResult:
    """The post-burn chain (burn = 3 τ_max, at most half) and its diagnostics (those the stop
    rule judged when they were of this same chain: ArviZ's R̂ and ESS cost ~0.2 s a fit)."""
    it = sampler.iteration
    if not np.all(np.isfinite(tau)):
        tau = sampler.get_autocorr_time(tol=0)
    burn = _burn(tau, it)
    chain = sampler.get_chain(discard=burn)
    same = judged is not None and judged[:2] == (burn, it)
    d = judged[2] if same else diagnose([chain])
    res = McmcResult(
        chain=chain,
        log_prob=sampler.get_log_prob(discard=burn),
        tau=np.asarray(tau, dtype=np.float64),
        ess=d.ess_bulk,
        rhat=d.rhat,
        acceptance=float(np.mean(sampler.acceptance_fraction)),
        burn=burn,
        iterations=it,
        converged=stop_reason == "converged",
        stop_reason=stop_reason,
        wall_time_s=time.perf_counter() - t0,
        ess_tail=d.ess_tail,
    )
    if stop_reason in ("max_steps", "time_budget"):
        # the rule's R̂ and ESS, and the MIN_TAU_LENGTHS τ from which τ is trusted
        length = int(math.ceil(MIN_TAU_LENGTHS * np.max(tau))) if np.all(np.isfinite(tau)) else 0
        needed = max(d.steps_to(target, it) or 0, length)
        res.steps_needed = needed if needed > it else None
    return res


# -- the target's verdict, and a chain continued until it holds --------------------------------
def convergence_verdict(
    rhat: dict[str, float], ess: dict[str, float], target: ConvergenceTarget | None = None
) -> dict:
    """Worst R̂ and ESS over the parameters and whether `target` holds for every one (a NaN —
    no chain — is not converged)."""
    target = target or ConvergenceTarget()
    if not rhat or not ess:
        nan = float("nan")
        return {
            "rhat_max": nan,
            "rhat_worst": "",
            "ess_min": nan,
            "ess_worst": "",
            "converged": False,
        }
    r_name = max(rhat, key=lambda k: -math.inf if not math.isfinite(rhat[k]) else rhat[k])
    if any(not math.isfinite(v) for v in rhat.values()):
        r_name = next(k for k, v in rhat.items() if not math.isfinite(v))
    e_name = min(ess, key=lambda k: math.inf if not math.isfinite(ess[k]) else ess[k])
    if any(not math.isfinite(v) for v in ess.values()):
        e_name = next(k for k, v in ess.items() if not math.isfinite(v))
    ok = all(math.isfinite(v) and v < target.rhat_max for v in rhat.values()) and all(
        math.isfinite(v) and v >= target.ess_min for v in ess.values()
    )
    return {
        "rhat_max": float(rhat[r_name]),
        "rhat_worst": r_name,
        "ess_min": float(ess[e_name]),
        "ess_worst": e_name,
        "converged": bool(ok),
    }


def chain_diagnostics(chain: np.ndarray, ensembles: int = 1) -> tuple[np.ndarray, Diagnostics]:
    """τ (emcee, Sokal window) and the R̂ / bulk / tail ESS (fitting.convergence) of a chain
    (N, W, D) pooled from `ensembles` independent ensembles of W / ensembles walkers each."""
    tau = np.asarray(emcee.autocorr.integrated_time(chain, tol=0), dtype=np.float64)
    w = chain.shape[1] // ensembles
    return tau, diagnose([chain[:, k * w : (k + 1) * w] for k in range(ensembles)])

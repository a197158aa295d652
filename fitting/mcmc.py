"""emcee sampling with autocorrelation-based burn-in and stopping (issue 7 §4, DESIGN §7).

* Moves: differential-evolution + snooker by default (see ``_named_moves``).
* The ensemble starts in a small ball around the least-squares optimum (scaled by the LSQ
  standard errors when known), clipped inside the prior box; walkers with ln p = −∞ are
  redrawn closer to the optimum.
* It runs in chunks. After each chunk the integrated autocorrelation time τ_k of every
  parameter is estimated with ``get_autocorr_time(tol=0)`` (Sokal's automatic window, no
  "chain too short" error). It stops as *converged* when the chain length N > 50·τ_k for every
  k and the τ estimate changed by less than 5 % since the last check (the emcee documentation's
  criterion), otherwise when ``max_steps`` or the time budget is reached — ``stop_reason`` says
  which ("converged", "max_steps", "time_budget", or "target_ess" when ``target_ess`` is
  given and every parameter's ESS reached it first).
* Burn-in = ⌈3·max τ⌉ (capped at half the chain); ESS_k = (N − burn)·W/τ_k.
* R-hat: Gelman-Rubin potential scale reduction on *split* per-walker chains — each walker's
  post-burn chain is cut in half, giving 2W chains of length n; B = n·var(chain means),
  V = mean within-chain variance, R̂ = √(((n−1)/n·V + B/n)/V) (Gelman et al., BDA3 §11.4).
  Ensemble walkers are not independent, so this is a necessary, not sufficient, check;
  ``rhat_across`` gives R̂ across independent ensembles when several were run.
* Resumable: with ``backend_path`` an ``emcee.backends.HDFBackend`` is used; a file that holds
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

import emcee
import numpy as np

__all__ = [
    "MOVES",
    "ChainFileError",
    "McmcResult",
    "run_mcmc",
    "split_rhat",
    "rhat_across",
    "initial_ball",
]


class ChainFileError(ValueError):
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

    @property
    def flat(self) -> np.ndarray:
        return self.chain.reshape(-1, self.chain.shape[-1])


def split_rhat(chain: np.ndarray) -> np.ndarray:
    """Split-R̂ of a chain (N, W, D) → (D,); chains are the 2W walker halves."""
    chain = np.asarray(chain, dtype=np.float64)
    n = chain.shape[0] // 2
    if n < 2:
        return np.full(chain.shape[-1], np.nan)
    halves = np.concatenate([chain[:n], chain[n : 2 * n]], axis=1)  # (n, 2W, D)
    return _gelman_rubin(halves)


def rhat_across(chains: list[np.ndarray]) -> np.ndarray:
    """R̂ across independent ensembles: each ensemble's walker-mean trace is one chain."""
    n = min(c.shape[0] for c in chains)
    traces = np.stack([c[-n:].mean(axis=1) for c in chains], axis=1)  # (n, E, D)
    return _gelman_rubin(traces)


def _gelman_rubin(x: np.ndarray) -> np.ndarray:
    n = x.shape[0]
    means = x.mean(axis=0)  # (M, D)
    b = n * means.var(axis=0, ddof=1)
    v = x.var(axis=0, ddof=1).mean(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.sqrt(((n - 1) / n * v + b / n) / v)
    return np.where(v > 0, r, np.nan)


def initial_ball(
    log_prob: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    walkers: int,
    bounds: tuple[np.ndarray, np.ndarray],
    rng: np.random.Generator,
    scale: np.ndarray | None = None,
) -> np.ndarray:
    """Walkers (W, D) around x0: N(x0, scale²), scale = LSQ standard errors (or 1e-3)."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    x0 = np.asarray(x0, dtype=np.float64)
    span = hi - lo
    if scale is None or not np.all(np.isfinite(scale)) or np.any(np.asarray(scale) <= 0):
        scale = np.full_like(x0, 1e-3)
        factor = 1.0
    else:
        # Walkers drawn from the Laplace approximation N(x̂, diag C) start in the typical set;
        # a tiny ball must first expand, and 3τ of burn-in does not always cover that (it
        # under-covered 68% intervals in short runs).
        factor = 1.0
    step = np.minimum(factor * np.asarray(scale, dtype=np.float64), 0.1 * span)
    step = np.maximum(step, 1e-8 * np.maximum(1.0, np.abs(x0)))
    pad = 1e-9 * span
    p = np.clip(x0 + step * rng.standard_normal((walkers, x0.size)), lo + pad, hi - pad)
    for _ in range(30):
        bad = ~np.isfinite(log_prob(p))
        if not bad.any():
            break
        step = step * 0.5
        p[bad] = np.clip(
            x0 + step * rng.standard_normal((int(bad.sum()), x0.size)), lo + pad, hi - pad
        )
    else:
        raise RuntimeError("could not place walkers where the log-probability is finite")
    return p


MOVES = ("de", "stretch")


def _named_moves(name: str):
    """``de``: differential evolution 0.8 + DE snooker 0.2 (ter Braak & Vrugt 2008; the mix
    in emcee's "moves" tutorial). On a 9-parameter Torrance-Sparrow posterior it gave τ ≈ 33
    against ≈ 95 for the default stretch move (Goodman & Weare 2010), i.e. ~3× the ESS per
    step. ``stretch``: emcee's default."""
    if name == "de":
        return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    if name == "stretch":
        return emcee.moves.StretchMove()
    raise ValueError(f"moves {name!r}: use one of {', '.join(MOVES)}")


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


def _stored_fingerprint(backend) -> str | None:
    with backend.open() as fh:
        value = fh[backend.name].attrs.get("gonio_fingerprint")
    return None if value is None else str(value)


def run_mcmc(
    log_prob: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    *,
    bounds: tuple[np.ndarray, np.ndarray],
    walkers: int = 32,
    max_steps: int = 2000,
    time_budget_s: float | None = None,
    rng: np.random.Generator | int | None = 0,
    scale: np.ndarray | None = None,
    backend_path: str | Path | None = None,
    backend_name: str = "mcmc",
    fingerprint: str | None = None,
    chunk: int = 100,
    progress: bool = False,
    vectorize: bool = True,
    target_ess: float | None = None,
    moves="de",
) -> McmcResult:
    """Sample ``log_prob`` ((W, D) → (W,) when vectorised) with emcee; ``moves``: name or moves."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(rng)
    x0 = np.asarray(x0, dtype=np.float64)
    ndim = x0.size
    walkers = max(int(walkers), 2 * ndim + 2)
    walkers += walkers % 2  # the stretch move splits the ensemble in two halves
    backend = None
    resume = False
    if backend_path is not None:
        _check_chain_file(Path(backend_path))
        backend = emcee.backends.HDFBackend(str(backend_path), name=backend_name)
        try:
            resume = (
                backend.initialized
                and backend.shape == (walkers, ndim)
                and backend.iteration > 0
                and _stored_fingerprint(backend) == fingerprint
            )
        except (OSError, KeyError, ValueError, TypeError) as exc:
            # KeyError/ValueError: an HDF5 file whose chain group is damaged.
            raise ChainFileError(_chain_error(backend_path, exc)) from None
        if not resume:
            backend.reset(walkers, ndim)
            if fingerprint is not None:
                with backend.open("a") as fh:
                    fh[backend_name].attrs["gonio_fingerprint"] = fingerprint
    if isinstance(moves, str):
        moves = _named_moves(moves)
    fn = log_prob if vectorize else (lambda x: float(np.asarray(log_prob(x))))
    sampler = emcee.EnsembleSampler(
        walkers, ndim, fn, vectorize=vectorize, backend=backend, moves=moves
    )
    if resume:
        start = None  # emcee continues from the stored last sample and random state
    else:
        sampler.random_state = np.random.RandomState(
            rng.integers(0, 2**32 - 1, dtype=np.uint64)
        ).get_state()
        start = initial_ball(
            log_prob if vectorize else np.vectorize(fn, signature="(d)->()"),
            x0,
            walkers,
            bounds,
            rng,
            scale,
        )

    bar = None
    if progress:
        from rich.progress import Progress

        bar = Progress(transient=True)
        bar.start()
        task = bar.add_task("MCMC", total=max_steps, completed=sampler.iteration)
    stop_reason = "max_steps"
    converged = False
    tau_prev = None
    tau = np.full(ndim, np.nan)
    try:
        while sampler.iteration < max_steps:
            n = min(chunk, max_steps - sampler.iteration)
            if start is not None:
                sampler.run_mcmc(start, n, skip_initial_state_check=True)
                start = None
            else:
                sampler.run_mcmc(None, n, skip_initial_state_check=True)
            if bar is not None:
                bar.update(task, completed=sampler.iteration)
            tau = sampler.get_autocorr_time(tol=0)
            it = sampler.iteration
            stable = tau_prev is not None and np.all(np.abs(tau - tau_prev) < 0.05 * tau)
            if np.all(np.isfinite(tau)) and np.all(it > 50 * tau) and stable:
                converged = True
                stop_reason = "converged"
                break
            if target_ess is not None and np.all(np.isfinite(tau)):
                burn_now = min(int(math.ceil(3 * np.max(tau))), it // 2)
                if np.min((it - burn_now) * walkers / tau) >= target_ess:
                    stop_reason = "target_ess"
                    break
            tau_prev = tau
            # Checked after a chunk so even a tiny budget yields a (short) chain.
            if time_budget_s is not None and time.perf_counter() - t0 > time_budget_s:
                stop_reason = "time_budget"
                break
            # Longer chunks as the chain grows keep the τ estimates' cost a small fraction.
            chunk = max(chunk, it // 4)
    finally:
        if bar is not None:
            bar.stop()
    it = sampler.iteration
    if not np.all(np.isfinite(tau)):
        tau = sampler.get_autocorr_time(tol=0)
    tau_max = float(np.nanmax(tau)) if np.any(np.isfinite(tau)) else float(it) / 2
    burn = min(int(math.ceil(3 * tau_max)), it // 2)
    chain = sampler.get_chain(discard=burn)
    lp = sampler.get_log_prob(discard=burn)
    ess = chain.shape[0] * walkers / tau
    return McmcResult(
        chain=chain,
        log_prob=lp,
        tau=np.asarray(tau, dtype=np.float64),
        ess=np.asarray(ess, dtype=np.float64),
        rhat=split_rhat(chain),
        acceptance=float(np.mean(sampler.acceptance_fraction)),
        burn=burn,
        iterations=it,
        converged=converged,
        stop_reason=stop_reason,
        wall_time_s=time.perf_counter() - t0,
    )

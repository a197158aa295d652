"""Fit orchestration: sample table → least squares → MCMC → ``fit-<model>.json`` (issue 7).

Steps: build the parameter space (per-channel ``kd_R``…, shared ``m`` and Fresnel parameters),
the likelihood, a robust multi-start least-squares fit, the discrepancy start value by a 1-D
maximisation of the likelihood at the LSQ optimum, then emcee from a ball around that point.
Without MCMC the percentiles come from the Laplace approximation N(x̂, C_LSQ) in the sampled
space (so log parameters get log-normal intervals), C inflated by max(1, χ²/dof) when the
discrepancy term is on.

Goodness (at the MAP θ̂, over the uncensored samples): χ² = Σ((f − f̂)/σ)² with σ the
measurement error only, dof = n − k, AIC = 2k − 2 ln L̂, BIC = k ln n − 2 ln L̂ (ln L̂ the full
likelihood, discrepancy term included), k the number of free parameters.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from fitting import models
from fitting.likelihood import Likelihood
from fitting.lsq import fit_least_squares
from fitting.mcmc import rhat_across, run_mcmc
from fitting.priors import DISCREPANCY, ParameterSpace, PriorsConfig, albedo_prior, load_priors
from fitting.result import FitResult
from fitting.samples import SampleTable

__all__ = ["fit_samples", "summarise"]


def summarise(space: ParameterSpace, draws: np.ndarray, x_map: np.ndarray) -> dict[str, dict]:
    """Per-parameter summary in natural units from internal-space draws (S, D)."""
    nat = space.to_natural(draws)
    nat_map = space.to_natural(x_map)
    q = np.percentile(nat, [2.5, 16, 50, 84, 97.5], axis=0)
    out = {}
    for i, s in enumerate(space.specs):
        out[s.name] = {
            "unit": s.unit,
            "map": float(nat_map[i]),
            "median": float(q[2, i]),
            "p16": float(q[1, i]),
            "p84": float(q[3, i]),
            "p2.5": float(q[0, i]),
            "p97.5": float(q[4, i]),
        }
    return out


def _best_discrepancy(lik: Likelihood, x: np.ndarray) -> np.ndarray:
    """Set the discrepancy s in x to the grid value (log-spaced over its prior) maximising ln p."""
    names = lik.space.names
    if DISCREPANCY[0] not in names:
        return x
    i = names.index(DISCREPANCY[0])
    lo, hi = lik.space.bounds
    grid = np.linspace(lo[i], hi[i], 41)[1:-1]
    trial = np.repeat(x[None, :], grid.size, axis=0)
    trial[:, i] = grid
    lp = lik.log_prob(trial)
    x = x.copy()
    x[i] = grid[int(np.argmax(lp))] if np.any(np.isfinite(lp)) else grid[0]
    return x


def _fingerprint(lik: Likelihood, model_name, options, kind, nu, censor) -> str:
    """SHA-256 of what defines the posterior: data, model, options, parameter space."""
    h = hashlib.sha256()
    h.update(
        json.dumps([model_name, options, kind, nu, censor], sort_keys=True, default=str).encode()
    )
    h.update(
        json.dumps(
            [lik.space.names, lik.space.fixed, [s.internal_bounds for s in lik.space.specs]]
        ).encode()
    )
    for d in lik.data:
        for a in (d.wi, d.wo, d.f, d.sigma, d.kind):
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def fit_samples(
    table: SampleTable,
    model_name: str,
    options: Mapping | None = None,
    *,
    channels: Sequence[str] | None = None,
    shared: Sequence[str] | None = None,
    fix: Mapping[str, float] | None = None,
    priors: PriorsConfig | str | os.PathLike | None = None,
    energy_conservation: bool = False,
    mcmc: bool = True,
    walkers: int = 32,
    steps: int = 2000,
    time_budget_s: float | None = None,
    seed: int = 0,
    out_dir: str | os.PathLike | None = None,
    likelihood: str = "gaussian",
    nu: float = 4.0,
    censor: bool = False,
    discrepancy: bool = True,
    weighting: str = "sigma",
    loss: str | None = None,
    n_starts: int = 8,
    progress: bool = False,
    ensembles: int = 1,
    moves: str = "de",
    target_ess: float | None = None,
) -> FitResult:
    """Fit ``model_name`` to ``table``; write fit-<model>.json (+ .h5 chain) into ``out_dir``.

    ``shared=None`` shares m and the Fresnel parameters; kd, ks are per channel. ``fix`` holds
    parameters at natural values (bare or per-channel names). ``steps`` is the MCMC maximum
    per ensemble. ``ensembles`` ≥ 2 runs independent ensembles (seeds drawn from ``seed``,
    groups ``mcmc``, ``mcmc_1``… in the .h5), pools their chains, and reports R̂ across them
    (walker-mean traces, one per ensemble); with one ensemble R̂ is the split-walker R̂.
    τ, ESS and acceptance are then those of the first ensemble, ESS × ensembles.
    """
    t0 = time.perf_counter()
    options = dict(options or {})
    model = models.get(model_name, **options)
    present = table.channels
    channels = list(channels) if channels is not None else present
    missing = [c for c in channels if c not in present]
    if missing:
        raise ValueError(
            f"channel(s) {', '.join(missing)} not in the samples (present: {', '.join(present)})"
        )
    if priors is not None and not isinstance(priors, PriorsConfig):
        priors = load_priors(priors)
    space = ParameterSpace.build(
        model, channels, shared=shared, fix=fix, priors=priors, discrepancy=discrepancy
    )
    if energy_conservation or (priors is not None and priors.energy_conservation):
        space.energy_prior = albedo_prior(model, space)
    lik = Likelihood(model, table, space, kind=likelihood, nu=nu, censor=censor, channels=channels)
    lsq = fit_least_squares(lik, weighting=weighting, loss=loss, n_starts=n_starts, seed=seed)
    # The fractional discrepancy scales with the least-squares prediction, frozen (see
    # fitting.likelihood: a θ-dependent scale rewards overshooting, a measured one biases).
    lik.set_discrepancy_reference(lsq.x)
    x_lsq = _best_discrepancy(lik, lsq.x)

    out_dir = Path(out_dir) if out_dir is not None else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    lo, hi = space.bounds
    extras: dict = {"lsq": lsq, "likelihood": lik, "space": space}
    if mcmc:
        scale = None
        if lsq.cov is not None:
            scale = np.sqrt(np.clip(np.diag(lsq.cov), 0, None))
            scale = np.where(scale > 0, scale, 1e-3)
        fingerprint = _fingerprint(lik, model_name, options, likelihood, nu, censor)
        runs = []
        for e in range(max(1, int(ensembles))):
            h5 = None
            if out_dir is not None:
                h5 = out_dir / f"fit-{model_name}.h5"
            runs.append(
                run_mcmc(
                    lik.log_prob,
                    x_lsq,
                    bounds=(lo, hi),
                    walkers=walkers,
                    max_steps=steps,
                    time_budget_s=time_budget_s,
                    rng=rng,
                    scale=scale,
                    backend_path=h5,
                    backend_name="mcmc" if e == 0 else f"mcmc_{e}",
                    progress=progress,
                    moves=moves,
                    target_ess=target_ess,
                    fingerprint=fingerprint,
                )
            )
        res = runs[0]
        if len(runs) > 1:
            n_keep = min(r.chain.shape[0] for r in runs)
            res.chain = np.concatenate([r.chain[-n_keep:] for r in runs], axis=1)
            res.log_prob = np.concatenate([r.log_prob[-n_keep:] for r in runs], axis=1)
            res.rhat = rhat_across([r.chain for r in runs])
            res.ess = np.sum([r.ess for r in runs], axis=0)
            res.converged = all(r.converged for r in runs)
            res.stop_reason = ",".join(dict.fromkeys(r.stop_reason for r in runs))
        draws = res.flat
        flat_lp = res.log_prob.reshape(-1)
        lp_lsq = lik.log_prob(x_lsq)
        x_map = draws[int(np.argmax(flat_lp))] if flat_lp.max() > lp_lsq else x_lsq
        names = space.names
        diagnostics = {
            "tau": dict(zip(names, res.tau.tolist(), strict=True)),
            "ess": dict(zip(names, res.ess.tolist(), strict=True)),
            "acceptance": res.acceptance,
            "converged": res.converged,
            "rhat": dict(zip(names, res.rhat.tolist(), strict=True)),
            "stop_reason": res.stop_reason,
        }
        extras["mcmc"] = res
    else:
        x_map = x_lsq
        if lsq.cov is not None:
            cov = lsq.cov.copy()
            i_disc = [i for i, s in enumerate(space.specs) if s.base == DISCREPANCY[0]]
            for i in i_disc:  # not constrained by LSQ: keep it at its point value
                cov[i, :] = cov[:, i] = 0
            if i_disc and weighting == "sigma":
                # With a discrepancy term σ is not trusted alone: inflate by χ²/dof ≥ 1
                # (the usual Birge-ratio correction) so the Laplace interval is not
                # overconfident when the model does not fit.
                r = lik.residuals(x_lsq, "sigma")
                cov *= max(1.0, float(np.sum(r**2)) / max(lik.n_exact - space.ndim, 1))
            draws = rng.multivariate_normal(x_lsq, cov, size=4000, method="eigh")
            draws = np.clip(draws, lo, hi)
        else:
            draws = np.repeat(x_lsq[None, :], 2, axis=0)
        diagnostics = {
            "tau": {},
            "ess": {},
            "acceptance": None,
            "converged": False,
            "rhat": {},
            "stop_reason": "no_mcmc",
        }
    k = space.ndim
    n = lik.n_exact
    r = lik.residuals(x_map, "sigma")
    ll = float(lik.log_likelihood(x_map)[0])
    chi2 = float(np.sum(r**2))
    dof = n - k
    goodness = {
        "chi2": chi2,
        "dof": dof,
        "chi2_red": chi2 / dof if dof > 0 else float("nan"),
        "aic": 2 * k - 2 * ll,
        "bic": float(k * np.log(n) - 2 * ll),
        "n": n,
    }
    result = FitResult(
        model=model_name,
        options=options,
        channels=channels,
        parameters=summarise(space, draws, x_map),
        diagnostics=diagnostics,
        goodness=goodness,
        n_samples=int(lik.n),
        wall_time_s=time.perf_counter() - t0,
        extras=extras,
    )
    if out_dir is not None:
        result.write(out_dir / f"fit-{model_name}.json")
    return result

"""Fit orchestration: sample table → least squares → MCMC → ``fit-<model>.json`` (issue 7).

Steps: build the parameter space (per-channel ``kd_R``…, shared ``m`` and Fresnel parameters),
the likelihood, a robust multi-start least-squares fit, the discrepancy start value by a 1-D
maximisation of the likelihood at the LSQ optimum, then emcee from a ball around that point.
Without MCMC the percentiles come from the Laplace approximation N(x̂, C_LSQ) in the sampled
space (so log parameters get log-normal intervals), C inflated by max(1, χ²/dof) when the
discrepancy term is on.

Under model mismatch (the discrepancy term on, the default) the draws are then widened to the
HC3 sandwich where the residuals show the posterior is too narrow, and each (θ_h, θ_d) region
gets its own model-error fraction for predictions (fitting.mismatch); the intervals then cover
the best approximation on the measured domain (:func:`best_approximation`).

Goodness (at the MAP θ̂, over the uncensored samples): χ² = Σ((f − f̂)/σ)² with σ the
measurement error only, dof = n − k, AIC = 2k − 2 ln L̂, BIC = k ln n − 2 ln L̂ (ln L̂ the full
likelihood, discrepancy term included), k the number of free parameters.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from brdfdata.samples import SampleTable, dark_snr_of
from fitting import models
from fitting.budget import add_systematic, left_out_words, read_budget
from fitting.convergence import diagnose
from fitting.likelihood import Likelihood
from fitting.lsq import fit_least_squares, polish_in_blocks, start_points
from fitting.mcmc import SAMPLERS, ChainFile, McmcOptions, chain_diagnostics, run_mcmc
from fitting.mismatch import regional_discrepancy, sandwich_adjust
from fitting.moves import SAMPLER_REVISION
from fitting.nuisance import (
    arm_positions_known,
    carried_words,
    nuisance_effect,
    sampler_coordinates,
    shared_errors,
    split_uncertainty,
    with_nuisances,
)
from fitting.priors import DISCREPANCY, ParameterSpace, PriorsConfig, albedo_prior, load_priors
from fitting.result import FitResult
from fitting.tempered_run import posterior_modes, run_tempered
from fitting.verdicts import judge

__all__ = ["FitOptions", "FitSetup", "fit_setup", "best_approximation", "fit_samples", "summarise"]


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
    """SHA-256 of what defines the posterior: data, model, options, parameter space.

    ``censor`` enters as whether censored rows are actually in the likelihood: on a table with
    no DARK or SATURATED sample both settings give the same posterior, so a chain stored before
    censoring became the default (issue 18) is still continued; where flagged rows exist the
    data arrays differ anyway and a stored chain of the other setting is replaced, and said so
    (``McmcResult.replaced_steps``, printed by ``gonio fit``)."""
    censor = bool(censor) and any(bool(d.kind.any()) for d in lik.data)
    h = hashlib.sha256()
    # SAMPLER_REVISION: a chain drawn by an earlier, wrong sampler is replaced, not continued.
    key = [model_name, options, kind, nu, censor, SAMPLER_REVISION]
    h.update(json.dumps(key, sort_keys=True, default=str).encode())
    h.update(
        json.dumps(
            [lik.space.names, lik.space.fixed, [s.internal_bounds for s in lik.space.specs]]
        ).encode()
    )
    for d in lik.data:
        for a in (d.wi, d.wo, d.f, d.sigma, d.kind):
            h.update(np.ascontiguousarray(a).tobytes())
        if d.weight is not None:  # binned censored rows (fitting.binning)
            h.update(np.ascontiguousarray(d.weight).tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class FitOptions:
    """Everything that defines a fit besides the data (built once by the CLI, the demo and the
    studies; `replace(**changes)` for a variant, `with_mcmc(**changes)` for another sampler
    setting).

    ``model``/``model_options``: a registered model and its options. ``channels``: which to fit
    (default: all present). ``shared``: parameters shared by the channels (None: m and the
    Fresnel parameters; kd, ks per channel). ``fix``: parameters held at natural values (bare
    or per-channel names). ``priors``: a PriorsConfig or a priors file. ``mcmc``: how the
    sampler runs (fitting.mcmc.McmcOptions: walkers, the step maximum per ensemble, a wall-time
    budget, an ESS target, the moves), or None for no MCMC (the Laplace approximation at the
    least-squares optimum). ``ensembles`` ≥ 2 runs independent ensembles (seeds drawn from
    ``seed``, groups ``mcmc``, ``mcmc_1``… in the .h5), pools their chains and reports R̂ across
    them; with one ensemble R̂ is the split-walker R̂ (τ, ESS and acceptance are then those of
    the first ensemble, ESS × ensembles).
    """

    model: str = "torrance-sparrow"
    model_options: Mapping[str, str] = field(default_factory=dict)
    channels: Sequence[str] | None = None
    shared: Sequence[str] | None = None
    fix: Mapping[str, float] = field(default_factory=dict)
    priors: PriorsConfig | str | os.PathLike | None = None
    energy_conservation: bool = False
    mcmc: McmcOptions | None = field(default_factory=McmcOptions)
    seed: int = 0
    likelihood: str = "gaussian"
    nu: float = 4.0
    # DARK / SATURATED samples as censored observations (issue 18: the default; False drops
    # them, `gonio fit --drop-flagged`).
    censor: bool = True
    discrepancy: bool = True
    weighting: str = "sigma"
    loss: str | None = None
    n_starts: int = 8
    # Independent ensembles (walkers each): R̂ then compares them (fitting.convergence).
    ensembles: int = 1
    # The file a binned table (fitting.binning) was streamed from: the fit then corrects the
    # bins for the model's curvature and states what binning still moves (fitting.binning).
    binned_source: str | os.PathLike | None = None
    # With the discrepancy term: widen the intervals to the sandwich where the residuals say the
    # posterior is too narrow, and fit a model error per (θ_h, θ_d) region (fitting.mismatch;
    # `gonio fit --no-widen` keeps the plain posterior).
    widen_for_mismatch: bool = True
    # The samples' shared errors (their budget: scale, arm zeros) as nuisance parameters the
    # MCMC marginalises (fitting.nuisance); False, or without MCMC: the shared scale is added
    # after the fit to the amplitudes (fitting.budget.add_systematic), angles are not carried.
    shared_errors: bool = True

    def replace(self, **changes) -> FitOptions:
        return dataclasses.replace(self, **changes)

    def with_mcmc(self, **changes) -> FitOptions:
        """The same fit with the sampler's options changed (MCMC on if it was off)."""
        return self.replace(mcmc=dataclasses.replace(self.mcmc or McmcOptions(), **changes))


@dataclass(frozen=True)
class FitSetup:
    """What a fit of some FitOptions to a table stands on, validated once: the model, the
    fitted channels and the parameter space (per-channel and shared names, fixes, priors, the
    nuisance parameters of the samples' shared errors, the energy prior). Made by
    :func:`fit_setup`; ``fit_samples(..., setup=)`` uses it instead of building it again."""

    model: object
    channels: list[str]
    space: ParameterSpace


def fit_setup(table: SampleTable, opt: FitOptions) -> FitSetup:
    """The model, channels and parameter space of fitting ``opt`` to ``table`` — the one place
    that checks them: an unknown channel, model option, --fix, --shared name or priors entry
    is a ValueError (PriorsError for a priors file) with a one-line message."""
    model = models.get(opt.model, **dict(opt.model_options))
    present = table.channels
    channels = list(opt.channels) if opt.channels is not None else present
    missing = [c for c in channels if c not in present]
    if missing:
        raise ValueError(
            f"channel(s) {', '.join(missing)} not in the samples (present: {', '.join(present)})"
        )
    priors = opt.priors
    if priors is not None and not isinstance(priors, PriorsConfig):
        priors = load_priors(priors)
    space = ParameterSpace.build(
        model,
        channels,
        shared=opt.shared,
        fix=dict(opt.fix),
        priors=priors,
        discrepancy=opt.discrepancy,
    )
    shared = (
        shared_errors(
            read_budget(table.metadata),
            channels,
            positions=arm_positions_known(table.metadata),
            levels="bend_level" in table.extra,
        )
        if opt.shared_errors and opt.mcmc is not None
        else None
    )
    if shared is not None:
        space = with_nuisances(space, shared)
    if opt.energy_conservation or (priors is not None and priors.energy_conservation):
        space.energy_prior = albedo_prior(model, space)
    return FitSetup(model, channels, space)


def _likelihood(table: SampleTable, opt: FitOptions, setup: FitSetup) -> Likelihood:
    return Likelihood(
        setup.model,
        table,
        setup.space,
        kind=opt.likelihood,
        nu=opt.nu,
        censor=opt.censor,
        channels=setup.channels,
        dark_snr=dark_snr_of(table.metadata),
    )


def fit_samples(
    table: SampleTable,
    options: FitOptions | None = None,
    *,
    out_dir: str | os.PathLike | None = None,
    progress: bool = False,
    setup: FitSetup | None = None,
) -> FitResult:
    """Fit ``options.model`` to ``table``; write fit-<model>.json (+ .h5 chain) into
    ``out_dir`` (see FitOptions for every choice). ``setup``: :func:`fit_setup` of the same
    table and options, when the caller has checked them already."""
    opt = options or FitOptions()
    t0 = time.perf_counter()
    setup = setup or fit_setup(table, opt)
    _model, channels, space = setup.model, setup.channels, setup.space
    lik = _likelihood(table, opt, setup)
    lsq = _search_then_polish(table, lik, opt, setup)
    eps_corrected = None
    if opt.binned_source is not None and "gonio.binned" in table.metadata:
        # Binned samples: remove the model's curvature over each bin from its mean (one more
        # streamed pass at the least-squares optimum), then fit the corrected bins.
        table, eps_corrected = _correct_binning(table, lik, lsq.x, opt.binned_source)
        lik = _likelihood(table, opt, setup)
        lsq = _polish(lik, lsq.x, opt, len(table))
    # The fractional discrepancy scales with the least-squares prediction, frozen (see
    # fitting.likelihood: a θ-dependent scale rewards overshooting, a measured one biases).
    # and the arms' zero errors are linearised there (fitting.likelihood.Likelihood.frozen_at).
    lik = lik.frozen_at(lsq.x)
    x_lsq = _best_discrepancy(lik, lsq.x)
    out_dir = Path(out_dir) if out_dir is not None else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(opt.seed)
    extras: dict = {"lsq": lsq, "likelihood": lik, "space": space}
    if opt.mcmc is not None:
        h5 = None if out_dir is None else out_dir / f"fit-{opt.model}.h5"
        coords = sampler_coordinates(space, _model, x_lsq)
        # The model in float32 where its rounding is negligible beside the noise (about twice
        # as fast; fitting.likelihood), for the sampling only: everything else stays float64.
        probes = _precision_probes(lik, lsq, x_lsq, opt.seed)
        with lik.sampling_precision(probes) as (choice, diff):
            precision = {"mcmc": choice, "rounding_lnl": diff, "reason": lik.precision_reason}
            res = _run_ensembles(lik, lsq, x_lsq, opt, rng, h5, progress, coords)
            lp_lsq = lik.log_prob(x_lsq)  # in the chain's precision, to compare with its values
        if coords is not None:
            res = _from_sampler(res, coords, max(1, int(opt.ensembles)))
        draws = res.flat
        flat_lp = res.log_prob.reshape(-1)
        x_map = draws[int(np.argmax(flat_lp))] if flat_lp.max() > lp_lsq else x_lsq
        names = space.names
        diagnostics = {
            "tau": dict(zip(names, res.tau.tolist(), strict=True)),
            "ess": dict(zip(names, res.ess.tolist(), strict=True)),
            "ess_tail": dict(zip(names, np.asarray(res.ess_tail).tolist(), strict=True)),
            "acceptance": res.acceptance,
            "converged": False,  # set by the verdicts below
            "rhat": dict(zip(names, res.rhat.tolist(), strict=True)),
            "stop_reason": res.stop_reason,
            "steps_needed": res.steps_needed,
            "precision": precision,
        }
        diagnostics.update(_tempered_diagnostics(lik, x_lsq, opt, res))
        extras["mcmc"] = res
        extras["notes"] = _chain_notes(res, h5)
    else:
        x_map, draws = _no_mcmc_draws(lik, lsq, x_lsq, opt, rng)
        diagnostics = {
            "tau": {},
            "ess": {},
            "acceptance": None,
            "converged": False,
            "rhat": {},
            "stop_reason": "no_mcmc",
        }
    draws = _mismatch(lik, draws, opt, extras, diagnostics)
    parameters, diagnostics["budget"] = _with_budget(space, draws, x_map, _model, table)
    if "gonio.binned" in table.metadata:  # the samples were binned (fitting.binning)
        diagnostics["binning"] = _binning_diagnostics(
            table, lik, x_map, opt.binned_source, eps_corrected
        )
    result = FitResult(
        model=opt.model,
        options=dict(opt.model_options),
        channels=channels,
        parameters=parameters,
        diagnostics=diagnostics,
        goodness=_goodness(lik, x_map),
        n_samples=int(lik.n),
        wall_time_s=time.perf_counter() - t0,
        fixed=dict(space.fixed),
        samples_sha256=table.source_sha256,
        extras=extras,
    )
    # The verdicts (fitting.verdicts); "converged" then means their stated criteria.
    result.verdicts, conv = judge(result, lik, extras.get("mcmc"))
    result.diagnostics.update(conv)
    if out_dir is not None:
        result.write(out_dir / f"fit-{opt.model}.json")
    return result


#: Above this many rows the multi-start search runs on a random subsample of this many and only
#: its best start is polished on every row: the starts only have to find the basin, and each
#: start costs a Jacobian by finite differences per iteration over every row (issue 23: 72 % of
#: a 10⁶-row fit). 10⁴ rows: a basin's χ² lead over another grows with the rows, and at 10⁴ a
#: basin that a start can tell apart at all leads by thousands; the polish on every row then
#: moves the optimum by its own statistical error only. (50 000 before: the demo's 67k-row fit
#: spent 47 of its 113 s in the search; 10 000 gives the same optimum after the polish.)
SEARCH_ROWS = 10_000


def _search_then_polish(table: SampleTable, lik: Likelihood, opt: FitOptions, setup: FitSetup):
    """The least-squares fit of `lik`: the multi-start search on a seeded random subsample of
    SEARCH_ROWS rows, polished from its best start on all rows — where that is less work than
    the search on all rows: K starts on n rows cost ≈ K·n, the subsample's K·S + n (the polish
    about one start), so it pays when n (K − 1) > K·S (two starts: above 2·S rows)."""
    kw = {"weighting": opt.weighting, "loss": opt.loss, "seed": opt.seed}
    k = opt.n_starts
    if k <= 1 or len(table) * (k - 1) <= k * SEARCH_ROWS:
        return fit_least_squares(lik, n_starts=opt.n_starts, **kw)
    pick = np.random.default_rng(opt.seed).choice(len(table), SEARCH_ROWS, replace=False)
    keep = np.zeros(len(table), dtype=bool)
    keep[pick] = True
    sub = _likelihood(table.select(keep), opt, setup)
    search = fit_least_squares(sub, n_starts=opt.n_starts, **kw)
    return _polish(lik, search.x, opt, len(table))


def _polish(lik: Likelihood, x0: np.ndarray, opt: FitOptions, rows: int):
    """Least squares from the one start `x0`, in the optimum's basin: above SEARCH_ROWS rows
    on normal equations summed over blocks of rows (fitting.lsq.polish_in_blocks: the solver's
    per-row arrays, ~5 copies of the n × k Jacobian in least_squares, are never held)."""
    if rows > SEARCH_ROWS and (opt.loss or "soft_l1") in ("soft_l1", "linear"):
        return polish_in_blocks(lik, x0, weighting=opt.weighting, loss=opt.loss)
    kw = {"weighting": opt.weighting, "loss": opt.loss, "seed": opt.seed}
    return fit_least_squares(lik, starts=x0[None, :], **kw)


def _with_budget(space, draws, x_map, model, table) -> tuple[dict, list[str]]:
    """(parameter summaries with sd_stat / sd_sys / sd_total, the words on the samples' budget):
    from the nuisance parameters' draws (fitting.nuisance), or the shared scale added after the
    fit (fitting.budget) when the fit carries none."""
    budget = read_budget(table.metadata)
    summary = summarise(space, draws, x_map)
    if space.shared_errors is None:
        return add_systematic(summary, model, list(space.channels), budget)
    nat = space.to_natural(draws)
    words = [carried_words(space.shared_errors, space.names, nat)]
    return split_uncertainty(summary, space.names, nat), words + left_out_words(
        budget, space.shared_errors.carried
    )


def _mismatch(lik, draws, opt: FitOptions, extras: dict, diagnostics: dict) -> np.ndarray:
    """The draws the intervals come from: with the discrepancy term, widened where the
    residuals say the posterior is too narrow for the best approximation, and a model error
    fitted per (θ_h, θ_d) region (fitting.mismatch) into ``diagnostics["mismatch"]``. The
    sampler's own draws stay in ``extras["raw_draws"]``."""
    extras["raw_draws"] = draws
    if opt.discrepancy:
        info: dict = {"applied": False, "reason": "--no-widen"}
        if opt.widen_for_mismatch:
            # Only the statistical part is widened: the nuisances' effect is set aside and
            # added back (fitting.nuisance.nuisance_effect).
            nuis = [i for i, s in enumerate(lik.space.specs) if s.prior_sigma is not None]
            effect = nuisance_effect(draws, nuis)
            draws, info = sandwich_adjust(lik, draws - effect)
            draws = np.clip(draws + effect, *lik.space.bounds)
        info["regions"] = regional_discrepancy(lik, np.median(draws, axis=0))
        diagnostics["mismatch"] = info
    extras["draws"] = draws
    return draws


def best_approximation(table: SampleTable, options: FitOptions | None = None) -> dict[str, float]:
    """The best-approximating parameters θ* of ``options``'s fit to ``table`` — the target of
    the intervals when the model does not describe the material (fitting.mismatch).

    Definition: ``table`` holds the material's noise-free f on a dense set of directions
    covering the measured domain, with the σ the measurement would have; θ* is where the fit's
    own criterion is best on it — the least-squares start, the discrepancy reference frozen
    there, then the maximum of the posterior density (discrepancy s included) by alternating a
    1-D search in s and bounded L-BFGS in the model parameters until neither moves. On
    measured data the same fit's estimate converges to θ* as the directions fill the domain
    (White 1982), so a 95 % interval should hold θ* in 95 % of repeated measurements.
    Returns natural values by fitted name (``kd_G``, ``m``, ``discrepancy``…).
    """
    from scipy.optimize import minimize, minimize_scalar

    opt = options or FitOptions()
    setup = fit_setup(table, opt)
    space, lik = setup.space, _likelihood(table, opt, setup)
    lsq = fit_least_squares(
        lik, weighting=opt.weighting, loss=opt.loss, n_starts=opt.n_starts, seed=opt.seed
    )
    lik = lik.frozen_at(lsq.x, angles=False)
    x = _best_discrepancy(lik, lsq.x)
    lo, hi = space.bounds
    disc = [i for i, s in enumerate(space.specs) if s.base == DISCREPANCY[0]]
    model_cols = np.array([i for i in range(space.ndim) if i not in disc], dtype=int)

    def neg(y: np.ndarray) -> float:
        v = float(lik.log_prob(y))
        return -v if np.isfinite(v) else 1e300

    for _ in range(50):
        before = x.copy()
        for i in disc:

            def along(t: float, i: int = i) -> float:
                y = x.copy()
                y[i] = t
                return neg(y)

            x[i] = minimize_scalar(along, bounds=(lo[i], hi[i]), method="bounded").x

        def of_model(t: np.ndarray) -> float:
            y = x.copy()
            y[model_cols] = t
            return neg(y)

        x[model_cols] = minimize(
            of_model,
            x[model_cols],
            method="L-BFGS-B",
            bounds=list(zip(lo[model_cols], hi[model_cols], strict=True)),
            options={"ftol": 1e-15, "gtol": 1e-10},
        ).x
        if np.max(np.abs(x - before)) < 1e-8:
            break
    nat = space.to_natural(x)
    out = {s.name: float(v) for s, v in zip(space.specs, nat, strict=True)}
    out.update(space.fixed)
    return out


def _tempered_diagnostics(lik, x_lsq, opt: FitOptions, res) -> dict:
    """A tempered chain's ladder and the posterior's modes with their masses
    (fitting.tempered_run.posterior_modes), searched from the least-squares point, the chain's
    best draw and the least-squares start grid; nothing for the ensemble's chain."""
    if res.tempering is None:
        return {}
    draws = res.flat
    best = draws[int(np.argmax(res.log_prob.reshape(-1)))]
    starts = np.vstack([x_lsq[None, :], best[None, :], start_points(lik, opt.n_starts, opt.seed)])

    def neg_log_post(x: np.ndarray) -> np.ndarray:
        return -lik.log_prob(x)

    modes = posterior_modes(neg_log_post, draws, starts, lik.space)
    return {"tempering": res.tempering, "modes": modes}


def _chain_notes(res, h5) -> list[str]:
    """One line when the run replaced a stored chain of another problem (never silently)."""
    if not getattr(res, "replaced_steps", 0) or h5 is None:
        return []
    return [
        f"{Path(h5).name}: its stored {res.replaced_steps}-step chain was made with other data "
        "or options (e.g. before censoring became the default) and was replaced by a new one"
    ]


def _walkers_covariance(cov: np.ndarray, specs, x: np.ndarray, coords) -> np.ndarray:
    """The covariance the first walkers are drawn from (fitting.mcmc.initial_ball): the
    least-squares (Laplace) covariance with its correlations, in the sampler's coordinates
    (C_y = T C Tᵀ, T = ∂y/∂x at x by central differences); a parameter least squares held gets
    its prior's σ (a nuisance) or 1e-3, uncorrelated."""
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    held = ~(sd > 0)
    c = np.array(cov, dtype=np.float64)
    c[held, :] = c[:, held] = 0.0
    fill = np.array([s.prior_sigma if s.prior_sigma is not None else 1e-3 for s in specs])
    c[held, held] = fill[held] ** 2
    if coords is None:
        return c
    h = 1e-6 * np.maximum(1.0, np.abs(x))
    t = np.empty((x.size, x.size))
    for k in range(x.size):
        xp, xm = x.copy(), x.copy()
        xp[k] += h[k]
        xm[k] -= h[k]
        t[:, k] = (coords.to_sampler(xp) - coords.to_sampler(xm)) / (2 * h[k])
    return t @ c @ t.T


def _from_sampler(res, coords, ensembles: int):
    """The chain in θ from the sampler's coordinates (fitting.nuisance.SamplerCoordinates):
    ln p without the Jacobian, τ / ESS / R̂ recomputed on θ (R̂ across the ensembles)."""
    res.log_prob = res.log_prob - coords.log_jacobian(res.chain)
    res.chain = coords.from_sampler(res.chain)
    res.tau, d = chain_diagnostics(res.chain, ensembles)
    res.set_diagnostics(d)
    return res


def _run_ensembles(lik, lsq, x_lsq, opt: FitOptions, rng, h5, progress: bool, coords=None):
    """emcee from a ball around the LSQ point; several ensembles pooled (R̂ across them). With
    `coords` the sampler walks in its coordinates (the chain stays in them here)."""
    lo, hi = lik.space.bounds
    scale = None
    if lsq.cov is not None:
        scale = _walkers_covariance(lsq.cov, lik.space.specs, x_lsq, coords)
    fingerprint = _fingerprint(
        lik, opt.model, dict(opt.model_options), opt.likelihood, opt.nu, opt.censor
    )
    mcmc = opt.mcmc
    if mcmc.sampler not in SAMPLERS:
        raise ValueError(f"sampler {mcmc.sampler!r}: choose one of {', '.join(SAMPLERS)}")
    if mcmc.sampler == "tempered":  # a tempered chain is never continued as an ensemble's
        fingerprint = hashlib.sha256(f"{fingerprint} tempered".encode()).hexdigest()
    log_prob, x0 = lik.log_prob, x_lsq
    log_like, log_prior = lik.log_likelihood, lik.space.log_prior
    if coords is not None:
        log_prob, x0, (lo, hi) = (
            coords.wrap(lik.log_prob),
            coords.to_sampler(x_lsq),
            coords.bounds(lo, hi),
        )
        log_like, log_prior = coords.split(lik.log_likelihood, lik.space.log_prior)

    def run(store: ChainFile | None):
        if mcmc.sampler == "tempered":
            posterior = (log_like, log_prior)
            return run_tempered(posterior, x0, (lo, hi), mcmc, rng=rng, scale=scale, store=store,
                                progress=progress)  # fmt: skip
        return run_mcmc(log_prob, x0, (lo, hi), mcmc, rng=rng, scale=scale, store=store,
                        progress=progress)  # fmt: skip

    runs = [
        run(None if h5 is None else ChainFile(h5, "mcmc" if e == 0 else f"mcmc_{e}", fingerprint))
        for e in range(max(1, int(opt.ensembles)))
    ]
    res = runs[0]
    if len(runs) > 1:
        n_keep = min(r.chain.shape[0] for r in runs)
        diagnostics = diagnose([r.chain[-n_keep:] for r in runs])  # before runs[0] is pooled
        res.chain = np.concatenate([r.chain[-n_keep:] for r in runs], axis=1)
        res.log_prob = np.concatenate([r.log_prob[-n_keep:] for r in runs], axis=1)
        res.set_diagnostics(diagnostics)
        res.converged = all(r.converged for r in runs)
        needed = [r.steps_needed for r in runs if r.steps_needed is not None]
        res.steps_needed = max(needed) if needed else None
        res.stop_reason = ",".join(dict.fromkeys(r.stop_reason for r in runs))
        res.replaced_steps = max(r.replaced_steps for r in runs)
    return res


def _precision_probes(lik, lsq, x_lsq, seed: int, n: int = 16) -> np.ndarray:
    """Where the sampler will go, for Likelihood.choose_precision: the least-squares optimum and
    ``n`` draws of its Laplace approximation (the walkers' starting ball is drawn from the same
    covariance). Its own generator, so the MCMC's random stream is the one it was."""
    if lsq.cov is None:
        return x_lsq[None, :]
    draws = _laplace_sample(lik.space, x_lsq, lsq.cov, np.random.default_rng([seed, 23]), n)
    return np.vstack([x_lsq[None, :], draws])


def _laplace_draws(lik, lsq, x_lsq, opt: FitOptions, rng) -> np.ndarray:
    """Draws of the Laplace approximation N(x̂, C_LSQ), clipped to the prior box."""
    space = lik.space
    if lsq.cov is None:
        return np.repeat(x_lsq[None, :], 2, axis=0)
    cov = lsq.cov
    if opt.weighting == "sigma" and any(s.base == DISCREPANCY[0] for s in space.specs):
        # With a discrepancy term σ is not trusted alone: inflate by χ²/dof ≥ 1 (the usual
        # Birge-ratio correction) so the Laplace interval is not overconfident when the model
        # does not fit.
        r = lik.residuals(x_lsq, "sigma")
        cov = cov * max(1.0, float(np.sum(r**2)) / max(lik.n_exact - space.ndim, 1))
    return _laplace_sample(space, x_lsq, cov, rng, 4000)


def _no_mcmc_draws(lik, lsq, x_lsq, opt: FitOptions, rng) -> tuple[np.ndarray, np.ndarray]:
    """(the point estimate, draws) of a fit without MCMC: the Laplace approximation at the
    least-squares optimum, or — with censored rows, which least squares leaves out — at the
    maximum of ln p (:func:`_censored_laplace`)."""
    if lik.censor and any(bool(d.kind.any()) for d in lik.data):
        found = _censored_laplace(lik, x_lsq, lsq.cov)
        if found is not None:
            return found[0], _laplace_sample(lik.space, found[0], found[1], rng, 4000)
    return x_lsq, _laplace_draws(lik, lsq, x_lsq, opt, rng)


def _censored_laplace(lik, x0: np.ndarray, cov0) -> tuple[np.ndarray, np.ndarray] | None:
    """The maximum of ln p and its Laplace covariance (the inverse Hessian of −ln p) when the
    likelihood holds censored rows and no MCMC will run. Why: least squares fits only the exact
    rows, and on a table whose dark rows were flagged by a threshold those are the rows selected
    for reading high — its optimum is biased (+4.9 posterior sd on the dark table of
    tests/fitting/test_negative_values.py); the censored terms, which undo that, enter only
    ln p. Started at the least-squares optimum; the discrepancy s stays at its point value as in
    :func:`_laplace_sample`. None when the optimum or the Hessian is not usable (then the least
    squares' Laplace approximation stands, as before)."""
    from scipy.optimize import minimize

    space = lik.space
    lo, hi = space.bounds
    disc = np.array([s.base == DISCREPANCY[0] for s in space.specs])
    if cov0 is not None and np.all(np.isfinite(np.diag(cov0))):
        scale = np.sqrt(np.clip(np.diag(cov0), 0, None))
    else:
        scale = np.abs(x0) * 1e-2
    # s is found with the rest (its best value at the least-squares optimum, which chased the
    # exact rows, is too large): internal units are ln s, a step of 0.5 suits it
    scale = np.where(disc, 0.5, np.where(scale > 0, scale, 1e-6))

    def x_of(u: np.ndarray) -> np.ndarray:
        return x0 + u * scale

    def cost(u: np.ndarray) -> float:
        lp = float(lik.log_prob(x_of(u)))
        return -lp if np.isfinite(lp) else 1e300

    # in units of the least-squares sd, so one step size suits every parameter
    bounds = list(zip((lo - x0) / scale, (hi - x0) / scale, strict=True))
    res = minimize(cost, np.zeros(space.ndim), method="L-BFGS-B", bounds=bounds)
    if not np.isfinite(res.fun) or res.fun >= 1e300:
        return None
    # central differences, steps of 0.05 least-squares sd: ln p's curvature over ±1 sd is
    # what a Laplace interval states, and the step stays far above ln p's rounding. Over the
    # parameters other than s: the Laplace draws hold s at its point value.
    u, d, h = res.x, space.ndim, 0.05
    step = np.eye(d) * h
    keep = np.flatnonzero(~disc)
    hess = np.zeros((d, d))
    for i in keep:
        for j in keep[keep >= i]:
            corners = [cost(u + a * step[i] + b * step[j]) for a, b in ((1, 1), (1, -1), (-1, 1))]
            corners.append(cost(u - step[i] - step[j]))
            if max(corners) >= 1e300:  # a step left the support: no curvature to read
                return None
            hess[i, j] = hess[j, i] = (corners[0] - corners[1] - corners[2] + corners[3]) / (
                4 * h * h
            )
    sub = hess[np.ix_(keep, keep)]
    try:
        inv = np.linalg.inv(sub)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(inv)) or np.any(np.linalg.eigvalsh((inv + inv.T) / 2) <= 0):
        return None
    cov = np.zeros((d, d))
    cov[np.ix_(keep, keep)] = inv * np.outer(scale[keep], scale[keep])
    return x_of(u), cov


def _laplace_sample(space, x, cov, rng, n: int) -> np.ndarray:
    """``n`` draws of N(x, cov) clipped to the prior box, the discrepancy (which least squares
    does not constrain) held at its point value."""
    cov = cov.copy()
    for i, spec in enumerate(space.specs):
        if spec.base == DISCREPANCY[0]:
            cov[i, :] = cov[:, i] = 0
    # C = s·(JᵀJ)⁻¹ is positive semi-definite by construction (s ≥ 0, rows zeroed); numpy checks
    # its factorisation at an absolute 1e-8, which a covariance with very different scales (a
    # parameter the data hardly constrain, which the "posterior ≈ prior" verdict reports)
    # fails by rounding alone, and would print a false "not positive-semidefinite" warning.
    draws = rng.multivariate_normal(x, cov, size=n, method="eigh", check_valid="ignore")
    return np.clip(draws, *space.bounds)


def model_values(lik: Likelihood, x: np.ndarray, table: SampleTable) -> np.ndarray:
    """The model at ``x`` (sampled space) for every row of ``table``; NaN for rows of channels
    the fit does not hold."""
    natural = lik.space.natural_dict(np.atleast_2d(x))
    out = np.full(len(table), np.nan)
    wi, wo = table.wi, table.wo
    for d in lik.data:
        rows = table.channel == d.channel
        if rows.any():
            params = lik.space.channel_params(natural, d.channel)
            with np.errstate(all="ignore"):
                fm = lik.model.evaluate(params, wi[rows], wo[rows])
            out[rows] = np.broadcast_to(np.asarray(fm, dtype=np.float64), (1, int(rows.sum())))[0]
    return out


def _correct_binning(table: SampleTable, lik: Likelihood, x, source):
    """(the binned table with each exact bin's mean corrected by the model's curvature over the
    bin at ``x``, f̄_b − ε_b, and ε_b/σ̄_b) — fitting.binning.binning_bias. The correction is
    exact for the model at ``x``; near ``x`` (within the posterior) it changes to second order."""
    from fitting.binning import binning_bias

    eps = binning_bias(source, table, lambda t: model_values(lik, x, t))
    corrected = table.select(np.ones(len(table), bool))
    corrected.f = table.f - eps * table.sigma
    corrected.metadata["gonio.binned_corrected"] = "curvature at the least-squares optimum"
    return corrected, eps


def _binning_diagnostics(table, lik, x_map, source, eps_corrected) -> dict:
    """What binning did and — with the file it came from — what it still moves after the
    curvature correction: the bias left, ε(x_map) − ε(x_lsq), as the bound ‖·‖ on the shift of
    any estimate and the linearised shift of each parameter, Δx = (JᵀJ)⁻¹Jᵀ(ε/σ̄) with J the
    whitened model Jacobian over the exact bins (finite differences), in posterior sds; and
    the same for the uncorrected bins (``uncorrected_*``, what the correction removed)
    (tests/fitting/test_binning.py checks both against refits)."""
    from fitting.binning import binning_bias

    info = {k: v for k, v in json.loads(table.metadata["gonio.binned"]).items() if k != "channels"}
    if source is None:
        return info
    eps = binning_bias(source, table, lambda t: model_values(lik, x_map, t))
    left = eps if eps_corrected is None else eps - eps_corrected
    rows = eps != 0
    sub = table.select(rows)
    base = model_values(lik, x_map, sub)
    jac = np.zeros((len(sub), x_map.size))
    for j in range(x_map.size):
        x = np.array(x_map, dtype=np.float64)
        x[j] += 1e-6 * max(abs(float(x[j])), 1.0)
        jac[:, j] = (model_values(lik, x, sub) - base) / (x[j] - x_map[j]) / sub.sigma
    informed = np.any(jac != 0, axis=0)  # the discrepancy s does not enter f̂
    cov = np.linalg.pinv(jac[:, informed].T @ jac[:, informed])
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    names = [n for n, ok in zip(lik.space.names, informed, strict=True) if ok]

    def shifts(e: np.ndarray) -> dict[str, float]:
        moved = (cov @ (jac[:, informed].T @ e[rows])) / np.where(sd > 0, sd, np.inf)
        return {n: float(v) for n, v in zip(names, moved, strict=True)}

    info["corrected"] = eps_corrected is not None
    info["bias_bound_sd"] = float(np.linalg.norm(left))
    info["shift_sd"] = shifts(left)
    info["max_shift_sd"] = max((abs(v) for v in info["shift_sd"].values()), default=0.0)
    info["uncorrected_bound_sd"] = float(np.linalg.norm(eps))
    info["uncorrected_shift_sd"] = shifts(eps)
    return info


def _goodness(lik, x_map) -> dict:
    # nuisance parameters are held by their priors, not fitted freely: no degree of freedom
    k = sum(s.prior_sigma is None for s in lik.space.specs)
    n = lik.n_exact
    r = lik.residuals(x_map, "sigma")
    ll = float(lik.log_likelihood(x_map)[0])
    chi2 = float(np.sum(r**2))
    dof = n - k
    out = {
        "chi2": chi2,
        "dof": dof,
        "chi2_red": chi2 / dof if dof > 0 else float("nan"),
        "aic": 2 * k - 2 * ll,
        "bic": float(k * np.log(n) - 2 * ll),
        "n": n,
    }
    selected = lik.chi2_selected(x_map)
    if selected is not None:
        # rows kept for reading above the detection limit (Likelihood.chi2_selected); the k
        # fitted parameters take ≈ k from the sum as they do from a plain χ²_n
        out["chi2_expected"] = selected[0] - k
        out["chi2_sd"] = math.sqrt(max(selected[1], 0.0))
    return out

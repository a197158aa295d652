"""Verdicts: what a fit says about itself — convergence and goodness of fit (issue 18 item 1).

Each verdict is a dict ``{"name", "status", "reason", "advice"}``: ``status`` is "ok",
"warning" or "fail", ``reason`` one line saying what was measured, ``advice`` one line saying
what to do ("" when ok). :func:`judge` gives, in this order:

* ``convergence`` — rank-normalised R̂ (fail > 1.1, warning > 1.01), bulk and tail ESS (fail
  < 100, warning < 400; fitting.convergence), chain length against 20 τ, stuck walkers
  (acceptance far below the ensemble's, or never moving) and lost walkers (typical ln p far
  below the ensemble's best). The sampler runs until R̂ and ESS meet their targets by itself
  (fitting.mcmc), so a warning here means a cap (--steps, --time-budget) stopped it first —
  the verdict says which, and how many steps the rule would need.
* ``chi2`` — χ²/dof against its sampling spread √(2/ν) for ν degrees of freedom.
* ``regions`` — the same per region of the Rusinkiewicz angles (θ_h, θ_d): residual structure
  the global χ² averages away (a missed specular core, a grazing-angle excess).
* ``discrepancy`` — the fitted fractional model error s against its prior [1e-4, 1].
* ``bounds`` — parameters whose posterior piles at a prior bound.
* ``energy`` — directional albedo of the fitted model > 1 at some incidence angle.
* ``identified`` — parameters whose posterior is about as wide as their prior.
* ``censoring`` — DARK and SATURATED counts and how they entered the fit.

The thresholds are module constants, each with the reason for its value. Inputs are plain
(an :class:`fitting.mcmc.McmcResult`, the fit's parameter summary, the parameter specs), so
each verdict can be tested on a constructed input as well as on a real fit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.stats import chi2 as _chi2

from fitting.convergence import TAU_LENGTHS
from fitting.mismatch import REGION_MIN_SAMPLES, exact_regions, region_label
from fitting.priors import DISCREPANCY, ParameterSpec

__all__ = [
    "STATUSES",
    "VERDICT_NAMES",
    "make_verdict",
    "mcmc_verdict",
    "walker_health",
    "chi2_verdict",
    "regions_verdict",
    "discrepancy_verdict",
    "bounds_verdict",
    "energy_verdict",
    "identified_verdict",
    "censoring_verdict",
    "binning_verdict",
    "judge",
    "failed",
]

STATUSES = ("ok", "warning", "fail")
VERDICT_NAMES = (
    "convergence",
    "chi2",
    "regions",
    "discrepancy",
    "bounds",
    "energy",
    "identified",
    "censoring",
)

# -- thresholds, each with its reason -------------------------------------------------------------
#: Gelman et al. (BDA3 §11.4): R̂ > 1.1 means the chains have not mixed — the posterior summary
#: is not trustworthy.
RHAT_FAIL = 1.1
#: Vehtari et al. 2021 (Bayesian Analysis 16(2)): R̂ < 1.01 before trusting quantiles.
RHAT_WARN = 1.01
#: Below 100 effective draws the 2.5 % tail holds fewer than 3 independent draws: the 95 %
#: interval's ends are Monte-Carlo noise.
ESS_FAIL = 100.0
#: Vehtari et al. 2021 recommend ESS ≥ 400 for stable R̂ and tail quantiles.
ESS_WARN = 400.0
#: The chain's length in τ before τ (and the burn-in from it) is trusted: fitting.convergence's
#: TAU_LENGTHS (20; why not emcee's 50 is said there).
TAU_LENGTH = float(TAU_LENGTHS)
#: A walker is *stuck* when its acceptance fraction is below this fraction of the ensemble's
#: median. All walkers of an ensemble share one proposal, so in a mixed ensemble their
#: acceptance differs only by counting noise (≤ 0.5/√N, < 0.02 for N ≥ 600 steps) and by
#: position; a factor of 5 below the median is far outside both.
STUCK_RATIO = 0.2
#: More than this fraction of walkers stuck (or lost) carries that much posterior mass at a
#: place the posterior does not put it: the intervals are visibly wrong (fail, not warning).
WALKER_FAIL_FRACTION = 0.1
#: A walker is *lost* when 2(ln p_max − its median ln p) exceeds the χ²_D quantile at 1 − 1e-6:
#: near the mode 2(ln p_max − ln p) ~ χ²_D (Laplace), and a healthy walker's median of it sits
#: near D, so this only fires for a walker in another, far less probable region.
LOST_TAIL = 1e-6
#: |z| of χ²/dof beyond these many sampling sd: 3 (p ≈ 0.003 two-sided) is a warning, 5 leaves
#: no doubt.
CHI2_Z_WARN = 3.0
CHI2_Z_FAIL = 5.0
#: ... and a fail also needs a deviation that matters: RMS residual / stated σ = √(χ²/dof)
#: beyond 1.5 or below 1/1.5 (errors 50 % larger or a third smaller than stated). With 10⁵
#: samples a 1 % error in σ is already 20 sd; that alone is a warning, not a failed fit.
CHI2_SIZE_FAIL = 1.5
#: The posterior of s piles at its upper bound 1 when the model misses the data by ≥ 100 %:
#: its width then comes from the prior edge, not the data.
#: A median s above 10 % of f means the parameters describe a compromise between regions the
#: model cannot fit together (docs/design.md §6: published fits of real materials reach ~10 %).
DISCREPANCY_WARN = 0.1
#: A bound is "piled at" when it lies within this fraction of the posterior's own 95 % width
#: of the 2.5 % (or 97.5 %) quantile: a Gaussian posterior untouched by the bound has its
#: quantile ≥ 0.4 sd away; one truncated at the bound (half-normal) has it at 0.03 sd.
BOUND_REACH = 0.1
#: Posterior ≈ prior: the central 68 % interval (in the sampled space, where every prior is
#: flat) spans ≥ 90 % of the prior's own central 68 % interval.
IDENTIFIED_RATIO = 0.9
#: Albedo tolerance: the half-vector quadrature (fitting.models.properties, n = 64) is accurate to
#: 2e-3 (property_table's tolerance); beyond 1 % the excess is more than a typical absolute
#: calibration error (~1 %) and a physically impossible fit (fail).
ALBEDO_QUADRATURE = 2e-3
ALBEDO_FAIL = 1.01
#: Incidence angles of the energy check, 0…89° (rad): the albedo of microfacet and Phong
#: lobes is largest at grazing incidence, so the grid goes close to it.
ALBEDO_THETA = np.radians([0.0, 20.0, 40.0, 60.0, 70.0, 80.0, 85.0, 89.0])
# The regions of (θ_h, θ_d) are fitting.mismatch's (one definition of "region").


def make_verdict(name: str, status: str, reason: str, advice: str = "") -> dict:
    """One verdict dict; ``advice`` is "" when ``status`` is "ok"."""
    if status not in STATUSES:
        raise ValueError(f"verdict status {status!r}: use one of {', '.join(STATUSES)}")
    return {
        "name": name,
        "status": status,
        "reason": reason,
        "advice": "" if status == "ok" else advice,
    }


def _worst(values: Mapping[str, float], largest: bool) -> tuple[str, float]:
    """(name, value) of the worst entry; a NaN counts as the worst."""
    for k, v in values.items():
        if v is None or not math.isfinite(v):
            return k, float("nan")
    k = (max if largest else min)(values, key=lambda n: values[n])
    return k, float(values[k])


# -- convergence ----------------------------------------------------------------------------------
def walker_health(chain: np.ndarray, log_prob: np.ndarray) -> tuple[list[int], list[int]]:
    """(stuck walkers, lost walkers) of a post-burn chain (N, W, D) and its ln p (N, W)."""
    chain = np.asarray(chain, dtype=np.float64)
    lp = np.asarray(log_prob, dtype=np.float64)
    if chain.shape[0] < 2:
        return [], []
    moved = np.any(chain[1:] != chain[:-1], axis=-1)  # (N−1, W): the walker's step was accepted
    acc = moved.mean(axis=0)
    stuck = np.flatnonzero((acc < STUCK_RATIO * np.median(acc)) | (acc == 0)).tolist()
    med = np.median(np.where(np.isfinite(lp), lp, -np.inf), axis=0)
    best = float(np.max(lp[np.isfinite(lp)])) if np.isfinite(lp).any() else float("nan")
    cut = float(_chi2.ppf(1.0 - LOST_TAIL, chain.shape[-1]))
    lost = np.flatnonzero(~(2.0 * (best - med) <= cut)).tolist()
    return stuck, [w for w in lost if w not in stuck]


def mcmc_verdict(mcmc, names: Sequence[str]) -> tuple[dict, list[str], str]:
    """(verdict, failed criteria, "converged_because" line) of an MCMC result (None: no MCMC).

    Criteria: R̂ < 1.01, ESS ≥ 400, chain ≥ 20 τ, no stuck and no lost walkers. A fail is
    R̂ > 1.1, ESS < 100, or more than 10 % of the walkers stuck or lost."""
    if mcmc is None:
        v = make_verdict(
            "convergence",
            "warning",
            "no MCMC was run: the intervals are the Laplace approximation at the optimum",
            "drop --no-mcmc to sample the posterior",
        )
        return v, ["mcmc"], "not converged: no MCMC run"
    rhat = dict(zip(names, np.asarray(mcmc.rhat, float).tolist(), strict=True))
    tail = getattr(mcmc, "ess_tail", None)
    bulk = np.asarray(mcmc.ess, float)
    ess_all = bulk if tail is None else np.minimum(bulk, np.asarray(tail, float))
    ess = dict(zip(names, ess_all.tolist(), strict=True))
    tau = dict(zip(names, np.asarray(mcmc.tau, float).tolist(), strict=True))
    r_name, r_max = _worst(rhat, largest=True)
    e_name, e_min = _worst(ess, largest=False)
    t_name, t_max = _worst(tau, largest=True)
    n_iter = int(mcmc.iterations)
    stuck, lost = walker_health(mcmc.chain, mcmc.log_prob)
    walkers = int(mcmc.chain.shape[1])
    fails, warns = [], []
    if not r_max <= RHAT_FAIL:
        fails.append(("rhat", f"R̂ {r_max:.4g} > {RHAT_FAIL} ({r_name})"))
    elif not r_max <= RHAT_WARN:
        warns.append(("rhat", f"R̂ {r_max:.4g} > {RHAT_WARN} ({r_name})"))
    if not e_min >= ESS_FAIL:
        fails.append(("ess", f"ESS {e_min:.0f} < {ESS_FAIL:.0f} ({e_name}, bulk or tail)"))
    elif not e_min >= ESS_WARN:
        warns.append(("ess", f"ESS {e_min:.0f} < {ESS_WARN:.0f} ({e_name}, bulk or tail)"))
    if not n_iter >= TAU_LENGTH * t_max:
        warns.append(
            ("length", f"chain {n_iter} < {TAU_LENGTH:.0f}τ = {TAU_LENGTH * t_max:.0f} ({t_name})")
        )
    for label, bad in (("stuck", stuck), ("lost", lost)):
        if bad:
            text = f"{len(bad)} of {walkers} walkers {label} ({_walker_list(bad)})"
            (fails if len(bad) > WALKER_FAIL_FRACTION * walkers else warns).append((label, text))
    met = (
        f"R̂ max {r_max:.4g} < {RHAT_WARN}, ESS (bulk and tail) min {e_min:.0f} ≥ {ESS_WARN:.0f}, "
        f"chain {n_iter} ≥ {TAU_LENGTH:.0f}τ ({TAU_LENGTH * t_max:.0f}), no stuck or lost walkers"
    )
    failed_names = [k for k, _ in fails + warns]
    if not fails and not warns:
        return make_verdict("convergence", "ok", met), [], met
    text = "; ".join(t for _, t in fails + warns)
    status = "fail" if fails else "warning"
    advice = "run a longer chain (--steps)"
    cap = {"max_steps": "the step cap (--steps)", "time_budget": "the time budget (--time-budget)"}
    stopped = [cap[r] for r in str(mcmc.stop_reason).split(",") if r in cap]
    if stopped:
        text = (
            f"stopped by {stopped[0]} at {n_iter} steps before R̂ and ESS met their targets: {text}"
        )
        needed = getattr(mcmc, "steps_needed", None)
        advice = (
            f"rerun with --steps {needed} (about what the rule needs)"
            if needed is not None and stopped[0].startswith("the step")
            else "rerun with a larger --steps or --time-budget"
        )
    if stuck or lost:
        advice = "run a longer chain (--steps) or start nearer the optimum; check for several modes"
    return make_verdict("convergence", status, text, advice), failed_names, f"not converged: {text}"


def _walker_list(idx: Sequence[int], limit: int = 5) -> str:
    head = ", ".join(str(i) for i in idx[:limit])
    return head + (", …" if len(idx) > limit else "")


# -- goodness of fit -----------------------------------------------------------------------------
def chi2_verdict(goodness: Mapping[str, float]) -> dict:
    """χ²/dof against 1 ± √(2/ν) (the χ²_ν/ν distribution's sd), ν = dof; or, where the exact
    rows were selected by a threshold (goodness "chi2_expected", "chi2_sd"), χ² against that
    expectation."""
    dof = goodness.get("dof")
    red = goodness.get("chi2_red")
    if not dof or dof <= 0 or red is None or not math.isfinite(red):
        return make_verdict(
            "chi2", "warning", "no degrees of freedom left: χ² cannot be judged", "add samples"
        )
    expected, spread = goodness.get("chi2_expected"), goodness.get("chi2_sd")
    if expected and spread and math.isfinite(expected) and math.isfinite(spread) and expected > 0:
        # rows selected by reading above the detection limit (fitting.fit._goodness): judge χ²
        # against the truncated normal's mean and sd, in the units of the plain case
        red = float(goodness["chi2"]) / expected
        sd = spread / expected
        z = (red - 1.0) / sd
        reason = (
            f"χ² = {goodness['chi2']:.4g} over {dof} dof of rows kept for reading above the "
            f"detection limit, whose expectation is {expected:.4g} ± {spread:.3g}: ratio "
            f"{red:.4g}, {z:+.1f} sd from 1"
        )
    else:
        sd = math.sqrt(2.0 / dof)
        z = (red - 1.0) / sd
        reason = f"χ²/dof = {red:.4g} with dof {dof}: {z:+.1f} sd from 1 (sd √(2/dof) = {sd:.2g})"
    if abs(z) <= CHI2_Z_WARN:
        return make_verdict("chi2", "ok", reason)
    big = not (1 / CHI2_SIZE_FAIL**2 <= red <= CHI2_SIZE_FAIL**2)
    status = "fail" if abs(z) > CHI2_Z_FAIL and big else "warning"
    if red > 1:
        advice = "the model misses the data or σ is underestimated: try another model (--model)"
    else:
        advice = "σ is overestimated: check the noise model of the calibration"
    return make_verdict("chi2", status, reason, advice)


def _region_table(reg, r) -> list[tuple[str, int, float, float]]:
    """(label, n, χ²/n, mean residual) per (θ_h, θ_d) region (index ``reg`` per row, from
    fitting.mismatch.region_index) with enough samples."""
    rows = []
    for k in range(9):
        sel = reg == k
        n = int(sel.sum())
        if n >= REGION_MIN_SAMPLES:
            rows.append((region_label(k), n, float(np.mean(r[sel] ** 2)), float(np.mean(r[sel]))))
    return rows


def regions_verdict(regions, residuals) -> dict:
    """χ²/n per region of (θ_h, θ_d) against its spread √(2/n), residuals (f − f̂)/σ of the
    exact samples in ``regions`` (their fitting.mismatch.region_index). The worst region
    decides, with the thresholds of :func:`chi2_verdict` (9 regions: |z| > 3 by chance
    somewhere with p ≈ 2.4 %)."""
    r = np.asarray(residuals, dtype=np.float64)
    rows = _region_table(np.asarray(regions), r)
    if not rows:
        return make_verdict(
            "regions", "ok", f"no region of (θ_h, θ_d) holds {REGION_MIN_SAMPLES} samples"
        )
    scored = [
        (label, n, red, mean, (red - 1.0) / math.sqrt(2.0 / n)) for label, n, red, mean in rows
    ]
    label, n, red, mean, z = max(scored, key=lambda t: abs(t[4]))
    # The mean of n unit residuals has sd 1/√n: beyond 3 of those the residuals lean one way.
    if abs(mean) * math.sqrt(n) > 3:
        side = "the model mostly " + ("above" if mean < 0 else "below") + " the data"
    else:
        side = "residuals on both sides"
    reason = (
        f"worst of {len(rows)} regions: {label}, χ²/n = {red:.3g} over {n} samples "
        f"({z:+.1f} sd), {side}"
    )
    if abs(z) <= CHI2_Z_WARN:
        return make_verdict("regions", "ok", reason)
    big = not (1 / CHI2_SIZE_FAIL**2 <= red <= CHI2_SIZE_FAIL**2)
    bad = sum(abs(t[4]) > CHI2_Z_WARN for t in scored)
    return make_verdict(
        "regions",
        "fail" if abs(z) > CHI2_Z_FAIL and big else "warning",
        f"{reason}; {bad} of {len(rows)} regions beyond {CHI2_Z_WARN:g} sd",
        "the model misses the data there: another model (--model all), or a plan with more "
        "samples in that region",
    )


def _internal(spec: ParameterSpec, value: float) -> float:
    if spec.log:
        return math.log(value) if value > 0 else -math.inf
    return float(value)


def _piles(spec: ParameterSpec, p: Mapping[str, float]) -> set[str]:
    """The prior bounds ("lower", "upper") one parameter's posterior piles at."""
    lo, hi = spec.internal_bounds
    q_lo, q_hi = _internal(spec, p["p2.5"]), _internal(spec, p["p97.5"])
    reach = BOUND_REACH * max(q_hi - q_lo, 0.0) + 1e-9 * (hi - lo)
    return {side for side, gap in (("lower", q_lo - lo), ("upper", hi - q_hi)) if gap <= reach}


def _width_ratio(spec: ParameterSpec, p: Mapping[str, float]) -> float:
    """Posterior 68 % span / the flat prior's own 68 % span, in the sampled space."""
    lo, hi = spec.internal_bounds
    return (_internal(spec, p["p84"]) - _internal(spec, p["p16"])) / (0.68 * (hi - lo))


def _mismatch_words(mismatch: Mapping | None) -> str:
    """'; largest in θh 30–90°, θd 30–60° (8 %); intervals widened up to ×2 (m)' — what the
    regional model error and the sandwich (fitting.mismatch) add to the verdict, or ''."""
    if not mismatch:
        return ""
    from fitting.mismatch import widening_words

    words = ""
    regions = [r for r in mismatch.get("regions", []) if r.get("median") is not None]
    if len(regions) > 1:
        worst = max(regions, key=lambda r: r["median"])
        words += f"; largest in {worst['label']} ({100 * worst['median']:.3g} %)"
    if mismatch.get("applied") or mismatch.get("reason") not in (None, "--no-widen"):
        words += "; " + widening_words(mismatch)
    return words


def discrepancy_verdict(
    parameters: Mapping[str, Mapping],
    specs: Sequence[ParameterSpec],
    mismatch: Mapping | None = None,
) -> dict:
    """The fitted model error s (fraction of f) against its prior; with ``mismatch`` (the fit's
    diagnostics from fitting.mismatch) also the region where it is largest and how much the
    intervals were widened for it."""
    spec = next((s for s in specs if s.name == DISCREPANCY[0]), None)
    if spec is None:
        return make_verdict("discrepancy", "ok", "no discrepancy term fitted (σ taken as given)")
    p = parameters[spec.name]
    s, hi = float(p["median"]), float(p["p97.5"])
    sides = _piles(spec, p)
    reason = f"model error s = {100 * s:.3g} % of f (95 % ≤ {100 * hi:.3g} %)"
    reason += _mismatch_words(mismatch)
    advice = "try another model (--model all ranks them)"
    # Spread over the whole prior first: then both bounds are "reached" and neither tells.
    if _width_ratio(spec, p) >= IDENTIFIED_RATIO:
        return make_verdict(
            "discrepancy",
            "warning",
            f"{reason}: spread over its whole prior — the data cannot tell the model error "
            "(it is small next to σ where the model is large)",
            advice,
        )
    if "upper" in sides:
        return make_verdict(
            "discrepancy",
            "fail",
            f"{reason}: piled at its prior bound {spec.upper:g} — the model misses the data by "
            "≥ 100 %",
            advice + " or check the data's flags",
        )
    if "lower" in sides:
        return make_verdict(
            "discrepancy", "ok", f"{reason}: at its lower bound — no model error detected"
        )
    if s > DISCREPANCY_WARN:
        return make_verdict(
            "discrepancy",
            "warning",
            f"{reason}: the parameters are a compromise the model cannot fit everywhere",
            advice,
        )
    return make_verdict("discrepancy", "ok", reason)


def _judged(parameters: Mapping[str, Mapping], specs: Sequence[ParameterSpec]):
    """(spec, its summary, posterior/prior width ratio) of each fitted parameter but s, which
    has its own verdict."""
    for spec in specs:
        if spec.name != DISCREPANCY[0] and spec.name in parameters:
            yield spec, parameters[spec.name], _width_ratio(spec, parameters[spec.name])


def bounds_verdict(parameters: Mapping[str, Mapping], specs: Sequence[ParameterSpec]) -> dict:
    """Parameters (s aside: its own verdict) whose posterior piles at a prior bound."""
    hits = []
    for spec, summary, ratio in _judged(parameters, specs):
        if ratio >= IDENTIFIED_RATIO:
            continue  # spread over the whole prior: the "identified" verdict names it
        for where in sorted(_piles(spec, summary)):
            bound = spec.lower if where == "lower" else spec.upper
            hits.append(f"{spec.name} at its {where} bound {bound:g}")
    if not hits:
        return make_verdict("bounds", "ok", "no parameter piles at a prior bound")
    return make_verdict(
        "bounds",
        "warning",
        "posterior piled at a prior bound: " + ", ".join(hits),
        "the interval is cut by the prior: if the bound is not physical, widen it (--priors)",
    )


def identified_verdict(parameters: Mapping[str, Mapping], specs: Sequence[ParameterSpec]) -> dict:
    """Parameters (s aside) whose posterior is about as wide as their (bounded, flat) prior."""
    weak = []
    for spec, _summary, ratio in _judged(parameters, specs):
        if ratio >= IDENTIFIED_RATIO:
            weak.append(f"{spec.name} ({ratio:.0%} of the prior's width)")
    if not weak:
        return make_verdict("identified", "ok", "every parameter is narrower than its prior")
    return make_verdict(
        "identified",
        "warning",
        "posterior ≈ prior, the data do not constrain: " + ", ".join(weak),
        "fix it (--fix) or measure where it matters (another plan)",
    )


def energy_verdict(model, channel_params: Mapping[str, Mapping[str, float]]) -> dict:
    """Largest directional albedo of the fitted model over θ_i 0…89° per channel.

    a(ω_i) = ∫ f_r cos θ_o dω_o by half-vector quadrature (fitting.models.properties; it integrates
    over ω_i at fixed ω_o, the same for a reciprocal model)."""
    from fitting.models.properties import directional_albedo

    worst_ch, worst_a, worst_t = "", -math.inf, 0.0
    for ch, params in channel_params.items():
        with np.errstate(all="ignore"):
            a = np.asarray(directional_albedo(model, dict(params), ALBEDO_THETA, n=64))
        a = np.where(np.isfinite(a), a, math.inf)
        i = int(np.argmax(a))
        if a[i] > worst_a:
            worst_ch, worst_a, worst_t = ch, float(a[i]), float(ALBEDO_THETA[i])
    reason = (
        f"largest directional albedo {worst_a:.4g} ({worst_ch}, θ_i = "
        f"{math.degrees(worst_t):.0f} deg)"
    )
    if worst_a <= 1.0 + ALBEDO_QUADRATURE:
        return make_verdict("energy", "ok", reason + " ≤ 1")
    conserving = bool(getattr(model, "flags", {}).get("energy_conserving", True))
    note = "" if conserving else " (the model's form is not energy conserving)"
    return make_verdict(
        "energy",
        "fail" if worst_a > ALBEDO_FAIL else "warning",
        f"{reason} > 1: the fit reflects more than it receives{note}",
        "fit with an energy-conservation prior (--priors with energy_conservation = true) or "
        "another model",
    )


def censoring_verdict(n_dark: int, n_saturated: int, censored: bool, n_total: int) -> dict:
    """How the DARK and SATURATED samples entered the fit (counts over the fitted channels)."""
    counts = f"{n_dark} DARK, {n_saturated} SATURATED of {n_total} samples"
    if n_dark + n_saturated == 0:
        return make_verdict("censoring", "ok", f"{counts}: none flagged")
    if censored:
        return make_verdict(
            "censoring", "ok", f"{counts}: entered as censored observations (Tobit likelihood)"
        )
    share = (n_dark + n_saturated) / max(n_total, 1)
    return make_verdict(
        "censoring",
        "warning",
        f"{counts} ({share:.0%}) dropped (--drop-flagged): what they say is ignored, which "
        "biases the fit",
        "refit without --drop-flagged to censor them",
    )


# -- all verdicts of a fit -----------------------------------------------------------------------
#: Binning moves an estimate by at most the bias bound (fitting.binning), in posterior sds: a
#: shift of 0.3 sd lowers a 95 % interval's coverage to ≈ 94 % (negligible), 1 sd to ≈ 83 %
#: (the interval can no longer be trusted).
BINNING_WARN_SD = 0.3
BINNING_FAIL_SD = 1.0


def lobes_verdict(parameters: Mapping, draws: Mapping | None = None) -> dict:
    """Whether a two-lobe fit's lobes are distinguishable (fitting.models.multilobe.check_lobes): a
    warning naming why when they are not — the second lobe is then the prior's, not the data's."""
    from fitting.models.multilobe import check_lobes

    flat = None
    if draws is not None:
        flat = {k: np.asarray(v).reshape(-1) for k, v in draws.items() if k.startswith("ks")}
    check = check_lobes(parameters, draws=flat)
    if check.distinguishable:
        return make_verdict("lobes", "ok", "the two lobes are distinguishable", "")
    return make_verdict(
        "lobes",
        "warning",
        "the two lobes are not distinguishable: " + "; ".join(check.reasons),
        "fit one lobe (heavy-tail or torrance-sparrow), or measure where the broad lobe "
        "differs from the sharp one (off-specular and grazing directions)",
    )


def binning_verdict(info: Mapping) -> dict:
    """What binning the samples (fitting.binning) moved: the largest linearised shift of a
    parameter in posterior sds (fitting.fit), with the bound on any combination beside it."""
    width = info.get("width_deg")
    what = f"{info.get('rows', 0):,} rows binned into {info.get('bins', 0):,} cells of {width:g}°"
    shift = info.get("max_shift_sd")
    smaller = f"refit with --bin {width / 2:g} (or --bin 0 to fit every row)"
    if shift is None:
        return make_verdict(
            "binning",
            "warning",
            f"{what}; its effect was not measured",
            f"to measure it, {smaller}",
        )
    moved = info.get("shift_sd") or {}
    worst = max(moved, key=lambda n: abs(moved[n])) if moved else "-"
    after = "after the curvature correction " if info.get("corrected") else ""
    said = (
        f"{what}: {after}it moves the estimates by at most {shift:.2g} posterior sd ({worst}; "
        f"any combination of them by ≤ {info.get('bias_bound_sd', float('nan')):.2g} sd)"
    )
    if shift <= BINNING_WARN_SD:
        return make_verdict("binning", "ok", said)
    status = "fail" if shift > BINNING_FAIL_SD else "warning"
    return make_verdict("binning", status, said, smaller)


def judge(fit, lik, mcmc) -> tuple[list[dict], dict]:
    """(verdicts in VERDICT_NAMES order, diagnostics additions) of a fit.

    ``fit`` a :class:`fitting.result.FitResult` (parameters, goodness), ``lik`` its
    :class:`fitting.likelihood.Likelihood`, ``mcmc`` its McmcResult or None. The diagnostics
    additions are ``converged`` (the criteria of :func:`mcmc_verdict`),
    ``converged_because`` (one line) and ``failed_criteria`` (names, [] when converged).
    """
    space = lik.space
    specs = space.specs
    conv, failed_criteria, because = mcmc_verdict(mcmc, space.names)
    x_map = space.to_internal(np.array([fit.parameters[n]["map"] for n in space.names]))
    natural = space.natural_dict(x_map[None, :])
    per_channel = {
        ch: {k: float(v[0, 0]) for k, v in space.channel_params(natural, ch).items()}
        for ch in space.channels
    }
    verdicts = [
        conv,
        chi2_verdict(fit.goodness),
        regions_verdict(*_exact_residuals(lik, x_map)),
        discrepancy_verdict(fit.parameters, specs, fit.diagnostics.get("mismatch")),
        bounds_verdict(fit.parameters, specs),
        energy_verdict(lik.model, per_channel),
        identified_verdict(fit.parameters, specs),
        censoring_verdict(lik.n_dark, lik.n_saturated, lik.censor, lik.n_considered),
    ]
    if "binning" in fit.diagnostics:  # only binned fits (fitting.binning) have this verdict
        verdicts.append(binning_verdict(fit.diagnostics["binning"]))
    if "m_ratio" in fit.parameters:  # two-lobe fits (fitting.models.multilobe) only
        draws = fit.extras.get("draws")
        natural = None if draws is None else space.natural_dict(draws)
        verdicts.append(lobes_verdict(fit.parameters, natural))
    extra = {
        "converged": not failed_criteria,
        "converged_because": because,
        "failed_criteria": failed_criteria,
    }
    return verdicts, extra


def _exact_residuals(lik, x_map: np.ndarray):
    """(region index, (f − f̂)/σ) of the exact samples at x_map, channels concatenated."""
    return exact_regions(lik), lik.residuals(x_map, "sigma")


def failed(verdicts: Sequence[Mapping]) -> list[str]:
    """Names of the verdicts with status "fail"."""
    return [str(v["name"]) for v in verdicts if v.get("status") == "fail"]

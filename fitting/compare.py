"""Model comparison: WAIC, PSIS-LOO (with Pareto k̂ diagnostics), AIC/BIC, ranked table (issue 7).

Inputs are pointwise log-likelihoods ``ll`` of shape (S, n): S posterior draws × n samples
(:meth:`fitting.likelihood.Likelihood.pointwise_log_likelihood`). All models compared must be
fitted to the *same* n samples (same table, channels and censoring) so the pointwise
differences are meaningful.

* WAIC (Watanabe 2010; Vehtari, Gelman & Gabry 2017, eqs. 3–5, 11–12):
  lppd_j = ln( (1/S) Σ_s p(y_j|θ_s) ),  p_waic,j = Var_s[ln p(y_j|θ_s)],
  elpd_waic = Σ_j (lppd_j − p_waic,j),  WAIC = −2 elpd_waic.
* PSIS-LOO (Vehtari, Gelman & Gabry 2017, "Practical Bayesian model evaluation using
  leave-one-out cross-validation and WAIC", Stat. Comput. 27:1413, §2.1 and §3):
  raw importance ratios r_s = 1/p(y_j|θ_s); the M = min(⌈0.2 S⌉, ⌈3√S⌉) largest are replaced
  by expected order statistics of a generalized Pareto distribution fitted to them (Zhang &
  Stephens 2009 estimator with the weakly informative prior of Vehtari et al.: k̂ ←
  (M k̂ + 10·0.5)/(M + 10)), truncated at the largest raw ratio; then
  elpd_loo,j = ln( Σ_s w_s p(y_j|θ_s) / Σ_s w_s ).  p_loo = lppd − elpd_loo.
  k̂ > 0.7 means that sample's LOO estimate is unreliable (heavy-tailed ratios).
* SE of an elpd: √(n Var_j elpd_j); of a difference between models A and B:
  √(n Var_j (elpd_A,j − elpd_B,j)) (Vehtari et al. 2017, eq. 24). Units: nats (ln-density,
  f in sr⁻¹).
* AIC / BIC are copied from the fit JSON goodness (at the MAP, see :mod:`fitting.fit`).

Only a reliable score is ranked: a model whose PSIS-LOO has any k̂ > 0.7 (its elpd is then not
an estimate of the out-of-sample fit; Vehtari et al. 2017 §2.1, 2024) or whose sampler failed
its convergence verdict (the draws are not the posterior) is listed below the ranked ones,
unranked, with the reason. A difference of less than 2 SE between two ranked models does not
separate them (:func:`margin_words`).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from brdfdata.coverage import coverage_report
from plumbing.atomic import atomic_write_bytes
from plumbing.inputs import MiB, check_nesting, read_input_text

__all__ = [
    "COMPARE_SCHEMA_VERSION",
    "KHAT_BAD",
    "gpd_fit",
    "psis_smooth",
    "waic",
    "psis_loo",
    "posterior_draws",
    "pointwise_log_likelihood",
    "ModelScore",
    "score_fit",
    "rank",
    "margin_words",
    "write_compare",
    "read_compare",
    "Candidate",
    "Skipped",
    "candidates",
    "restrict",
    "run_comparison",
]

COMPARE_SCHEMA_VERSION = 2  # 2: unranked rows (rank null, why_unranked), "skipped"
#: Pareto k̂ above which a PSIS-LOO term is unreliable (Vehtari et al. 2017/2024).
KHAT_BAD = 0.7


def _lse(a: np.ndarray, axis: int = 0) -> np.ndarray:
    """ln Σ exp(a) along ``axis``, max-shifted (scipy's logsumexp costs ~10× more here)."""
    mx = np.max(a, axis=axis, keepdims=True)
    mx = np.where(np.isfinite(mx), mx, 0.0)
    with np.errstate(divide="ignore"):
        out = np.log(np.sum(np.exp(a - mx), axis=axis, keepdims=True)) + mx
    return np.squeeze(out, axis=axis)


def _gpd_fit_columns(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`gpd_fit` for every column of ``x`` (M, n) at once (each column sorted ascending)."""
    x = np.asarray(x, dtype=np.float64)
    n = x.shape[0]
    m = 30 + int(math.sqrt(n))
    grid = 1.0 - np.sqrt(m / (np.arange(1, m + 1, dtype=np.float64) - 0.5))
    with np.errstate(all="ignore"):
        b = grid[:, None] / (3.0 * x[int(n / 4 + 0.5) - 1])[None, :] + (1.0 / x[-1])[None, :]
        k = np.empty_like(b)
        step = max(1, 4_000_000 // (m * n))  # columns per chunk: ≤ 4e6 temporaries
        for c in range(0, x.shape[1], step):
            k[:, c : c + step] = np.log1p(
                -b[:, None, c : c + step] * x[None, :, c : c + step]
            ).mean(axis=1)
        profile = n * (np.log(-b / k) - k - 1.0)
        # Normalised exp(profile) (= 1/Σ_j exp(L_j − L_i)); weights < 10 ε are dropped.
        w = np.exp(profile - _lse(profile, axis=0))
        w = np.where(w >= 10 * np.finfo(float).eps, w, 0.0)
        w /= w.sum(axis=0)
        b_post = np.sum(b * w, axis=0)
        k_post = np.log1p(-b_post[None, :] * x).mean(axis=0)
        sigma = -k_post / b_post
    k_post = (n * k_post + 10 * 0.5) / (n + 10)
    return k_post, sigma


def gpd_fit(x: np.ndarray) -> tuple[float, float]:
    """Generalized Pareto (shape k, scale σ) fitted to exceedances ``x`` > 0, sorted ascending.

    Zhang & Stephens (2009), "A new and efficient estimation method for the generalized Pareto
    distribution", Technometrics 51:316 — the profile-posterior mean of b = −k/σ over a grid
    of m = 30 + ⌊√n⌋ points, k = mean ln(1 − b x) (k > 0: heavy tail), σ = −k/b; then the
    weakly informative prior of Vehtari et al. (2017, appendix), k ← (n k + 5)/(n + 10).
    """
    k, sigma = _gpd_fit_columns(np.asarray(x, dtype=np.float64)[:, None])
    return float(k[0]), float(sigma[0])


def _gpd_quantile(p: np.ndarray, k, sigma) -> np.ndarray:
    """Inverse CDF of the GPD: σ ((1 − p)^(−k) − 1)/k, or −σ ln(1 − p) for k → 0."""
    k = np.asarray(k, dtype=np.float64)
    small = np.abs(k) < 1e-12
    with np.errstate(all="ignore"):
        q = sigma * np.expm1(-k * np.log1p(-p)) / np.where(small, 1.0, k)
    return np.where(small, -sigma * np.log1p(-p), q)


def _psis_column(x: np.ndarray, m: int) -> tuple[np.ndarray, float]:
    """One column (log ratios minus their max), general case: ties and tiny cutoffs."""
    tiny = math.log(np.finfo(float).tiny)
    x = x.copy()
    order = np.argsort(x)
    cutoff = max(x[order[-m - 1]], tiny)
    tail = np.flatnonzero(x > cutoff)
    khat = math.inf
    if tail.size > 4:
        t_order = np.argsort(x[tail])
        exceed = np.exp(x[tail][t_order]) - math.exp(cutoff)
        k, sigma = gpd_fit(exceed)
        khat = k if math.isfinite(k) else math.inf
        if math.isfinite(k):
            p = (np.arange(tail.size) + 0.5) / tail.size
            x[tail[t_order]] = np.log(_gpd_quantile(p, k, sigma) + math.exp(cutoff))
            x[x > 0] = 0.0  # truncate at the largest raw ratio
    return x - _lse(x), khat


def psis_smooth(log_ratios: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pareto-smoothed importance log-weights for log ratios (S, n) → (log w (S, n), k̂ (n,)).

    Each column's log weights are normalised (logsumexp = 0). The M largest ratios of each
    column are replaced by GPD quantiles at (z − ½)/M, z = 1…M, truncated at the largest raw
    ratio. A column whose tail has ≤ 4 draws gets k̂ = inf and is left unsmoothed. Columns are
    processed together; ones with ties at the cutoff take the per-column path.
    """
    lr = np.asarray(log_ratios, dtype=np.float64)
    if lr.ndim == 1:
        lr = lr[:, None]
    s, n = lr.shape
    m = int(math.ceil(min(0.2 * s, 3.0 * math.sqrt(s))))
    # Rows = samples j, contiguous draws: the sorts and gathers run along memory.
    x = np.ascontiguousarray((lr - lr.max(axis=0)).T)  # max 0: no overflow in exp
    order = np.argsort(x, axis=1)
    xs = np.take_along_axis(x, order, axis=1)
    cutoff = xs[:, s - m - 1]
    tiny = math.log(np.finfo(float).tiny)
    simple = (cutoff > tiny) & (xs[:, s - m] > cutoff) & (m > 4)
    khat = np.full(n, np.inf)
    if simple.any():
        cols = np.flatnonzero(simple)
        exp_cut = np.exp(cutoff[cols])
        exceed = np.exp(xs[cols, s - m :].T) - exp_cut
        k, sigma = _gpd_fit_columns(exceed)
        ok = np.isfinite(k) & np.isfinite(sigma)
        p = ((np.arange(m) + 0.5) / m)[:, None]
        with np.errstate(all="ignore"):
            smooth = np.log(_gpd_quantile(p, k[None, :], sigma[None, :]) + exp_cut[None, :])
        smooth = np.minimum(smooth, 0.0)  # truncate at the largest raw ratio
        tail = xs[cols, s - m :].T
        xs[cols, s - m :] = np.where(ok[None, :], smooth, tail).T
        khat[cols] = np.where(ok, k, np.inf)
    out_t = np.empty_like(x)
    np.put_along_axis(out_t, order, xs, axis=1)
    out_t -= _lse(out_t, axis=1)[:, None]
    out = out_t.T
    for j in np.flatnonzero(~simple):
        out[:, j], khat[j] = _psis_column(x[j], m)
    return out, khat


def _se(pointwise: np.ndarray) -> float:
    n = pointwise.size
    return float(math.sqrt(n * np.var(pointwise, ddof=1))) if n > 1 else float("nan")


def waic(ll: np.ndarray) -> dict:
    """WAIC from pointwise ln-likelihoods (S, n): elpd, se, p_waic, waic = −2 elpd, pointwise."""
    ll = np.asarray(ll, dtype=np.float64)
    s = ll.shape[0]
    lppd = _lse(ll, axis=0) - math.log(s)
    with np.errstate(invalid="ignore"):
        p = np.var(ll, axis=0, ddof=1)
    elpd_i = lppd - p
    return {
        "elpd": float(elpd_i.sum()),
        "se": _se(elpd_i),
        "p": float(p.sum()),
        "waic": float(-2 * elpd_i.sum()),
        "n_var_gt_0_4": int(np.sum(p > 0.4)),  # Vehtari et al. 2017: WAIC unreliable there
        "pointwise": elpd_i,
    }


def psis_loo(ll: np.ndarray) -> dict:
    """PSIS-LOO from pointwise ln-likelihoods (S, n): elpd, se, p_loo, looic, k̂ per sample."""
    ll = np.asarray(ll, dtype=np.float64)
    s = ll.shape[0]
    lw, khat = psis_smooth(-ll)
    elpd_i = _lse(lw + ll, axis=0)
    lppd = _lse(ll, axis=0) - math.log(s)
    return {
        "elpd": float(elpd_i.sum()),
        "se": _se(elpd_i),
        "p": float((lppd - elpd_i).sum()),
        "looic": float(-2 * elpd_i.sum()),
        "khat": khat,
        "khat_max": float(np.max(khat)) if khat.size else float("nan"),
        "n_khat_bad": int(np.sum(khat > KHAT_BAD)),
        "pointwise": elpd_i,
    }


def posterior_draws(result, max_draws: int = 500, seed: int = 0) -> np.ndarray:
    """Up to ``max_draws`` posterior draws (S, D) in the sampled space from a fresh FitResult.

    MCMC chain if there is one (thinned evenly, so autocorrelation is spread), else the
    Laplace approximation N(x̂, C_LSQ) clipped to the prior box (what fit_samples reports
    without MCMC), else the point estimate alone.
    """
    ex = result.extras
    if "mcmc" in ex:
        flat = ex["mcmc"].flat
        idx = np.linspace(0, flat.shape[0] - 1, min(max_draws, flat.shape[0])).astype(int)
        return flat[idx]
    lsq, space = ex["lsq"], ex["space"]
    # The reported MAP (fit_samples sets the discrepancy s by a 1-D search after LSQ).
    x = space.to_internal(np.array([result.parameters[n]["map"] for n in space.names]))
    if lsq.cov is None:
        return x[None, :]
    # As fit_samples: s is held at its point value (LSQ does not constrain it), and with s
    # fitted the covariance is inflated by max(1, χ²/dof) (Birge ratio).
    cov = np.array(lsq.cov, dtype=np.float64)
    i_disc = [i for i, sp in enumerate(space.specs) if sp.base == "discrepancy"]
    for i in i_disc:
        cov[i, :] = cov[:, i] = 0.0
    red = result.goodness.get("chi2_red")
    if i_disc and red is not None and math.isfinite(red):
        cov *= max(1.0, float(red))
    lo, hi = space.bounds
    rng = np.random.default_rng(seed)
    d = rng.multivariate_normal(x, cov, size=max_draws, method="eigh")
    return np.clip(d, lo, hi)


def pointwise_log_likelihood(lik, draws: np.ndarray, chunk: int = 64) -> np.ndarray:
    """(S, n) ln-likelihood per draw and sample, computed ``chunk`` draws at a time."""
    draws = np.atleast_2d(draws)
    return np.concatenate(
        [lik.pointwise_log_likelihood(draws[i : i + chunk]) for i in range(0, len(draws), chunk)]
    )


@dataclass
class ModelScore:
    """One row of the comparison table (nats for elpd; AIC/BIC on the −2 ln L scale)."""

    label: str
    model: str
    options: dict
    shared: list[str]
    k: int
    n: int
    elpd_loo: float
    se_loo: float
    p_loo: float
    looic: float
    khat_max: float
    n_khat_bad: int
    elpd_waic: float
    se_waic: float
    p_waic: float
    waic: float
    aic: float
    bic: float
    d_elpd: float = 0.0
    d_se: float = 0.0
    rank: int | None = None  # None: not ranked (why_unranked says why)
    why_unranked: str = ""
    warnings: list[str] = field(default_factory=list)
    pointwise: np.ndarray | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("pointwise")
        return {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()
        }


def score_fit(
    result, label: str | None = None, *, max_draws: int = 500, seed: int = 0
) -> ModelScore:
    """WAIC, PSIS-LOO, AIC, BIC of a fresh :class:`fitting.result.FitResult` (with extras),
    and why it cannot be ranked where it cannot (see the module docstring)."""
    lik = result.extras["likelihood"]
    space = result.extras["space"]
    ll = pointwise_log_likelihood(lik, posterior_draws(result, max_draws, seed))
    w = waic(ll)
    lo = psis_loo(ll)
    n = int(ll.shape[1])
    why = []
    if lo["n_khat_bad"]:
        why.append(
            f"its PSIS-LOO is unreliable: Pareto k̂ > {KHAT_BAD} at {lo['n_khat_bad']} of {n} "
            f"samples (max {lo['khat_max']:.2f}, p_loo {lo['p']:.3g})"
        )
    conv = next((v for v in result.verdicts or [] if v.get("name") == "convergence"), None)
    if conv is not None and conv.get("status") == "fail":
        why.append(f"its sampler did not converge ({conv.get('reason', '')})")
    warnings = []
    if result.diagnostics.get("stop_reason") == "no_mcmc":
        warnings.append("Laplace draws (no MCMC)")
    shared = [s.name for s in space.specs if s.name == s.base and s.base != "discrepancy"]
    return ModelScore(
        label=label or result.model,
        model=result.model,
        options=dict(result.options),
        shared=shared,
        k=int(space.ndim),
        n=n,
        elpd_loo=lo["elpd"],
        se_loo=lo["se"],
        p_loo=lo["p"],
        looic=lo["looic"],
        khat_max=lo["khat_max"],
        n_khat_bad=lo["n_khat_bad"],
        elpd_waic=w["elpd"],
        se_waic=w["se"],
        p_waic=w["p"],
        waic=w["waic"],
        aic=float(result.goodness.get("aic", float("nan"))),
        bic=float(result.goodness.get("bic", float("nan"))),
        why_unranked="; ".join(why),
        warnings=warnings,
        pointwise=lo["pointwise"],
    )


def rank(scores: Sequence[ModelScore]) -> list[ModelScore]:
    """The reliable scores sorted by elpd_loo (best first) with rank 1, 2, … and ΔELPD =
    elpd − elpd_best ≤ 0 with its SE; then the unreliable ones (``why_unranked`` set), rank
    None and no ΔELPD, in the same order."""

    def by_elpd(group: list[ModelScore]) -> list[ModelScore]:
        return sorted(group, key=lambda s: -s.elpd_loo if math.isfinite(s.elpd_loo) else math.inf)

    ordered = by_elpd([s for s in scores if not s.why_unranked])
    unranked = by_elpd([s for s in scores if s.why_unranked])
    for s in unranked:
        s.rank, s.d_elpd, s.d_se = None, float("nan"), float("nan")
    if not ordered:
        return unranked
    best = ordered[0]
    for i, s in enumerate(ordered):
        s.rank = i + 1
        s.d_elpd = s.elpd_loo - best.elpd_loo
        if s is best:
            s.d_se = 0.0
        elif (
            s.pointwise is not None
            and best.pointwise is not None
            and s.pointwise.shape == best.pointwise.shape
        ):
            s.d_se = _se(s.pointwise - best.pointwise)
        else:
            s.d_se = float("nan")
    return ordered + unranked


def margin_words(best: ModelScore, other: ModelScore) -> str:
    """How ``other`` (ranked below ``best``) compares, in words: separated when its ΔELPD is
    more than 2 SE of the pointwise difference below the best, else not (a normal
    approximation to the difference: within 2 SE is no clear preference; Vehtari et al.
    2017 §5, Sivula et al. 2022)."""
    d, se = other.d_elpd, other.d_se
    if not (math.isfinite(d) and math.isfinite(se)):
        return f"{other.label}: no SE of its difference from {best.label}"
    if -d > 2 * se:
        return f"{best.label} predicts better than {other.label} by {-d:.3g} ± {se:.2g} nats"
    return (
        f"{best.label} and {other.label} are not separated: ΔELPD {d:.3g} ± {se:.2g} nats is "
        "within 2 SE"
    )


def write_compare(
    path: str | os.PathLike, scores: Sequence[ModelScore], skipped: Sequence[Skipped] = ()
) -> Path:
    """compare.json: {"schema_version", "criterion": "elpd_loo", "models": [row, …] ranked
    best first then unranked (rank null, why_unranked), "skipped": [{model, reason}, …]}."""
    path = Path(path)
    doc = {
        "schema_version": COMPARE_SCHEMA_VERSION,
        "criterion": "elpd_loo",
        "models": [s.to_dict() for s in scores],
        "skipped": [asdict(s) for s in skipped],
    }
    data = (json.dumps(doc, indent=2, allow_nan=False) + "\n").encode()
    return atomic_write_bytes(path, data, overwrite=True)


def read_compare(path: str | os.PathLike) -> tuple[list[dict], list[Skipped]]:
    """(rows, models left out) of a compare.json (raises ValueError with one line if it is
    not one; a schema-1 file has no "skipped")."""
    path = Path(path)
    try:
        text = read_input_text(path, "compare.json", 256 * MiB)
        check_nesting(text, path, "compare.json")
        doc = json.loads(text)
        rows = doc["models"]
        skipped = [Skipped(str(r["model"]), str(r["reason"])) for r in doc.get("skipped", [])]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: not a compare.json ({type(exc).__name__})") from None
    if not isinstance(rows, list):
        raise ValueError(f"{path}: not a compare.json")
    return rows, skipped


@dataclass(frozen=True)
class Candidate:
    """One model fit to compare: ``label`` names its files (fit-<label>.json)."""

    label: str
    model: str
    options: dict
    shared: tuple[str, ...]


def _shared_for(model, shared: Sequence[str]) -> tuple[str, ...]:
    """The requested shared names that ``model`` has; Phong's exponent n stands in for m."""
    names = model.parameter_names
    out = [s for s in shared if s in names]
    if "m" in shared and "m" not in names and "n" in names:
        out.append("n")
    return tuple(out)


def shared_for(model, shared: Sequence[str], name: str) -> tuple[str, ...]:
    """The names of `shared` that ``model`` (registered as `name`) shares across channels: m,
    the default of every fit command, is the lobe's width where a model has one (Phong's n) and
    nothing where it has none (a Lambertian model); any other name the model lacks is a
    ValueError naming the model's parameters."""
    unknown = set(shared) - set(model.parameter_names) - {"m"}
    if unknown:
        raise ValueError(
            f"--shared {', '.join(sorted(unknown))}: not a parameter of {name} "
            f"(parameters: {', '.join(model.parameter_names)})"
        )
    return _shared_for(model, shared)


@dataclass(frozen=True)
class Skipped:
    """A model ``--model all`` does not fit, and why (listed by the command and compare.json)."""

    model: str
    reason: str


def _selection(
    model: str, options: Mapping | None, directions
) -> tuple[list[tuple[str, dict]], list[Skipped]]:
    """([(name, options)], skipped) that a --model value names: one name (options validated
    by the registry), names separated by commas, or "all" — every registered model and named
    variant, each with the ``options`` that apply to it (:func:`fitting.models.
    applicable_options`), except a variant that the options make the same model as one
    already chosen and, when ``directions`` (wi, wo) are given, an anisotropic model on
    samples measured in too few orientations of the sample to determine (α_x, α_y, φ₀)."""
    from fitting import models

    if model != "all" and "," not in model:
        return [(model, {str(k): str(v) for k, v in (options or {}).items()})], []
    if model == "all":
        names = models.names()
    else:
        names = [models.resolve(n.strip()) for n in model.split(",") if n.strip()]
    orientations = None
    if directions is not None and any("orientations" in models.entry(n).needs for n in names):
        orientations = coverage_report(("orientations",), *directions).regions[0]
    chosen, skipped, seen = [], [], {}
    for name in dict.fromkeys(names):
        opts = models.applicable_options(name, options)
        e = models.entry(name)
        same = (e.base or e.name, tuple(sorted(models.full_options(name, opts).items())))
        if same in seen:
            skipped.append(Skipped(name, f"the same model as {seen[same]} with these options"))
        elif (
            orientations is not None and orientations.status != "ok" and ("orientations" in e.needs)
        ):
            skipped.append(
                Skipped(
                    name,
                    f"anisotropic, but the samples reach {orientations.count} of the "
                    f"{orientations.needed} sample orientations (bins of the half vector's "
                    "azimuth) it needs to tell α_x, α_y and φ₀ apart; fit it by name to try",
                )
            )
        else:
            seen[same] = name
            chosen.append((name, opts))
    return chosen, skipped


def candidates(
    model: str,
    options: Mapping | None = None,
    shared: Sequence[str] = ("m",),
    *,
    compare_shared: bool = False,
    directions=None,
) -> tuple[list[Candidate], list[Skipped]]:
    """(the fits, the models left out with the reason) a ``gonio fit --model`` call asks
    for: one model (a registered name, a named variant or an alias, its options validated by
    the registry: ValueError naming the allowed ones), several separated by commas, or "all"
    (every registered one the samples can determine; the others come back as
    :class:`Skipped`). With several models each takes the ``options`` that apply to it and
    have an allowed value, and shared names a model lacks are dropped for it. ``m`` stands
    for the Phong exponent n where a model has no m; any other unknown shared name is an
    error for a single model. With ``compare_shared`` each model whose shared set is
    non-empty is fitted again with every parameter per channel (label suffix
    ``-per-channel``). ``directions`` (wi, wo): the samples' directions, which decide
    whether an anisotropic model can be determined."""
    from fitting import models

    chosen, skipped = _selection(model, options, directions)
    single = len(chosen) == 1 and model != "all" and "," not in model
    out = []
    for name, opts in chosen:
        m = models.get(name, **opts)
        sh = shared_for(m, shared, name) if single else _shared_for(m, shared)
        out.append(Candidate(name, name, opts, sh))
        if compare_shared and sh:
            out.append(Candidate(f"{name}-per-channel", name, opts, ()))
    return out, skipped


def restrict(model, fix: Mapping[str, float] | None, priors) -> tuple[dict, object]:
    """``fix`` and a PriorsConfig reduced to the names ``model`` knows (for ``--model all``,
    where one --fix or priors file serves several models)."""
    names = set(model.parameter_names) | {"discrepancy"}

    def known(key: str) -> bool:
        base, _, _ = key.rpartition("_")
        return key in names or base in names

    fix = {k: v for k, v in (fix or {}).items() if known(k)}
    if priors is not None:
        priors = priors.model_copy(
            update={"parameters": {k: v for k, v in priors.parameters.items() if known(k)}}
        )
    return fix, priors


def candidate_options(base, c: Candidate, *, comparison: bool = True):
    """The FitOptions of candidate ``c``: ``base`` with the candidate's model, options and
    shared names; in a comparison its fixes and priors reduced to the names the model knows
    (one --fix or priors file serves several models), in a single fit taken as given."""
    from fitting import models
    from fitting.priors import PriorsConfig, load_priors

    opts = base.replace(model=c.model, model_options=dict(c.options), shared=c.shared)
    if not comparison:
        return opts
    priors = base.priors
    if priors is not None and not isinstance(priors, PriorsConfig):
        priors = load_priors(priors)
    fx, pr = restrict(models.get(c.model, **c.options), base.fix, priors)
    return opts.replace(fix=fx, priors=pr)


def run_comparison(
    table,
    cands: Sequence[Candidate],
    base,
    *,
    out_dir: str | os.PathLike,
    on_fit=None,
    progress: bool = False,
    setups: Mapping | None = None,
    skipped: Sequence[Skipped] = (),
) -> tuple[list[ModelScore], dict]:
    """Fit every candidate with its :func:`candidate_options` of the `base` FitOptions, write
    fit-<label>.json/.h5 in ``out_dir``, score and rank them, write ``out_dir/compare.json``.
    ``on_fit(candidate, result)`` is called after each fit; ``setups`` (label →
    fitting.fit.FitSetup) are the candidates' setups where the caller has checked them;
    ``skipped`` (:func:`candidates`) are listed in compare.json.
    Returns (ranked scores, {label: FitResult})."""
    from fitting.fit import fit_samples

    out_dir = Path(out_dir)
    setups = setups or {}
    results, scores = {}, []
    for c in cands:
        opts = candidate_options(base, c)
        sub = out_dir if c.label == c.model else out_dir / c.label
        res = fit_samples(table, opts, out_dir=sub, progress=progress, setup=setups.get(c.label))
        results[c.label] = res
        scores.append(score_fit(res, c.label, seed=base.seed))
        if on_fit is not None:
            on_fit(c, res)
    ranked = rank(scores)
    write_compare(out_dir / "compare.json", ranked, skipped)
    return ranked, results

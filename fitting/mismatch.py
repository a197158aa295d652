"""Honest intervals and predictive bands when the model does not fit the material (issue 18
item 3).

No model describes a real material exactly. Then the data have no "true" parameters; what a
fit can estimate is the **best approximation on the measured domain**: the parameters θ* that
the same fit (likelihood, discrepancy term, weights) reaches on noise-free data covering that
domain densely (:func:`fitting.fit.best_approximation` computes it). Two things go wrong under
mismatch if nothing is done, and this module mends both:

1. **The posterior is too narrow for θ*.** The likelihood treats every sample's misfit as
   independent noise of variance v_j = σ_j² + (s f̃_j)² (fitting.likelihood), one global
   fraction s. Where the misfit is structured — larger where the gradient is large, say at the
   flank of the specular lobe — the spread of the estimate over repeated measurements is not
   the inverse Fisher information H⁻¹ but the sandwich H⁻¹ J H⁻¹ (Huber 1967; White 1982,
   Econometrica 50(1)), with J the variance of the score. :func:`sandwich_adjust` estimates J
   from the residuals (HC3: each squared residual divided by (1 − h_j)², h_j its leverage —
   MacKinnon & White 1985, J. Econometrics 29(3), because in-sample residuals understate the
   misfit where a few samples steer the fit) and moves the posterior draws so their
   covariance becomes the sandwich — the curvature adjustment of Ribatet, Cooley & Davison
   (2012, Statistica Sinica 22(2)), whose frequentist risk under misspecification Müller
   (2013, Econometrica 81(5)) shows is the better one. Only widening is allowed (each
   generalised eigenvalue of sandwich vs posterior is clipped at 1): a smaller sandwich is
   either noise or a posterior already wide for a reason (a prior edge, a non-Gaussian shape)
   that the linearisation does not see.
2. **One global fraction s is right on average, wrong locally.** The band in which the
   material's true f lies is narrow where the model fits and wide where it does not.
   :func:`regional_discrepancy` gives each region of the Rusinkiewicz angles (θ_h, θ_d) its own
   fraction s_k, from the residuals of that region at the fitted parameters, with a *uniform*
   prior on s_k ∈ [0, 1] (Gelman 2006, Bayesian Analysis 1(3): a log-uniform prior on a scale
   that the data cannot resolve piles the posterior at its lower end, here 1e-4, and a band
   drawn from it is far too narrow where the misfit is near the noise). The parameters
   themselves stay fitted with the global s: estimating weights per region from the same
   samples biases the estimate by about one posterior sd at a few hundred samples per region
   (measured: kd z-mean −1.0 on roughplastic), so the regional fractions are fitted after the
   parameters — a "cut" (Liu, Bayarri & Berger 2009, Bayesian Analysis 4(1)) — and used only
   for predictions. :func:`predictive_band` combines both: parameter draws (widened) plus the
   region's model error.

What this assumes, said where it is used: the measured directions stand for the domain (they
cover it, without a few directions steering the fit alone); for a fixed grid plan the
intervals then cover the plan's own best approximation conservatively.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fitting.differences import stencil_hessian

__all__ = [
    "REGION_THETA_H",
    "REGION_THETA_D",
    "REGION_MIN_SAMPLES",
    "OTHER_REGIONS",
    "region_index",
    "exact_regions",
    "region_label",
    "sandwich_adjust",
    "apply_transform",
    "regional_discrepancy",
    "region_fractions",
    "BandSource",
    "predictive_band",
    "widening_words",
]

#: Regions of (θ_h, θ_d) (rad): θ_h bands — specular core, lobe flank, off-specular — times θ_d
#: bands — near-normal, mid, grazing (where Fresnel and shadowing matter). The same grid as
#: the residual verdict (fitting.verdicts.regions_verdict), so "region" means one thing.
REGION_THETA_H = np.radians([0.0, 10.0, 30.0, 90.0])
REGION_THETA_D = np.radians([0.0, 30.0, 60.0, 90.0])
#: Fewest samples for a region of its own: the RMS of n unit residuals is known to √(1/2n),
#: ±16 % at 20 — enough to tell a 1 % misfit from a 10 % one. Sparser regions share one s.
REGION_MIN_SAMPLES = 20
#: The label of the pooled sparse regions.
OTHER_REGIONS = "other regions"
#: Grid of s for the regional posterior: 0, then log-spaced to 1 (the prior's range), fine
#: enough (2.3 % steps) that the quantiles are not grid artefacts.
_S_GRID = np.concatenate([[0.0], np.geomspace(1e-5, 1.0, 400)])
#: Quantile levels stored per region: the band draws s_k by inverse-CDF interpolation.
_LEVELS = np.linspace(0.0, 1.0, 41)
#: Rows per block when the regional likelihood is evaluated on the s grid (bounded memory).
_BLOCK = 8192
#: Rows per block of :func:`region_index` (≈ 10 temporaries of 1.5 MB each).
_REGION_BLOCK = 65536


def region_index(wi, wo) -> np.ndarray:
    """Index 0…8 of each (ω_i, ω_o) pair's region: 3 · (θ_h band) + (θ_d band)."""
    from brdfdata.rusinkiewicz import to_half_diff

    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    out = np.empty(wi.shape[:-1], np.int64)
    flat_i, flat_o, flat = wi.reshape(-1, 3), wo.reshape(-1, 3), out.reshape(-1)
    # in blocks of rows: the half/difference angles make several (n, 3) temporaries
    for start in range(0, flat.size, _REGION_BLOCK):
        sl = slice(start, start + _REGION_BLOCK)
        th, td, _ = to_half_diff(flat_i[sl], flat_o[sl])
        ih = np.clip(np.digitize(th, REGION_THETA_H) - 1, 0, REGION_THETA_H.size - 2)
        idd = np.clip(np.digitize(td, REGION_THETA_D) - 1, 0, REGION_THETA_D.size - 2)
        flat[sl] = ih * (REGION_THETA_D.size - 1) + idd
    return out if out.ndim else out[()]  # one pair: a scalar, as numpy's own functions give


def region_label(k: int) -> str:
    """'θh 0–10°, θd 0–30°' for region k."""
    n_d = REGION_THETA_D.size - 1
    a, b = divmod(int(k), n_d)
    h0, h1 = np.degrees(REGION_THETA_H[a : a + 2])
    d0, d1 = np.degrees(REGION_THETA_D[b : b + 2])
    return f"θh {h0:.0f}–{h1:.0f}°, θd {d0:.0f}–{d1:.0f}°"


# -- the model's values and derivatives over the exact samples ---------------------------------
def _predict_exact(lik, x: np.ndarray) -> np.ndarray:
    fms = lik.predict(np.atleast_2d(x))
    return np.concatenate([fm[0][d.exact] for d, fm in zip(lik.data, fms, strict=True)])


def _model_columns(space) -> np.ndarray:
    """Indices of the model's parameters in θ (everything but the discrepancy and the shared
    errors' nuisance parameters, which the caller holds: fitting.nuisance)."""
    return np.array(
        [i for i, s in enumerate(space.specs) if s.base != "discrepancy" and s.prior_sigma is None],
        dtype=int,
    )


def _adjustable_columns(space) -> np.ndarray:
    """The model's parameters and the discrepancy: everything but the nuisance parameters."""
    return np.array([i for i, s in enumerate(space.specs) if s.prior_sigma is None], dtype=int)


def _discrepancy_of(space, draws: np.ndarray) -> float:
    """Median of the global discrepancy s over the draws (0 without the term)."""
    idx = [i for i, s in enumerate(space.specs) if s.base == "discrepancy"]
    if not idx:
        return float(space.fixed.get("discrepancy", 0.0))
    return float(np.median(space.to_natural(draws)[:, idx[0]]))


def _weights(lik, x: np.ndarray, s: float):
    """(f̂, f̃, f, v) over the exact samples at x: v = σ² + (s f̃)²."""
    f_hat = _predict_exact(lik, x)
    f = np.concatenate([d.f[d.exact] for d in lik.data])
    sig2 = np.concatenate([d.sigma2[d.exact] for d in lik.data])
    frozen = lik.discrepancy_reference
    if frozen is not None:
        ref = np.concatenate([r[d.exact] for d, r in zip(lik.data, frozen, strict=True)])
    else:
        ref = np.abs(f_hat)
    return f_hat, ref, f, sig2 + (s * ref) ** 2


def _leverage(lik, x: np.ndarray, s: float) -> np.ndarray:
    """h_j = g_jᵀ H⁻¹ g_j / v_j of every row of the likelihood (0 for censored rows), with g the
    model's gradient (central differences) and H = Σ g gᵀ/v over the exact rows; NaN where it
    cannot be computed.

    Memory: the weighted gradient is the one n × k array (filled a column at a time); a row
    that is not finite is zeroed in it, which takes it out of H exactly, and h is taken in
    blocks of rows, not through an einsum of n × k copies."""
    space = lik.space
    cols = _model_columns(space)
    _f_hat, _ref, _f, v = _weights(lik, x, s)
    inv_sd = 1.0 / np.sqrt(v)
    del _f_hat, _ref, _f, v
    lo, hi = space.bounds
    gw = np.empty((inv_sd.size, cols.size))
    for k, i in enumerate(cols):
        h = 1e-6 * max(1.0, abs(float(x[i])))
        xp, xm = x.copy(), x.copy()
        xp[i] = min(x[i] + h, hi[i])
        xm[i] = max(x[i] - h, lo[i])
        with np.errstate(all="ignore"):
            col = _predict_exact(lik, xp)
            col -= _predict_exact(lik, xm)
            col *= inv_sd / (xp[i] - xm[i])
        gw[:, k] = col
    ok = np.all(np.isfinite(gw), axis=1)
    gw[~ok] = 0.0
    lev = np.full(inv_sd.size, np.nan)
    with np.errstate(all="ignore"):
        h_pinv = np.linalg.pinv(gw.T @ gw)
        for start in range(0, gw.shape[0], _BLOCK):
            b = gw[start : start + _BLOCK]
            lev[start : start + _BLOCK] = np.einsum("ij,jk,ik->i", b, h_pinv, b)
    lev[~ok] = np.nan
    exact = np.concatenate([d.exact for d in lik.data])
    out = np.zeros(exact.size)
    out[exact] = lev
    return out


def _scores(lik, x: np.ndarray, cols: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Per-row score ∂ ln L_j/∂x over ``cols`` (n, d) by central differences of the pointwise
    log-likelihood (censored rows included, as the fit uses them). One parameter's pair of
    points at a time: the (2, n) pointwise values, not (2d, n), are held at once."""
    out = np.empty((lik.n, cols.size))
    for a in range(cols.size):
        pair = np.repeat(x[None, :], 2, axis=0)
        pair[0, cols[a]] += step[a]
        pair[1, cols[a]] -= step[a]
        ll = lik.pointwise_log_likelihood(pair)
        out[:, a] = (ll[0] - ll[1]) / (2 * step[a])
    return out


def _hc3_scores(lik, x, cols, step, sd, lev) -> tuple[np.ndarray, np.ndarray]:
    """(ψ, ok): the per-row scores over ``cols`` in units of ``sd``, each divided by 1 − h_j
    (HC3: the row's score as if it had been left out of the fit, MacKinnon & White 1985), and
    the rows where that is finite. Rows not ok are zero in ψ (so Σ ψ ψᵀ is over the ok rows)
    rather than dropped: the n × d array is scaled in place, never copied."""
    psi = _scores(lik, x, cols, step)
    psi *= sd
    ok = np.all(np.isfinite(psi), axis=1) & np.isfinite(lev)
    psi /= (1.0 - np.clip(np.where(ok, lev, 0.0), 0.0, 0.99))[:, None]
    psi[~ok] = 0.0
    return psi, ok


def _sandwich_map(lik, draws: np.ndarray, cols: np.ndarray, lev: np.ndarray):
    """(linear map A over ``cols``, clipped and raw variance ratios) of the adjustment, or None
    when the observed information is not positive definite (a parameter at a prior bound or not
    informed)."""
    x = np.median(draws, axis=0)
    sd = draws[:, cols].std(axis=0)
    if not np.all(sd > 0):
        return None
    # Steps a twentieth of the posterior's own sd: the log-likelihood is near-quadratic there,
    # and its round-off (≈ 1e-16·|ln L|) divided by step² stays below 1e-8 of the curvature.
    step = 0.05 * sd
    info_obs = -stencil_hessian(lik.log_likelihood, x, step, cols) * np.outer(
        sd, sd
    )  # in units of sd
    psi, _ok = _hc3_scores(lik, x, cols, step, sd, lev)
    try:
        chol = np.linalg.cholesky(np.linalg.inv(info_obs))  # model-based covariance = L Lᵀ
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(chol)):
        return None
    j = psi.T @ psi
    lam, u = np.linalg.eigh(chol.T @ j @ chol)  # eigenvalues of L⁻¹ (I⁻¹ J I⁻¹) L⁻ᵀ
    lam_c = np.maximum(lam, 1.0)
    a_z = chol @ u @ np.diag(np.sqrt(lam_c)) @ u.T @ np.linalg.inv(chol)
    return a_z * sd[:, None] / sd[None, :], lam_c, lam


def _cluster_map(lik, draws: np.ndarray, cols: np.ndarray, lev: np.ndarray):
    """The linear map over the model's ``cols`` that widens ``draws`` to the cluster-robust
    sandwich where that is wider, or None (no clusters, too few, or a singular information).

    Rows of one pose share that pose's angle errors — backlash, arm sag, a drift step — which
    no per-row score sees: summed per pose before the outer product, the scores give the
    cluster-robust J = G/(G − 1) Σ_g s_g s_gᵀ of G poses (Liang & Zeger 1986), consistent
    whether or not a pose's rows are correlated. Only the model's parameters: the discrepancy
    s is a variance, whose information vanishes as s → 0, so 16 poses' J would blow its
    interval up to the prior's box; it keeps the rows' sandwich. Needs more than 2 poses per
    parameter (else J is singular or noise)."""
    clusters = lik.clusters
    if clusters is None or cols.size == 0:
        return None
    x = np.median(draws, axis=0)
    sd = draws[:, cols].std(axis=0)
    if not np.all(sd > 0):
        return None
    step = 0.05 * sd
    info_obs = -stencil_hessian(lik.log_likelihood, x, step, cols) * np.outer(sd, sd)
    psi, ok = _hc3_scores(lik, x, cols, step, sd, lev)
    groups, inverse = np.unique(clusters[ok], return_inverse=True)
    if groups.size <= 2 * cols.size:
        return None
    per = np.stack(
        [np.bincount(inverse, weights=psi[ok, a], minlength=groups.size) for a in range(cols.size)],
        axis=1,
    )
    j = per.T @ per * groups.size / (groups.size - 1)
    try:
        i_inv = np.linalg.inv(info_obs)
        chol = np.linalg.cholesky(np.cov(draws[:, cols] / sd, rowvar=False))
    except np.linalg.LinAlgError:
        return None
    target = i_inv @ j @ i_inv
    c_inv = np.linalg.inv(chol)
    lam, u = np.linalg.eigh(c_inv @ target @ c_inv.T)
    if not np.all(np.isfinite(lam)):
        return None
    a_z = chol @ u @ np.diag(np.sqrt(np.maximum(lam, 1.0))) @ u.T @ c_inv
    return a_z * sd[:, None] / sd[None, :]


def sandwich_adjust(lik, draws: np.ndarray) -> tuple[np.ndarray, dict]:
    """(draws moved so their covariance is the HC3 sandwich where that is wider, info).

    ``draws`` (S, D) in the sampled space (MCMC or Laplace), the model's parameters and the
    discrepancy s together: under mismatch the weights σ² + (s f̃)² move the estimate, so s's
    own sampling spread widens the parameters too. At the draws' median x̂: the observed
    information I = −∇² ln L (central second differences), the per-row scores ψ_j = ∇ ln L_j
    (censored rows included), each divided by 1 − h_j (HC3, h_j the row's leverage in the
    model's weighted Jacobian), J = Σ ψ ψᵀ, and the sandwich C_s = I⁻¹ J I⁻¹ (module
    docstring). With I⁻¹ = L Lᵀ, the eigenvalues λ of L⁻¹ C_s L⁻ᵀ (variance ratios sandwich /
    model-based along its eigenvectors U) are clipped at 1 and the draws move as
    x' = c + A (x − c), A = L U diag(√λ) Uᵀ L⁻¹, c their mean: Ribatet et al.'s curvature
    adjustment, a linear map, so the posterior's shape is kept and only scaled by the
    misspecification ratio. When s sits at its prior's lower bound (no model error) its
    information is not positive definite and only the model's parameters are adjusted. Draws
    are then clipped to the prior box.

    ``info``: ``applied``, ``method``, ``variance_ratio`` (the clipped λ, largest first),
    ``raw_variance_ratio`` (before clipping), ``sd_factor`` {name: sd after / sd before},
    ``transform`` {names, center, matrix} (to apply the same map to the stored chain,
    :func:`apply_transform`), or ``reason`` when not applied.
    """
    space = lik.space
    draws = np.asarray(draws, dtype=np.float64)
    model_cols = _model_columns(space)
    info: dict = {"applied": False, "method": "HC3 sandwich (Ribatet et al. 2012), widening only"}
    if model_cols.size == 0 or draws.shape[0] < 2 * space.ndim + 2:
        info["reason"] = "no model parameter to adjust"
        return draws, info
    n_exact = lik.n_exact
    if n_exact <= space.ndim + 1:
        info["reason"] = f"{n_exact} exact samples for {space.ndim} parameters"
        return draws, info
    x = np.median(draws, axis=0)
    with np.errstate(all="ignore"):
        lev = _leverage(lik, x, _discrepancy_of(space, draws))
        found = None
        for cols in (_adjustable_columns(space), model_cols):
            found = _sandwich_map(lik, draws, cols, lev)
            if found is not None:
                break
    if found is None:
        info["reason"] = "the information matrix is singular (a parameter is not identified)"
        return draws, info
    a, lam_c, lam = found
    lo, hi = space.bounds
    center = draws[:, cols].mean(axis=0)
    moved = apply_transform(draws, cols, center, a, (lo, hi))
    with np.errstate(all="ignore"):
        by_pose = _cluster_map(lik, moved, model_cols, lev)
    if by_pose is not None:  # a second widening, for what the poses share (see _cluster_map)
        a2 = np.eye(cols.size)
        pos = np.searchsorted(cols, model_cols)
        a2[np.ix_(pos, pos)] = by_pose
        a = a2 @ a
        moved = apply_transform(draws, cols, center, a, (lo, hi))
        info["method"] += "; then cluster-robust by pose (Liang & Zeger 1986)"
    sd0 = draws[:, cols].std(axis=0)
    sd1 = moved[:, cols].std(axis=0)
    names = [space.specs[i].name for i in cols]
    info.update(
        applied=True,
        variance_ratio=sorted((float(v_) for v_ in lam_c), reverse=True),
        raw_variance_ratio=sorted((float(v_) for v_ in lam), reverse=True),
        sd_factor={
            nm: float(b / a_) if a_ > 0 else 1.0 for nm, a_, b in zip(names, sd0, sd1, strict=True)
        },
        transform={"names": names, "center": center.tolist(), "matrix": a.tolist()},
    )
    return moved, info


def apply_transform(draws, cols, center, matrix, bounds) -> np.ndarray:
    """x' = c + A (x − c) on the ``cols`` of ``draws`` (S, D), clipped to ``bounds``."""
    out = np.array(draws, dtype=np.float64, copy=True)
    c = np.asarray(center, dtype=np.float64)
    a = np.asarray(matrix, dtype=np.float64)
    out[:, cols] = c + (out[:, cols] - c) @ a.T
    lo, hi = bounds
    return np.clip(out, lo, hi)


# -- regional model error -------------------------------------------------------------------------
def _grouping(regions: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """(label, indices of the regions it covers) for every region with enough samples, then
    the pooled rest."""
    counts = np.bincount(regions, minlength=9)
    own = [k for k in range(9) if counts[k] >= REGION_MIN_SAMPLES]
    rest = [k for k in range(9) if 0 < counts[k] < REGION_MIN_SAMPLES]
    groups = [(region_label(k), np.array([k])) for k in own]
    if rest:
        groups.append((OTHER_REGIONS, np.array(rest)))
    return groups


def exact_regions(lik) -> np.ndarray:
    """:func:`region_index` of every exact row of ``lik``, channels concatenated in
    :func:`_weights`'s order (the order of ``lik.residuals``), without concatenating the rows'
    directions first."""
    out = [region_index(d.wi[d.exact], d.wo[d.exact]) for d in lik.data]
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def regional_discrepancy(lik, x: np.ndarray) -> list[dict]:
    """The model error s_k (fraction of f̃) of each (θ_h, θ_d) region at the fitted θ = x:
    the posterior on a grid with a uniform prior on [0, 1] of
    Π_j N(r_j; 0, σ_j² + s_k² f̃_j²) over the region's exact samples (module docstring).

    One dict per region: ``label``, ``regions`` (indices 0…8), ``n``, ``median``, ``p2.5``,
    ``p16``, ``p84``, ``p97.5`` and ``quantiles`` (s at the levels 0, 2.5, … 100 %).
    """
    f_hat, ref, f, v0 = _weights(lik, x, 0.0)  # v0 = σ²
    reg = exact_regions(lik)
    r2 = (f - f_hat) ** 2
    ok = np.isfinite(r2) & np.isfinite(ref)
    prior = np.log(np.gradient(_S_GRID))  # uniform in s on the non-uniform grid
    out = []
    for label, members in _grouping(reg[ok]):
        rows = np.flatnonzero(ok & np.isin(reg, members))
        ll = np.zeros(_S_GRID.size)
        t2 = _S_GRID[:, None] ** 2
        for start in range(0, rows.size, _BLOCK):
            j = rows[start : start + _BLOCK]
            v = v0[j][None, :] + t2 * (ref[j] ** 2)[None, :]
            ll += -0.5 * np.sum(r2[j][None, :] / v + np.log(v), axis=1)
        lp = ll + prior
        p = np.exp(lp - lp.max())
        cdf = np.cumsum(p)
        cdf /= cdf[-1]
        q = np.interp(_LEVELS, cdf, _S_GRID)
        q[0] = 0.0 if cdf[0] > 0 else q[0]
        pick = {lv: float(np.interp(lv, cdf, _S_GRID)) for lv in (0.025, 0.16, 0.5, 0.84, 0.975)}
        out.append(
            {
                "label": label,
                "regions": [int(k) for k in members],
                "n": int(rows.size),
                "median": pick[0.5],
                "p2.5": pick[0.025],
                "p16": pick[0.16],
                "p84": pick[0.84],
                "p97.5": pick[0.975],
                "quantiles": [float(v) for v in q],
            }
        )
    return out


def _region_draws(regions_info: Sequence[Mapping], n: int, rng) -> tuple[dict, np.ndarray]:
    """({region index 0…8: column}, s draws (n, groups)) by inverse-CDF sampling of the
    stored quantiles; regions no group covers map to the pooled group, else to the widest."""
    col = {}
    draws = np.empty((n, len(regions_info)))
    for c, info in enumerate(regions_info):
        u = rng.uniform(0.0, 1.0, size=n)
        draws[:, c] = np.interp(u, _LEVELS, np.asarray(info["quantiles"], dtype=np.float64))
        for k in info["regions"]:
            col[int(k)] = c
    fallback = next(
        (c for c, info in enumerate(regions_info) if info["label"] == OTHER_REGIONS),
        int(np.argmax([info["median"] for info in regions_info])) if regions_info else 0,
    )
    for k in range(9):
        col.setdefault(k, fallback)
    return col, draws


def region_fractions(inside: np.ndarray, wi, wo) -> dict[int, tuple[int, float]]:
    """{region: (count, fraction of ``inside``)} — how often a band held the truth, per
    region."""
    reg = region_index(wi, wo)
    inside = np.asarray(inside, dtype=bool)
    return {
        int(k): (int(np.sum(reg == k)), float(np.mean(inside[reg == k]))) for k in np.unique(reg)
    }


@dataclass(frozen=True)
class BandSource:
    """What a predictive band is drawn from: the ``model``, its parameter ``space``, parameter
    ``draws`` (sampled space; the widened ones) and the model error per region (``regions``
    from :func:`regional_discrepancy`; None: no model-error term)."""

    model: Any
    space: Any
    draws: np.ndarray
    regions: Sequence[Mapping] | None = None

    @classmethod
    def of_fit(cls, fit) -> BandSource:
        """The band source of a fit made in this process (fitting.fit.fit_samples)."""
        extras = fit.extras
        regions = fit.diagnostics.get("mismatch", {}).get("regions")
        return cls(extras["likelihood"].model, extras["space"], extras["draws"], regions)


def predictive_band(
    source: BandSource,
    wi,
    wo,
    channel: str,
    *,
    level: float = 0.95,
    n_draws: int = 400,
    rng: np.random.Generator | int | None = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of the ``level`` band of the material's f at (wi, wo) for ``channel``:
    f̂(θ) + s_k f̃ ε, θ from the source's draws, s_k the model error of the direction's region,
    f̃ the model at the draws' median, ε ~ N(0, 1). A band for the true f, not for a new
    measurement: the measurement noise is not added.
    """
    model, space = source.model, source.space
    rng = np.random.default_rng(rng)
    draws = np.asarray(source.draws, dtype=np.float64)
    pick = draws[rng.choice(draws.shape[0], size=min(n_draws, draws.shape[0]), replace=False)]
    nat = space.natural_dict(pick)
    wi = np.atleast_2d(np.asarray(wi, dtype=np.float64))
    wo = np.atleast_2d(np.asarray(wo, dtype=np.float64))
    with np.errstate(all="ignore"):
        fm = np.broadcast_to(
            model.evaluate(space.channel_params(nat, channel), wi, wo), (pick.shape[0], wi.shape[0])
        )
        center = space.natural_dict(np.median(draws, axis=0)[None, :])
        ref = np.abs(np.asarray(model.evaluate(space.channel_params(center, channel), wi, wo)))
    ref = np.broadcast_to(ref, (1, wi.shape[0]))[0]
    pred = np.array(fm, dtype=np.float64)
    if source.regions:
        col, s_draws = _region_draws(source.regions, pick.shape[0], rng)
        which = np.array([col[int(k)] for k in region_index(wi, wo)])
        pred += s_draws[:, which] * ref[None, :] * rng.standard_normal(pred.shape)
    tail = 100.0 * (1.0 - level) / 2.0
    lo, hi = np.percentile(pred, [tail, 100.0 - tail], axis=0)
    return lo, hi


def widening_words(info: Mapping) -> str:
    """One line: how much the intervals were widened for the model's mismatch, or why not."""
    if not info or not info.get("applied"):
        return f"intervals not widened for mismatch ({info.get('reason', 'no discrepancy term')})"
    factors = info.get("sd_factor", {})
    if not factors:
        return "intervals not widened for mismatch"
    name = max(factors, key=lambda k: factors[k])
    big = factors[name]
    if not math.isfinite(big) or big < 1.05:
        return "intervals not widened: the residuals are consistent with the posterior's width"
    return (
        f"intervals widened for the model's mismatch (sandwich): up to ×{big:.2g} ({name}); "
        "they cover the best approximation on the measured directions"
    )

"""gonio's sampler against NumPyro NUTS on the identical posterior (issue 23, item 1, "sampler").

One run, two posteriors, ESS per second of each sampler and the gonio/NUTS ratio:

* **smooth** — bench_mcmc.py's problem exactly: the seed Torrance-Sparrow (Beckmann, V-cavity,
  dielectric) + Lambert, m = 0.2, 10⁴ rows × 3 channels from ``bench_mcmc.synthetic_table``,
  ``ParameterSpace.build(model, "RGB", discrepancy=True)``: 9 parameters (kd_R/G/B, ln ks_R/G/B,
  ln m, ior, ln s).
* **sharp** — the same model at a near-mirror roughness m = 0.02 (:func:`sharp_table`). Uniform
  directions would almost never land in a lobe 2m ≈ 2.3° wide, so the table is built the way
  tests/fitting/models/test_models_vs_mitsuba.py's ``direction_pairs`` covers a narrow lobe: per
  channel 40 % of the rows are mirror pairs about a half vector whose slope is drawn from the
  Beckmann distribution of width m (tan θ_h = m √(−ln u): the lobe's core), 20 % with width 2m (its
  shoulders, where D falls to e⁻⁴…e⁻¹⁶ of the peak and the width is best measured) and 40 % are
  bench_mcmc's wide pairs (the diffuse part and the empty far field). Light at φ = 0, θ_i, θ_o ∈
  [0.05, 1.3] rad as in synthetic_table (lobe pairs outside are redrawn), noise σ = 3 % f + 10⁻³ as
  there.

The posterior (fitting.likelihood, fitting.priors): θ in gonio's sampled coordinates (log of the log
parameters), flat on the prior box, −∞ outside; ln L = Σ −½[(f − f̂)²/v + ln 2πv] with v = σ² + (s
f̃)², f̃ = |f̂(θ_LSQ)| frozen at the least-squares optimum (``Likelihood.frozen_at``). It is
written again in JAX float64 below (geometry, Beckmann D, V-cavity G, dielectric Fresnel, all as
fitting.models.microfacet_kernels computes them) and checked against ``Likelihood.log_prob`` at
several points to 1e-9 relative *before* anything is sampled, and its gradient against central
differences of ``log_prob``.

gonio's side is what ``gonio fit`` does (fitting.fit.fit_samples): multi-start least squares,
the discrepancy reference frozen there, ln s set to its best grid value, then ``run_mcmc`` with
the default moves (DE) from the Laplace ball until every ESS ≥ the target (default 1000).
Timed end to end (LSQ + MCMC) and sampling only.

NUTS' side: ``numpyro.infer.NUTS(potential_fn=U)``, U(z) = −ln p(θ(z)) − ln|dθ/dz| with z ∈ R⁹
unconstrained: the *same* posterior over θ (its push-forward), so draws are compared in θ. Why not
U = −ln p(θ) on θ itself: θ lives in a box and the discrepancy's posterior is flat in ln s right
down to its prior bound (these data have no model error), so trajectories would keep running into
a −∞ wall, which NUTS can only reject as divergences. Coordinates (``--coords``): "natural"
(default) is what NumPyro does itself for a model written with Uniform / LogUniform priors — z is
the logit of each *natural* value's place in its box (kd, ks, m, ior, s) — and "theta" the logit
of gonio's θ in its box. Both are exact; natural mixed better in a development run (smooth, LSQ
start, dense: min ESS 107 against 84 from 500 draws) and is what a NumPyro user gets. Set-ups
tried, as a competent user would: NumPyro's default init_to_uniform (z ~ U(−2, 2), "random") or
the least-squares optimum (gonio's own Laplace ball, "lsq"), × diagonal or dense mass matrix;
default step-size adaptation (target acceptance 0.8) and tree depth (10). Chains: 2 on the 2
cores, run as the faster of ``chain_method="parallel"`` (one chain per XLA device) and
"vectorized", or 1 chain if neither beats it — chosen by measured gradient throughput on the spot
(:func:`pick_chain_method`; one value-and-gradient does not use the second core). The best set-up
(highest end-to-end ESS/s) that agrees with gonio (below) is the comparison; every set-up is
listed.

Checks before any time is compared: each sampler's chains must agree among themselves (split
R̂ < 1.05, emcee's walkers as the chains) and have min ESS ≥ 50; then for each natural parameter
the posterior means must agree within 4·√(MCSE₁² + MCSE₂²), MCSE = sd/√ESS, and the sds within 4
standard errors of an sd (from the ESS of the series (x − x̄)², so no Gaussian assumption). A
set-up that fails is printed loudly and gets no ratio; if none passes, the posterior gets none.

ESS: one estimator for both samplers, NumPyro's (Geyer's initial monotone sequence on the
autocovariance averaged over chains, Stan's between- and within-chain variance), with emcee's
walkers as the chains. That is what emcee's own τ does too (the walkers' autocorrelation
functions averaged, Foreman-Mackey 2017); the between-walker variance term only makes it more
conservative if walkers have not mixed. What it cannot see is correlation *between* walkers at
lags > 0 (a DE move makes a walker's next position depend on two others' present ones), which
could make it optimistic for an ensemble. Checked in development with 12 independent gonio runs
per posterior (same LSQ start, other seeds): the spread of their posterior means over the MCSE
sd/√ESS from this estimator was 0.97 (sharp) and 1.12 (smooth) across the 9 parameters (±0.07),
i.e. its ESS is honest to within ~25 % — as honest as emcee's τ (1.05, 1.19) and the ESS of the
ensemble-mean trace, which carries every cross-walker correlation (1.03, 1.18). emcee's
Sokal-window τ applied to both samplers is printed as a second estimator.
ESS/s = min ESS over the 9 parameters (θ coordinates) / wall seconds; also over the 8 BRDF
parameters alone, since the discrepancy is by far NUTS' slowest.

Timings, three columns each: end to end (gonio: LSQ + MCMC; NUTS: JAX compile + warmup + draws,
+ the LSQ for a set-up started there), MCMC only (gonio: run_mcmc with its 3τ burn-in; NUTS:
warmup + draws, no compile) and draws only (gonio: the kept post-burn steps' share of run_mcmc;
NUTS: the post-warmup draws); and the seconds to the target ESS, the fixed part plus the draws'
time scaled to the target (ESS grows linearly with draws). NUTS draws 1000 per chain, fewer (≥
100) where the warmup's last trees predict more than ``--nuts-budget-s`` (45 s) of draws: slow
set-ups are measured at the same rate in less time, and their time to the target extrapolated.
Threads: both get the same ``--threads`` (2): the process' CPU affinity is cut to that many CPUs
(XLA sizes its pool from it), numba.set_num_threads, and as many XLA host devices for parallel
chains. Speed is printed, never asserted.

Run: ``.venv/bin/python benchmarks/bench_peers_sampler.py [--posteriors smooth,sharp]`` (about
15 minutes on 2 cores); ``--quick`` is a smoke run of a minute or two: 3000 rows per channel,
gonio's target ESS 200, only the lsq/dense NUTS set-up, warmup 300 + 500 draws. (At a target of
200, emcee stops after its first 100-step chunk, a few τ, and the R̂ check then refuses the
comparison; ``--quick --target-ess 1000`` runs the whole path in about two minutes.) Needs
``pip install -e '.[bench]'``; without jax/numpyro it says so and exits 0.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import time
from dataclasses import dataclass

import numpy as np
from bench_mcmc import TRUTH, synthetic_table

from brdfdata.directions import reflect, spherical_to_vector, vector_to_spherical
from brdfdata.samples import SampleTable
from fitting import models
from fitting.fit import _best_discrepancy, _precision_probes, _walkers_covariance
from fitting.likelihood import Likelihood
from fitting.lsq import fit_least_squares
from fitting.mcmc import McmcOptions, initial_ball, run_mcmc
from fitting.priors import ParameterSpace

__all__ = ["main", "sharp_table"]

SHARP_M = 0.02
THETA_RANGE_RAD = (0.05, 1.3)  # synthetic_table's incidence and exitance range
#: NUTS set-ups of the first round: (name, start, dense mass matrix).
SETUPS = (
    ("random/diag", "random", False),
    ("random/dense", "random", True),
    ("lsq/diag", "lsq", False),
    ("lsq/dense", "lsq", True),
)
AGREE_Z = 4.0  # agreement bound, in standard errors
RHAT_MAX = 1.05  # a sampler's chains must agree among themselves before it is compared
MIN_ESS_TO_CHECK = 50  # below it the MCSEs of the check are themselves too uncertain
IDENTITY_RTOL = 1e-9


# -- the sharp table ------------------------------------------------------------------------------
def _lobe_pairs(count: int, width: float, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """(θ_i, θ_o, φ_o) of `count` mirror pairs about half vectors whose slope is Beckmann
    distributed with RMS `width` (tan θ_h = width·√(−ln u)); the light at φ = 0."""
    lo, hi = THETA_RANGE_RAD
    out = [np.empty(0)] * 3
    while out[0].size < count:
        k = 2 * (count - out[0].size) + 16
        ti = rng.uniform(lo, hi, k)
        tan_h = width * np.sqrt(-np.log(rng.uniform(1e-300, 1.0, k)))
        h = spherical_to_vector(np.arctan(tan_h), rng.uniform(0, 2 * np.pi, k))
        wo = reflect(spherical_to_vector(ti, np.zeros(k)), h)
        to, po = vector_to_spherical(wo)
        keep = (to >= lo) & (to <= hi)  # a lobe pair the rig's range cannot take is redrawn
        out = [np.concatenate([a, b[keep]]) for a, b in zip(out, (ti, to, po), strict=True)]
    return tuple(a[:count] for a in out)


def sharp_table(
    n: int, rng: np.random.Generator, m: float = SHARP_M, rel_noise: float = 0.03
) -> SampleTable:
    """`n` rows per channel of the seed Torrance-Sparrow at roughness `m` (TRUTH otherwise):
    40 % in the lobe's core, 20 % on its shoulders, 40 % wide (module docstring)."""
    model = models.get("torrance-sparrow")
    n_core, n_shoulder = 4 * n // 10, 2 * n // 10
    n_wide = n - n_core - n_shoulder
    lo, hi = THETA_RANGE_RAD
    parts = []
    for c, kd, ks in zip("RGB", TRUTH["kd"], TRUTH["ks"], strict=True):
        core = _lobe_pairs(n_core, m, rng)
        shoulder = _lobe_pairs(n_shoulder, 2 * m, rng)
        wide_po = np.where(
            np.arange(n_wide) % 2 == 0,
            np.pi + rng.uniform(-0.3, 0.3, n_wide),
            rng.uniform(0, 2 * np.pi, n_wide),
        )
        wide = (rng.uniform(lo, hi, n_wide), rng.uniform(lo, hi, n_wide), wide_po)
        ti, to, po = (np.concatenate(cols) for cols in zip(core, shoulder, wide, strict=True))
        wi, wo = spherical_to_vector(ti, np.zeros(n)), spherical_to_vector(to, po)
        f = model.evaluate({"kd": kd, "ks": ks, "m": m, "ior": TRUTH["ior"]}, wi, wo)
        sig = rel_noise * f + 1e-3
        parts.append(
            (ti, np.zeros(n), to, po, np.full(n, c), f + sig * rng.standard_normal(n), sig)
        )
    cols = [np.concatenate([p[i] for p in parts]) for i in range(7)]
    return SampleTable(*cols, np.zeros(cols[0].size, np.int32))


# -- gonio's side ---------------------------------------------------------------------------------
@dataclass
class GonioRun:
    lik: Likelihood
    x_lsq: np.ndarray  # the least-squares optimum, where f̃ is frozen
    x_start: np.ndarray  # the MCMC's start (x_lsq with ln s at its best grid value)
    cov: np.ndarray | None  # the walkers' starting covariance (sampled space)
    lsq_s: float
    mcmc_s: float
    draws_s: float  # the kept (post-burn) steps' share of mcmc_s
    theta: np.ndarray  # (walkers, kept steps, D): walkers as chains
    res: object  # fitting.mcmc.McmcResult


def run_gonio(table: SampleTable, target_ess: float, walkers: int, seed: int) -> GonioRun:
    """What ``gonio fit`` does (fitting.fit.fit_samples), timed: LSQ, the discrepancy reference
    and start, then emcee with the default moves until every ESS ≥ `target_ess`."""
    model = models.get("torrance-sparrow")
    space = ParameterSpace.build(model, ["R", "G", "B"], discrepancy=True)
    lik = Likelihood(model, table, space)
    # numba's kernels are compiled once per machine (cache=True); load them before the clock
    for precision in ("float32", "float64"):
        lik.precision = precision
        lik.log_prob(np.tile(np.mean(space.bounds, axis=0), (2, 1)))
    t0 = time.perf_counter()
    lsq = fit_least_squares(lik, seed=seed)
    lik = lik.frozen_at(lsq.x)
    x_start = _best_discrepancy(lik, lsq.x)
    cov = None if lsq.cov is None else _walkers_covariance(lsq.cov, space.specs, x_start, None)
    # the model's precision for the sampling only, as fit_samples chooses it (fitting.likelihood)
    with lik.sampling_precision(_precision_probes(lik, lsq, x_start, seed)) as (precision, diff):
        lsq_s = time.perf_counter() - t0
        print(f"  gonio samples with the model in {precision} (ln L rounding {diff:.1e})")
        res = run_mcmc(
            lik.log_prob,
            x_start,
            space.bounds,
            McmcOptions(walkers=walkers, max_steps=100_000, target_ess=target_ess),
            rng=seed,
            scale=cov,
        )
    kept = res.chain.shape[0]
    return GonioRun(
        lik,
        lsq.x,
        x_start,
        cov,
        lsq_s,
        res.wall_time_s,
        res.wall_time_s * kept / res.iterations,
        np.ascontiguousarray(np.swapaxes(res.chain, 0, 1)),
        res,
    )


# -- the posterior in JAX -------------------------------------------------------------------------
def _geometry(wi: np.ndarray, wo: np.ndarray) -> dict[str, np.ndarray]:
    """Per-pair tan²θ_h, ω·h and the V-cavity G/(4 cos θ_i cos θ_o), as
    fitting.models.microfacet_kernels' geometry pass: θ-independent, so computed once (a JAX user
    would hoist it too)."""
    ci, co = wi[:, 2], wo[:, 2]
    valid = (ci > 0) & (co > 0)
    ci_s, co_s = np.where(valid, ci, 1.0), np.where(valid, co, 1.0)
    sx, sy, sz = wi[:, 0] + wo[:, 0], wi[:, 1] + wo[:, 1], ci_s + co_s
    rho2 = sx * sx + sy * sy
    norm = np.sqrt(rho2 + sz * sz)
    # ω_i·h and ω_o·h averaged, as the kernel does (keeps f exactly reciprocal)
    vh = 0.5 * (
        (wi[:, 0] * sx + wi[:, 1] * sy + ci_s * sz) + (wo[:, 0] * sx + wo[:, 1] * sy + co_s * sz)
    )
    vh = np.clip(vh / norm, 0.0, 1.0)
    ch = sz / norm
    with np.errstate(divide="ignore"):
        gv = np.minimum(
            0.25 / (ci_s * co_s), np.minimum(0.5 * ch / (vh * ci_s), 0.5 * ch / (vh * co_s))
        )
    return {"t2": rho2 / (sz * sz), "vh": vh, "gv": np.where(valid, gv, 0.0), "valid": valid}


def jax_posterior(lik: Likelihood, x_ref: np.ndarray):
    """(ln p(θ), coordinates) in JAX float64 for `lik`'s posterior with the discrepancy
    reference frozen at `x_ref`; the seed Torrance-Sparrow (Beckmann, V-cavity, dielectric).
    ``coordinates(kind)`` gives NUTS' potential in unconstrained coordinates."""
    import jax
    import jax.numpy as jnp

    space, model = lik.space, lik.model
    if model.name != "torrance-sparrow" or not model.flags.get("seed_form"):
        raise ValueError("the JAX posterior is written for the seed Torrance-Sparrow only")
    if lik.kind != "gaussian" or any(d.kind.any() for d in lik.data) or space.energy_prior:
        raise ValueError("the JAX posterior covers the Gaussian likelihood without censoring")
    if any(s.prior_sigma is not None for s in space.specs) or space.fixed:
        raise ValueError("the JAX posterior covers the plain box prior without fixed values")
    names = space.names
    lo, hi = (np.asarray(b, dtype=np.float64) for b in space.bounds)
    log_idx = np.flatnonzero(space.is_log)
    s_idx = names.index("discrepancy")
    # f̃ by Likelihood.frozen_at's rule, from gonio's prediction at x_ref (it is data)
    refs = [
        np.where(np.isfinite(fm[0]), np.abs(fm[0]), np.abs(d.f))
        for d, fm in zip(lik.data, lik.predict(np.atleast_2d(x_ref)), strict=True)
    ]
    channels = []
    for d, ref in zip(lik.data, refs, strict=True):
        geo = _geometry(d.wi, d.wo)
        idx = {
            base: names.index(base if base in space.shared else f"{base}_{d.channel}")
            for base in ("kd", "ks", "m", "ior")
        }
        channels.append(
            {
                "idx": idx,
                **{k: jnp.asarray(v) for k, v in geo.items()},
                "f": jnp.asarray(d.f),
                "sig2": jnp.asarray(d.sigma**2),
                "ref2": jnp.asarray(ref**2),
            }
        )
    ln_2pi = math.log(2 * math.pi)

    def fresnel(c, ior):
        # fitting.models.microfacet_kernels.stage_fresnel: R_s, R_p with one division; TIR and 0/0
        # give 1
        eta2 = ior * ior
        u2 = (eta2 - 1.0) + c * c
        ok = u2 > 0.0
        u = jnp.sqrt(jnp.where(ok, u2, 1.0))  # the double where keeps the gradient finite
        b, bp = c + u, eta2 * c + u
        a, ap = (c - u) * bp, (eta2 * c - u) * b
        den = b * b * bp * bp
        ok = ok & (den > 0.0)
        return jnp.where(ok, 0.5 * (a * a + ap * ap) / jnp.where(ok, den, 1.0), 1.0)

    def log_likelihood(theta):
        nat = theta.at[log_idx].set(jnp.exp(theta[log_idx]))
        s2 = nat[s_idx] ** 2
        total = 0.0
        for ch in channels:
            i = ch["idx"]
            kd, ks, m, ior = nat[i["kd"]], nat[i["ks"]], nat[i["m"]], nat[i["ior"]]
            t2 = ch["t2"]
            # π-normalised Beckmann D = exp(−tan²θ_h/m²)(1 + tan²θ_h)²/(π m²); exp underflows
            # to 0 far off the lobe, as in the kernel
            d = jnp.exp(-t2 / (m * m)) * (1.0 + t2) ** 2 / (jnp.pi * m * m)
            fm = kd / jnp.pi + ks * (d * ch["gv"] * fresnel(ch["vh"], ior))
            fm = jnp.where(ch["valid"], fm, 0.0)
            v = ch["sig2"] + s2 * ch["ref2"]
            r = ch["f"] - fm
            total = total - 0.5 * jnp.sum(r * r / v + jnp.log(v) + ln_2pi)
        return jnp.where(jnp.isfinite(total), total, -jnp.inf)

    def log_post(theta):
        inside = jnp.all((theta >= lo) & (theta <= hi))
        return jnp.where(inside, log_likelihood(jnp.clip(theta, lo, hi)), -jnp.inf)

    is_log = np.asarray(space.is_log)
    # The natural values' box: NumPyro's own unconstrained space for Uniform / LogUniform priors.
    nat_lo, nat_hi = np.where(is_log, np.exp(lo), lo), np.where(is_log, np.exp(hi), hi)

    def coordinates(kind: str):
        """(U(z), θ(z), z(θ)) for z = logit of the position in gonio's θ box ("theta") or in
        the natural values' box ("natural"); both carry ln|dθ/dz|, so the posterior over θ is
        the same."""
        a, b = (lo, hi) if kind == "theta" else (nat_lo, nat_hi)
        width = b - a

        def theta_of(z):
            v = a + width * jax.nn.sigmoid(z)
            return v if kind == "theta" else jnp.where(is_log, jnp.log(v), v)

        def potential(z):
            # ln|dv/dz| = ln(b − a) + ln σ(z) + ln σ(−z); natural: ln|dθ/dv| = −ln v for log ones
            log_jac = jnp.sum(jnp.log(width) - jax.nn.softplus(-z) - jax.nn.softplus(z))
            theta = theta_of(z)
            if kind == "natural":
                log_jac = log_jac - jnp.sum(jnp.where(is_log, theta, 0.0))
            return -(log_likelihood(theta) + log_jac)

        def z_of(theta):
            theta = np.asarray(theta, dtype=np.float64)
            v = theta if kind == "theta" else np.where(is_log, np.exp(theta), theta)
            p = np.clip((v - a) / width, 1e-12, 1 - 1e-12)
            return np.log(p) - np.log1p(-p)

        return potential, theta_of, z_of

    return jax.jit(log_post), coordinates


def check_identity(lik: Likelihood, log_post, x_start, cov, rng) -> bool:
    """ln p in JAX against ``lik.log_prob`` at the start, Laplace draws, points across the box
    and one outside it; the gradient against central differences of ``lik.log_prob``."""
    import jax
    import jax.numpy as jnp

    lo, hi = lik.space.bounds
    sd = np.sqrt(np.diag(cov)) if cov is not None else np.full(lo.size, 1e-3)
    points = [("start (LSQ)", x_start)]
    points += [(f"Laplace draw {k}", x_start + sd * rng.standard_normal(lo.size)) for k in (1, 2)]
    points += [
        (f"box point {k}", lo + (hi - lo) * rng.uniform(0.12, 0.88, lo.size)) for k in (1, 2, 3)
    ]
    points.append(("outside the box", np.where(np.arange(lo.size) == 0, hi + 0.1, x_start)))
    ok = True
    print(f"  identity: JAX ln p vs gonio Likelihood.log_prob (tolerance {IDENTITY_RTOL:g} rel.)")
    for name, x in points:
        x = np.clip(x, lo, hi) if "outside" not in name else x
        a = float(lik.log_prob(x))
        b = float(log_post(jnp.asarray(x)))
        if np.isfinite(a) or np.isfinite(b):
            rel = abs(a - b) / max(1.0, abs(a))
            good = rel <= IDENTITY_RTOL
        else:
            rel, good = 0.0, a == b
        ok &= bool(good)
        verdict = "ok" if good else "FAIL"
        print(f"    {name:16s} gonio {a:22.12f}  jax {b:22.12f}  rel {rel:8.1e}  {verdict}")
    # The gradient NUTS uses, at a Laplace draw (at the optimum it is ~0 and says nothing).
    x = np.clip(points[1][1], lo + 1e-6, hi - 1e-6)
    g = np.asarray(jax.grad(log_post)(jnp.asarray(x)))
    g_fd = np.empty_like(g)
    for k in range(x.size):
        h = 1e-6 * max(1.0, abs(x[k]))
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        g_fd[k] = (lik.log_prob(xp) - lik.log_prob(xm)) / (2 * h)
    grad_rel = float(np.linalg.norm(g - g_fd) / max(np.linalg.norm(g_fd), 1e-300))
    print(f"    gradient vs central differences of log_prob: ‖Δ‖/‖g‖ = {grad_rel:.1e}")
    return ok


def check_potential(lik: Likelihood, potential, theta_of, z_of, points: np.ndarray) -> bool:
    """NUTS' U(z) against −ln p(θ(z)) from gonio minus ln|dθ/dz| by central differences of θ(z)
    (the map is diagonal), at `points` (k, D) in θ: the coordinates add no error of their own."""
    import jax.numpy as jnp

    ok = True
    for x in points:
        z = z_of(x)
        theta = np.asarray(theta_of(jnp.asarray(z)))
        h = 1e-5
        dtheta_dz = [
            (
                np.asarray(theta_of(jnp.asarray(z + h * e)))[k]
                - np.asarray(theta_of(jnp.asarray(z - h * e)))[k]
            )
            / (2 * h)
            for k, e in enumerate(np.eye(z.size))
        ]
        want = -(float(lik.log_prob(theta)) + float(np.sum(np.log(dtheta_dz))))
        got = float(potential(jnp.asarray(z)))
        rel = abs(got - want) / max(1.0, abs(want))
        good = bool(rel <= 1e-8) and bool(np.allclose(theta, x, rtol=1e-9, atol=1e-9))
        ok &= good
        print(
            f"    NUTS' U(z) vs −(gonio ln p + ln|dθ/dz| by differences): rel {rel:.1e}, "
            f"θ(z(θ)) round trip {'ok' if good else 'FAIL'}"
        )
    return ok


# -- NUTS -----------------------------------------------------------------------------------------
class _CompileClock:
    """Seconds JAX spends tracing, lowering and compiling (jax.monitoring events)."""

    EVENTS = (
        "/jax/core/compile/jaxpr_trace_duration",
        "/jax/core/compile/jaxpr_to_mlir_module_duration",
        "/jax/core/compile/backend_compile_duration",
    )

    def __init__(self) -> None:
        from jax import monitoring

        self.seconds = 0.0
        monitoring.register_event_duration_secs_listener(self._listen)

    def _listen(self, event: str, duration: float, **_kw) -> None:
        if event in self.EVENTS:
            self.seconds += duration


@dataclass
class NutsRun:
    name: str
    chains: int
    method: str
    theta: np.ndarray  # (chains, draws, D)
    compile_s: float
    warmup_s: float  # without compile
    draws_s: float  # without compile
    lsq_s: float  # the least squares a set-up started there needed (else 0)
    leapfrog_per_draw: float
    divergences: int
    accept: float
    step_size: float
    draws_cut: bool = False  # fewer draws than asked, to stay in the time budget

    @property
    def draws(self) -> int:
        return self.theta.shape[1]

    @property
    def end_to_end_s(self) -> float:
        return self.lsq_s + self.compile_s + self.warmup_s + self.draws_s

    @property
    def mcmc_s(self) -> float:
        return self.warmup_s + self.draws_s


def run_nuts(
    name: str,
    potential,
    theta_of,
    z0: np.ndarray,
    *,
    dense: bool,
    method: str,
    warmup: int,
    draws: int,
    draw_budget_s: float,
    seed: int,
    lsq_s: float,
    clock: _CompileClock,
) -> NutsRun:
    """One NUTS run from z0 (chains, D): warmup, then `draws` per chain — fewer if the trees
    the warmup ended with predict more than `draw_budget_s` for them (the rates are per second,
    so a shorter run measures them as well; its ESS is then short of the target and the time
    to the target is extrapolated)."""
    import jax
    from numpyro.infer import MCMC, NUTS

    chains = z0.shape[0]
    mcmc = MCMC(
        NUTS(potential_fn=potential, dense_mass=dense),
        num_warmup=warmup,
        num_samples=draws,
        num_chains=chains,
        chain_method=method if chains > 1 else "sequential",
        progress_bar=False,  # the bar's per-step host callbacks would be timed too
    )
    init = z0 if chains > 1 else z0[0]
    c0, t0 = clock.seconds, time.perf_counter()
    # the warmup's tree sizes are kept to predict the draws' time
    mcmc.warmup(
        jax.random.PRNGKey(seed), init_params=init, collect_warmup=True, extra_fields=("num_steps",)
    )
    jax.block_until_ready(mcmc.post_warmup_state)
    c1, t1 = clock.seconds, time.perf_counter()
    steps = np.asarray(mcmc.get_extra_fields(group_by_chain=True)["num_steps"], dtype=float)
    # chains run side by side: the wall time follows the busiest chain
    per_leapfrog_s = ((t1 - t0) - (c1 - c0)) / max(float(np.max(steps.sum(axis=1))), 1.0)
    # NumPyro's last 50 warmup iterations already use the final mass matrix
    recent = float(np.max(steps[:, -min(50, warmup) :].mean(axis=1)))
    n_draws = int(min(draws, max(100, draw_budget_s / max(recent * per_leapfrog_s, 1e-9))))
    mcmc.num_samples = n_draws
    mcmc.run(
        mcmc.post_warmup_state.rng_key,
        extra_fields=("num_steps", "diverging", "accept_prob", "adapt_state.step_size"),
    )
    z = np.asarray(mcmc.get_samples(group_by_chain=True))
    c2, t2 = clock.seconds, time.perf_counter()
    extra = {k: np.asarray(v) for k, v in mcmc.get_extra_fields(group_by_chain=True).items()}
    theta = np.asarray(jax.vmap(jax.vmap(theta_of))(z.reshape(chains, n_draws, -1)))
    return NutsRun(
        name,
        chains,
        method if chains > 1 else "1 chain",
        theta,
        compile_s=(c1 - c0) + (c2 - c1),
        warmup_s=(t1 - t0) - (c1 - c0),
        draws_s=(t2 - t1) - (c2 - c1),
        lsq_s=lsq_s,
        leapfrog_per_draw=float(np.mean(extra["num_steps"])),
        divergences=int(np.sum(extra["diverging"])),
        accept=float(np.mean(extra["accept_prob"])),
        step_size=float(np.mean(extra["adapt_state.step_size"])),
        draws_cut=n_draws < draws,
    )


# -- statistics -----------------------------------------------------------------------------------
def ess(x: np.ndarray) -> np.ndarray:
    """NumPyro's ESS of draws (chains, draws, ...) — the one estimator used for both."""
    from numpyro.diagnostics import effective_sample_size

    return np.asarray(effective_sample_size(np.asarray(x, dtype=np.float64)), dtype=np.float64)


def ess_emcee(x: np.ndarray) -> np.ndarray:
    """ESS = chains·draws/τ with emcee's τ (Sokal window, averaged autocorrelation), for both."""
    import emcee

    tau = emcee.autocorr.integrated_time(np.swapaxes(x, 0, 1), tol=0)
    return x.shape[0] * x.shape[1] / np.asarray(tau, dtype=np.float64)


def split_rhat(x: np.ndarray) -> np.ndarray:
    from numpyro.diagnostics import split_gelman_rubin

    return np.asarray(split_gelman_rubin(np.asarray(x, dtype=np.float64)), dtype=np.float64)


def agreement(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """z-scores of the difference of posterior means and of sds, per parameter, of draws
    (chains, draws, D) in natural units; and the figures behind them."""
    rows = []
    for k in range(a.shape[-1]):
        stats = []
        for x in (a[..., k], b[..., k]):
            mean, sd = float(x.mean()), float(x.std())
            q = (x - mean) ** 2  # the variance's own series: its MCSE needs no Gaussian
            se_sd = float(q.std() / math.sqrt(max(float(ess(q[..., None])[0]), 1.0)) / (2 * sd))
            stats.append((mean, sd, sd / math.sqrt(max(float(ess(x[..., None])[0]), 1.0)), se_sd))
        (m1, s1, e1, q1), (m2, s2, e2, q2) = stats
        rows.append(
            {
                "mean": (m1, m2),
                "sd": (s1, s2),
                "z_mean": (m1 - m2) / math.hypot(e1, e2),
                "z_sd": (s1 - s2) / math.hypot(q1, q2),
            }
        )
    z_mean = np.array([r["z_mean"] for r in rows])
    z_sd = np.array([r["z_sd"] for r in rows])
    return z_mean, z_sd, rows


# -- one posterior --------------------------------------------------------------------------------
def pick_chain_method(potential, z: np.ndarray, chains: int, repeats: int = 200) -> str:
    """The fastest way to run `chains` chains on this machine, by the throughput of the
    gradient NUTS evaluates (gradients per second, all chains together): 1 chain ("single"),
    one chain per XLA device ("parallel", pmap) or all chains in one vmapped computation
    ("vectorized"). Vectorized NUTS also runs every chain's tree to the longest one's size, so
    it is picked only if it is faster per gradient by more than that could cost (25 %)."""
    import jax
    import jax.numpy as jnp

    vg = jax.value_and_grad(potential)
    zz = jnp.asarray(np.repeat(z[None, :], chains, axis=0))
    funcs = {"single": (jax.jit(vg), zz[0], 1)}
    if chains > 1:
        funcs["vectorized"] = (jax.jit(jax.vmap(vg)), zz, chains)
        if jax.local_device_count() >= chains:
            funcs["parallel"] = (jax.pmap(vg), zz, chains)
    rate = {}
    for name, (f, x, n) in funcs.items():
        jax.block_until_ready(f(x))
        t0 = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(f(x))
        rate[name] = n * repeats / (time.perf_counter() - t0)
    print(
        "  gradient throughput (grads/s, all chains): "
        + ", ".join(f"{k} {v:.0f}" for k, v in rate.items())
    )
    best = max(("single", "parallel"), key=lambda k: rate.get(k, 0.0))
    if rate.get("vectorized", 0.0) > 1.25 * rate[best]:
        best = "vectorized"
    return best


def compare(name: str, table: SampleTable, args, clock) -> dict:
    rng = np.random.default_rng([args.seed, 1])
    print(f"\n=== {name} posterior: {len(table)} rows, gonio vs NumPyro NUTS ===")
    g = run_gonio(table, args.target_ess, args.walkers, args.seed)
    lik, space, res = g.lik, g.lik.space, g.res
    names = space.names
    log_post, coordinates = jax_posterior(lik, g.x_lsq)
    if not check_identity(lik, log_post, g.x_start, g.cov, rng):
        print(f"  !!! {name}: the JAX posterior is NOT gonio's: no NUTS comparison for it !!!")
        return {"name": name, "identical": False}

    print(
        f"  gonio: LSQ {g.lsq_s:.1f} s; emcee DE, {res.chain.shape[1]} walkers, "
        f"{res.iterations} steps (burn {res.burn}), {res.wall_time_s:.1f} s, acceptance "
        f"{res.acceptance:.2f}, split R̂ max {np.nanmax(res.rhat):.3f}, stop: {res.stop_reason}"
    )
    print(
        "    τ (steps): "
        + ", ".join(f"{n} {t:.0f}" for n, t in zip(names, res.tau, strict=True))
        + f"; gonio's own min ESS {np.min(res.ess):.0f}"
    )
    gonio_ess = ess(g.theta)
    print(
        f"    min ESS: walkers as chains {np.min(gonio_ess):.0f} (used), emcee τ "
        f"{np.min(ess_emcee(g.theta)):.0f}; split R̂ (walkers as chains) "
        f"{np.max(split_rhat(g.theta)):.3f}"
    )
    out = {"name": name, "identical": True, "gonio": g, "nuts": []}
    if unusable := _unusable(g.theta):
        print(f"  !!! {name}: gonio's chain {unusable}: no check, no ratio !!!")

    potential, theta_of, z_of = coordinates(args.coords)
    chains = args.chains
    ball = initial_ball(lik.log_prob, g.x_start, chains, space.bounds, rng, g.cov)
    if not check_potential(lik, potential, theta_of, z_of, np.vstack([g.x_start, ball[:1]])):
        print(f"  !!! {name}: NUTS' potential is NOT gonio's posterior: no comparison !!!")
        return out
    z_lsq = z_of(ball)
    z_rand = rng.uniform(-2.0, 2.0, (chains, space.ndim))  # NumPyro's init_to_uniform
    method = args.chain_method
    if method == "auto":
        method = pick_chain_method(potential, z_lsq[0], chains)
    n_chains = 1 if method == "single" else chains
    print(
        f"  NUTS: coordinates {args.coords}, {n_chains} chain(s)"
        + (f" {method}" if n_chains > 1 else "")
        + f", warmup {args.nuts_warmup} + up to {args.nuts_draws} draws per chain "
        f"(≤ ~{args.nuts_budget_s:g} s of draws); seconds:"
    )
    print(
        f"    {'set-up':13s} {'compile':>7s} {'warmup':>7s} {'draws':>7s} {'n':>5s} "
        f"{'leapfrog':>8s} {'div':>4s} {'accept':>6s} {'step':>6s} {'R̂max':>6s} {'minESS':>7s} "
        f"{'ESS/s':>7s}  agrees with gonio (max |z|)"
    )
    g_nat = space.to_natural(g.theta)
    for label, start, dense in SETUPS:
        if args.setups and label not in args.setups:
            continue
        r = run_nuts(
            label,
            potential,
            theta_of,
            (z_lsq if start == "lsq" else z_rand)[:n_chains],
            dense=dense,
            method=method,
            warmup=args.nuts_warmup,
            draws=args.nuts_draws,
            draw_budget_s=args.nuts_budget_s,
            seed=args.seed + len(out["nuts"]),
            lsq_s=g.lsq_s if start == "lsq" else 0.0,
            clock=clock,
        )
        zm, zs, _ = agreement(g_nat, space.to_natural(r.theta))
        worst_z = float(np.max(np.abs(np.concatenate([zm, zs]))))
        why = unusable or _unusable(r.theta)
        agrees = not why and bool(np.all(np.isfinite(zm)) and worst_z < AGREE_Z)
        out["nuts"].append((r, agrees))
        e = ess(r.theta)
        if agrees:
            flag = f"yes ({worst_z:.1f})"
        elif why:
            flag = f"cannot tell: {'gonio' if unusable else 'NUTS'} {why}"
        else:
            flag = f"NO — THE POSTERIORS DIFFER ({worst_z:.1f})"
        print(
            f"    {r.name:13s} {r.compile_s:7.1f} {r.warmup_s:7.1f} {r.draws_s:7.1f} "
            f"{r.draws:5d}{'*' if r.draws_cut else ' '}{r.leapfrog_per_draw:7.1f} "
            f"{r.divergences:4d} {r.accept:6.2f} {r.step_size:6.3f} "
            f"{np.max(split_rhat(r.theta)):6.3f} {np.min(e):7.0f} "
            f"{np.min(e) / r.end_to_end_s:7.2f}  {flag}"
        )
    print(
        "    (n: draws per chain, * cut to the time budget; leapfrog: steps per draw; step: "
        "adapted step size; ESS/s: end to end)"
    )
    ok = [(np.min(ess(r.theta)) / r.end_to_end_s, r) for r, agrees in out["nuts"] if agrees]
    if not ok:
        print(f"  !!! {name}: NO NUTS set-up checked out against gonio's posterior: no ratio !!!")
        return out
    best = max(ok, key=lambda t: t[0])[1]
    print(f"  best NUTS set-up: {best.name} (the highest end-to-end ESS/s of those that agree)")
    print_agreement(names, g_nat, space.to_natural(best.theta))
    out.update(print_rates(g, best, names, args.target_ess))
    return out


def _unusable(theta: np.ndarray) -> str:
    """Why draws (chains, draws, D) cannot be checked against another sampler's, or "": chains
    that disagree (split R̂ ≥ 1.05) or too few effective draws for the MCSEs the check uses
    (min ESS < 50)."""
    rhat, e = float(np.max(split_rhat(theta))), float(np.min(ess(theta)))
    if not rhat < RHAT_MAX:
        return f"has not mixed (split R̂ {rhat:.2f} ≥ {RHAT_MAX:g})"
    if not e >= MIN_ESS_TO_CHECK:
        return f"is too short (min ESS {e:.0f} < {MIN_ESS_TO_CHECK})"
    return ""


def print_agreement(names, a: np.ndarray, b: np.ndarray) -> None:
    zm, zs, rows = agreement(a, b)
    print(f"  agreement, natural units (|z| < {AGREE_Z:g} for each):")
    print(
        f"    {'parameter':12s} {'gonio mean':>13s} {'± sd':>10s} {'NUTS mean':>13s} "
        f"{'± sd':>10s} {'z mean':>7s} {'z sd':>6s}"
    )
    for n, r in zip(names, rows, strict=True):
        (m1, m2), (s1, s2) = r["mean"], r["sd"]
        print(
            f"    {n:12s} {m1:13.7g} {s1:10.3g} {m2:13.7g} {s2:10.3g} "
            f"{r['z_mean']:7.2f} {r['z_sd']:6.2f}"
        )


def print_rates(g: GonioRun, best: NutsRun, names, target: float) -> dict:
    """ESS/s of both, three timings, and the ratio; min over all 9 parameters, then over the
    8 BRDF parameters (without the discrepancy, NUTS' slowest by far)."""
    e_g, e_n = ess(g.theta), ess(best.theta)
    brdf = np.array([n != "discrepancy" for n in names])
    # time to the target: the fixed part (LSQ, burn-in / compile, warmup) + the kept draws'
    # time scaled to the target (ESS grows linearly with the draws)
    g_fixed = g.lsq_s + g.mcmc_s - g.draws_s
    n_fixed = best.end_to_end_s - best.draws_s
    secs = {
        "end-to-end": (g.lsq_s + g.mcmc_s, best.end_to_end_s),
        "MCMC only": (g.mcmc_s, best.mcmc_s),
        "draws only": (g.draws_s, best.draws_s),
    }
    out = {}
    for label, sel in (("all 9 parameters", slice(None)), ("8 BRDF parameters", brdf)):
        mg, mn = float(np.min(e_g[sel])), float(np.min(e_n[sel]))
        to_target = (g_fixed + g.draws_s * target / mg, n_fixed + best.draws_s * target / mn)
        print(f"  ESS/s, min ESS over {label} (NumPyro's estimator for both):")
        print(
            f"    {'':12s} {'min ESS':>8s}"
            + "".join(f" {k + ' s':>14s} {'ESS/s':>7s}" for k in secs)
            + f" {'s to ' + format(target, 'g') + ' ESS':>14s}"
        )
        for who, k, e in (("gonio", 0, mg), ("NUTS", 1, mn)):
            print(
                f"    {who:12s} {e:8.0f}"
                + "".join(f" {t[k]:14.1f} {e / t[k]:7.1f}" for t in secs.values())
                + f" {to_target[k]:14.1f}"
            )
        ratio = {k: (mg / t[0]) / (mn / t[1]) for k, t in secs.items()}
        ratio["to target"] = to_target[1] / to_target[0]
        print(
            f"    {'gonio/NUTS':12s} {'':8s}"
            + "".join(f" {'':14s} {ratio[k]:7.2f}" for k in secs)
            + f" {ratio['to target']:14.2f}"
        )
        if label.startswith("all"):
            print(
                f"    (emcee τ estimator on both: min ESS gonio {np.min(ess_emcee(g.theta)):.0f}, "
                f"NUTS {np.min(ess_emcee(best.theta)):.0f})"
            )
        out[label] = {"gonio_ess": mg, "nuts_ess": mn, "ratio": ratio, "to_target_s": to_target}
    print(
        f"    end-to-end: gonio LSQ + MCMC; NUTS JAX compile ({best.compile_s:.1f} s) + warmup "
        "+ draws"
        + (f" + the LSQ it starts from ({best.lsq_s:.1f} s)" if best.lsq_s else "")
        + ". MCMC only: gonio with its burn-in; NUTS warmup + draws, no compile. Draws only:"
        " gonio's kept steps, NUTS' post-warmup draws. s to target: extrapolated from the draws'"
        " rate where an ESS is short of it (ratios > 1: gonio faster)"
    )
    return out


def _configure_threads(threads: int) -> None:
    """The same thread count for both: CPU affinity (XLA sizes its pool from it), numba's
    threads, and as many XLA host devices for chain_method="parallel". Before jax is imported."""
    import numba

    if hasattr(os, "sched_setaffinity"):
        cpus = sorted(os.sched_getaffinity(0))
        if len(cpus) > threads:
            os.sched_setaffinity(0, cpus[:threads])
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    flag = f"--xla_force_host_platform_device_count={threads}"
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {flag}".strip()


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: target ESS 200, 3000 rows per channel, only lsq/dense, short NUTS",
    )
    ap.add_argument("--posteriors", default="smooth,sharp", help="comma-separated subset")
    ap.add_argument("--samples", type=int, default=None, help="rows per channel (10000)")
    ap.add_argument("--sharp-m", type=float, default=SHARP_M, help="roughness of 'sharp'")
    ap.add_argument("--target-ess", type=float, default=None, help="gonio's target (1000)")
    ap.add_argument("--walkers", type=int, default=32)
    ap.add_argument("--nuts-warmup", type=int, default=None, help="default 500 (quick 300)")
    ap.add_argument("--nuts-draws", type=int, default=None, help="per chain; 1000 (quick 500)")
    ap.add_argument(
        "--nuts-budget-s",
        type=float,
        default=45.0,
        help="fewer NUTS draws (≥ 100) where the warmup predicts more seconds of draws",
    )
    ap.add_argument("--chains", type=int, default=2, help="NUTS chains (default 2: 2 cores)")
    ap.add_argument(
        "--chain-method",
        default="auto",
        choices=("auto", "parallel", "vectorized", "single"),
        help="auto: the fastest by gradient throughput",
    )
    ap.add_argument(
        "--coords", default="natural", choices=("natural", "theta"), help="NUTS' coordinates"
    )
    ap.add_argument("--setups", default="", help="only these set-ups, e.g. lsq/dense")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    args.target_ess = args.target_ess or (200.0 if args.quick else 1000.0)
    args.samples = args.samples or (3000 if args.quick else 10_000)
    args.nuts_warmup = args.nuts_warmup or (300 if args.quick else 500)
    args.nuts_draws = args.nuts_draws or (500 if args.quick else 1000)
    args.setups = [s for s in args.setups.split(",") if s] or (["lsq/dense"] if args.quick else [])

    if importlib.util.find_spec("jax") is None or importlib.util.find_spec("numpyro") is None:
        print("jax/numpyro not installed: `pip install -e '.[bench]'`; NUTS comparison skipped")
        return {}
    _configure_threads(args.threads)
    import jax

    jax.config.update("jax_enable_x64", True)
    clock = _CompileClock()
    print(
        f"threads {args.threads} (numba and XLA), XLA devices {jax.local_device_count()}, "
        f"gonio target ESS {args.target_ess:g}, NUTS warmup {args.nuts_warmup} + "
        f"{args.nuts_draws} draws × {args.chains} chains"
    )
    out = {}
    for name in args.posteriors.split(","):
        rng = np.random.default_rng(args.seed)  # bench_mcmc's table for 'smooth', same seed
        if name == "smooth":
            table = synthetic_table(args.samples, rng)
        elif name == "sharp":
            table = sharp_table(args.samples, rng, m=args.sharp_m)
        else:
            raise SystemExit(f"unknown posterior {name!r}: use smooth, sharp")
        out[name] = compare(name, table, args, clock)
    return out


if __name__ == "__main__":
    main()

"""MCMC speed benchmark (issue 7 acceptance, "Speed"): Torrance-Sparrow + Lambert on 10⁴ samples
× 3 channels. Reports the wall time for emcee (vectorised log-probability, one model call per
channel per half-ensemble) to reach 1000 effective samples for every parameter, and the ratio
of per-step cost against a plain per-walker numpy log-probability (``vectorize=False``, model
evaluated with scalar parameters on the numpy backend). The baseline is timed over a short run
and its time-to-1000-ESS extrapolated with the same number of steps (the chain statistics do not
depend on how the log-probability is computed).

Run: ``.venv/bin/python benchmarks/bench_mcmc.py [--samples 10000] [--walkers 32]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from brdfdata.directions import spherical_to_vector
from brdfdata.samples import SampleTable
from fitting import models
from fitting.fit import _precision_probes
from fitting.likelihood import Likelihood
from fitting.lsq import fit_least_squares
from fitting.mcmc import McmcOptions, run_mcmc
from fitting.priors import ParameterSpace

__all__ = ["main", "synthetic_table"]

TRUTH = {"kd": (0.5, 0.3, 0.2), "ks": (0.8, 0.6, 0.4), "m": 0.2, "ior": 1.5}


def synthetic_table(n: int, rng: np.random.Generator, rel_noise: float = 0.03) -> SampleTable:
    model = models.get("torrance-sparrow")
    parts = []
    for c, kd, ks in zip("RGB", TRUTH["kd"], TRUTH["ks"], strict=True):
        ti = rng.uniform(0.05, 1.3, n)
        to = rng.uniform(0.05, 1.3, n)
        po = np.where(
            np.arange(n) % 2 == 0, np.pi + rng.uniform(-0.3, 0.3, n), rng.uniform(0, 2 * np.pi, n)
        )
        wi, wo = spherical_to_vector(ti, np.zeros(n)), spherical_to_vector(to, po)
        f = model.evaluate({"kd": kd, "ks": ks, "m": TRUTH["m"], "ior": TRUTH["ior"]}, wi, wo)
        sig = rel_noise * f + 1e-3
        parts.append(
            (ti, np.zeros(n), to, po, np.full(n, c), f + sig * rng.standard_normal(n), sig)
        )
    cols = [np.concatenate([p[i] for p in parts]) for i in range(7)]
    return SampleTable(*cols, np.zeros(cols[0].size, np.int32))


def plain_log_prob(lik: Likelihood):
    """Per-walker log-probability in plain numpy: θ (D,) → float (the baseline)."""
    space = lik.space

    def log_prob(theta: np.ndarray) -> float:
        lp = float(space.log_prior(theta[None, :])[0])
        if not np.isfinite(lp):
            return -np.inf
        nat = space.natural_dict(theta[None, :])
        s = nat.get("discrepancy")
        total = 0.0
        for i, d in enumerate(lik.data):
            params = {k: float(v[0, 0]) for k, v in space.channel_params(nat, d.channel).items()}
            fm = lik.model.evaluate(params, d.wi, d.wo, backend="numpy")
            ref = fm if lik.discrepancy_reference is None else lik.discrepancy_reference[i]
            var = d.sigma**2 + (0.0 if s is None else (s[0] * ref) ** 2)
            total += float(np.sum(-0.5 * ((d.f - fm) ** 2 / var + np.log(2 * np.pi * var))))
        return total if np.isfinite(total) else -np.inf

    return log_prob


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=10_000, help="samples per channel")
    ap.add_argument("--walkers", type=int, default=32)
    ap.add_argument("--target-ess", type=float, default=1000.0)
    ap.add_argument("--baseline-steps", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--moves", default="de", help="de (default) or stretch")
    ap.add_argument("--fix-ior", action="store_true", help="hold ior = 1.5 (8 parameters)")
    ap.add_argument("--no-discrepancy", action="store_true", help="drop the discrepancy term")
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    table = synthetic_table(args.samples, rng)
    model = models.get("torrance-sparrow")
    space = ParameterSpace.build(
        model,
        ["R", "G", "B"],
        discrepancy=not args.no_discrepancy,
        fix={"ior": TRUTH["ior"]} if args.fix_ior else None,
    )
    lik = Likelihood(model, table, space)

    t0 = time.perf_counter()
    lsq = fit_least_squares(lik, seed=args.seed)
    t_lsq = time.perf_counter() - t0
    lik = lik.frozen_at(lsq.x)  # as fit_samples does
    scale = np.sqrt(np.clip(np.diag(lsq.cov), 1e-12, None)) if lsq.cov is not None else None
    x0 = lsq.x.copy()
    if not args.no_discrepancy:
        x0[space.index("discrepancy")] = np.log(2e-4)
    lo, hi = space.bounds
    probes = _precision_probes(lik, lsq, x0, args.seed)
    # as fit_samples: the model in float32 for the sampling only, where it is measured harmless
    with lik.sampling_precision(probes) as (precision, rounding):
        res = run_mcmc(
            lik.log_prob,
            x0,
            (lo, hi),
            McmcOptions(
                walkers=args.walkers,
                max_steps=100_000,
                target_ess=args.target_ess,
                moves=args.moves,
            ),
            rng=args.seed,
            scale=scale,
        )
    per_step_vec = res.wall_time_s / res.iterations

    base = plain_log_prob(lik)
    t0 = time.perf_counter()
    run_mcmc(
        base,
        x0,
        (lo, hi),
        McmcOptions(
            walkers=args.walkers,
            max_steps=args.baseline_steps,
            vectorize=False,
            chunk=args.baseline_steps,
        ),
        rng=args.seed,
        scale=scale,
    )
    per_step_base = (time.perf_counter() - t0) / args.baseline_steps
    out = {
        "rows": len(table),
        "names": " ".join(space.names),
        "tau": " ".join(f"{t:.0f}" for t in res.tau),
        "parameters": space.ndim,
        "walkers": args.walkers,
        "lsq_s": t_lsq,
        "model_precision": f"{precision} (ln L rounding {rounding:.1e})",
        "mcmc_s_to_target": res.wall_time_s,
        "steps": res.iterations,
        "stop_reason": res.stop_reason,
        "min_ess": float(np.min(res.ess)),
        "max_tau": float(np.max(res.tau)),
        "acceptance": res.acceptance,
        "ms_per_step_vectorised": 1e3 * per_step_vec,
        "ms_per_step_plain": 1e3 * per_step_base,
        "speedup": per_step_base / per_step_vec,
        "plain_s_to_target_extrapolated": per_step_base * res.iterations,
    }
    for k, v in out.items():
        print(f"{k:32s} {v:.4g}" if isinstance(v, float) else f"{k:32s} {v}")
    return out


if __name__ == "__main__":
    main()

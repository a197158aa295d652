"""The two samplers of `gonio fit` on a unimodal posterior (issue 44 item 1: "the chosen default
must keep today's speed on unimodal posteriors; make bench shows both"): the same fit of a
Torrance-Sparrow table (benchmarks/bench_mcmc.py's synthetic table, 3 channels) with the
ensemble (the default) and with parallel tempering (`--sampler tempered`), each as `gonio fit`
runs it (fitting.fit.fit_samples). Reported per sampler: the fit's wall time, the chain's steps,
its worst R̂ and bulk ESS, ESS per second of sampling, and the modes a tempered fit reports.

Run: ``.venv/bin/python benchmarks/bench_tempered.py [--samples 2000] [--temperatures 8]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from bench_mcmc import synthetic_table

from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions

__all__ = ["main"]


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=2000, help="samples per channel")
    ap.add_argument("--temperatures", type=int, default=8)
    ap.add_argument("--steps", type=int, default=3000, help="the cap on each chain's steps")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    table = synthetic_table(args.samples, np.random.default_rng(args.seed))
    out = {}
    for sampler in ("ensemble", "tempered"):
        mcmc = McmcOptions(max_steps=args.steps, sampler=sampler, temperatures=args.temperatures)
        t0 = time.perf_counter()
        fit = fit_samples(table, FitOptions(mcmc=mcmc, seed=args.seed))
        wall = time.perf_counter() - t0
        d = fit.diagnostics
        res = fit.extras["mcmc"]
        ess = min(d["ess"].values())
        row = {
            "fit_s": wall,
            "mcmc_s": res.wall_time_s,
            "steps": res.iterations,
            "stop_reason": d["stop_reason"],
            "rhat_max": max(d["rhat"].values()),
            "ess_min": ess,
            "ess_per_mcmc_s": ess / res.wall_time_s,
            "modes": d.get("modes", {}).get("words", "(not searched by the ensemble)"),
        }
        out[sampler] = row
        print(f"-- {sampler}")
        for k, v in row.items():
            print(f"{k:20s} {v:.4g}" if isinstance(v, float) else f"{k:20s} {v}")
    ratio = out["tempered"]["fit_s"] / out["ensemble"]["fit_s"]
    print(f"tempered / ensemble fit time {ratio:.2f}× ({args.temperatures} temperatures)")
    return out


if __name__ == "__main__":
    main()

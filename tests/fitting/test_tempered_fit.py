"""`gonio fit --sampler tempered` (issue 44 item 1): parallel tempering as the fit's chain.

On a unimodal posterior (a Torrance-Sparrow table made by the independent numpy reference of
tests/support/synthetic_ts.py) the tempered chain must sample the same posterior as the
ensemble — medians and widths agree within their Monte Carlo error — report one mode, and leave
the chain file the report reads. That the tempered sampler finds modes the ensemble cannot, with
their masses, is tests/fitting/test_tempering.py's (known weights 0.7 / 0.3)."""

from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np

from brdfdata.samples import write_samples
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions
from tests.support.synthetic_ts import synthetic

FIT = dict(model="torrance-sparrow", model_options={"fresnel": "none"}, discrepancy=False, seed=5)


def test_tempered_chain_samples_the_ensembles_posterior_and_reports_one_mode(tmp_path):
    table = synthetic(0.2, 150, np.random.default_rng(21))
    plain = fit_samples(table, FitOptions(**FIT, mcmc=McmcOptions(walkers=32, max_steps=4000)))
    tempered = fit_samples(
        table,
        FitOptions(
            **FIT, mcmc=McmcOptions(walkers=32, max_steps=2000, sampler="tempered", temperatures=4)
        ),
        out_dir=tmp_path,
    )
    d = tempered.diagnostics
    assert d["modes"]["count"] == 1, d["modes"]
    assert d["modes"]["words"].startswith("one mode"), d["modes"]["words"]
    # The ladder passes walkers on: every neighbouring pair swaps (a stuck ladder reads ~0).
    assert min(d["tempering"]["swap_acceptance"]) > 0.05, d["tempering"]
    ess = min(d["ess"].values())
    assert ess > 300, d["ess"]
    for name, p in plain.parameters.items():
        q = tempered.parameters[name]
        sd = 0.5 * (p["p84"] - p["p16"])
        # Two chains of the same posterior, each ESS ≥ 300: a median's Monte Carlo sd is about
        # 1.25 sd/√ESS ≤ 0.07 sd, the difference of two ≤ 0.1 sd, so 0.4 sd is 4 of its sds; a
        # tempered chain that samples L^β with β ≠ 1 (the wrong temperature kept) is off by far
        # more, and its widths by √(1/β).
        assert abs(q["median"] - p["median"]) < 0.4 * sd, (name, p, q)
        # A 68 % half-width's Monte Carlo error at ESS 300 is ~5 %: 25 % is 3.5 of its sds
        # for the difference of two.
        width = 0.5 * (q["p84"] - q["p16"])
        assert abs(width / sd - 1) < 0.25, (name, width, sd)
    # The stopping rule ended the run early (a unimodal posterior needs no 2000 steps), and the
    # chain file holds the kept chain as its second half (the report draws that half).
    res = tempered.extras["mcmc"]
    assert d["stop_reason"] == "converged" and res.iterations < 2000, (d, res.iterations)
    kept = res.iterations - res.burn
    stored = kept + min(res.burn, kept)
    with h5py.File(tmp_path / "fit-torrance-sparrow.h5") as fh:
        assert int(fh["mcmc"].attrs["iteration"]) == stored
        assert fh["mcmc"]["chain"].shape == (stored, 32, len(plain.parameters))


def test_fit_command_refuses_an_unknown_sampler_in_one_line(tmp_path):
    path = tmp_path / "samples.parquet"
    write_samples(path, synthetic(0.2, 20, np.random.default_rng(1)))
    for args, says in (
        (["--sampler", "gibbs"], "--sampler 'gibbs': use one of ensemble, tempered"),
        (["--sampler", "tempered", "--temperatures", "0"], "--temperatures 0: give 1 to 64"),
    ):
        run = subprocess.run(
            [sys.executable, "-m", "gonio.cli", "fit", str(path), *args],
            capture_output=True,
            text=True,
            timeout=60,  # a one-line refusal takes ~2 s
        )
        assert run.returncode == 2, run.stderr
        assert run.stderr.count("\n") == 1 and says in run.stderr, run.stderr

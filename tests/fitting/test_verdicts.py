"""Verdicts a fit gives about itself (issue 18 item 1, fitting.verdicts).

Two kinds of cases. Convergence verdicts are tested on constructed chains, because the chain
*is* the verdict's input and a constructed one has known properties (independent draws, a
known split between walker groups, walkers that never move). Goodness-of-fit verdicts are
tested on real fits to samples of Mitsuba's own BSDF (simulator.truth.direct_samples: ground
truth from an independent implementation, never from the model under test), plus the energy
check on parameter sets whose albedo is known analytically.
"""

from __future__ import annotations

import emcee
import numpy as np
import pytest

from brdfdata.directions import grid_direction_pairs
from fitting import models
from fitting.convergence import diagnose
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions, McmcResult
from fitting.priors import ParameterSpec, PriorBound, PriorsConfig
from fitting.verdicts import (
    VERDICT_NAMES,
    bounds_verdict,
    censoring_verdict,
    chi2_verdict,
    energy_verdict,
    identified_verdict,
    mcmc_verdict,
)
from simulator.scene import BlendMaterial, DiffuseMaterial, RoughConductorMaterial
from simulator.truth import direct_samples

TS_MITSUBA = {"fresnel": "none", "shadowing": "smith-rational"}  # what roughconductor renders


def _result(chain: np.ndarray, log_prob: np.ndarray) -> McmcResult:
    """An McmcResult of a constructed post-burn chain, diagnosed as fitting.mcmc does."""
    tau = np.asarray(emcee.autocorr.integrated_time(chain, tol=0), float)
    d = diagnose([chain])
    return McmcResult(
        chain=chain,
        log_prob=log_prob,
        tau=tau,
        ess=d.ess_bulk,
        ess_tail=d.ess_tail,
        rhat=d.rhat,
        acceptance=1.0,
        burn=0,
        iterations=chain.shape[0],
        converged=True,
        stop_reason="converged",
        wall_time_s=0.0,
    )


def _iid(n=2000, walkers=32, ndim=2, seed=0):
    """Independent N(0, 1) draws: a perfectly mixed ensemble (τ = 1, R̂ → 1)."""
    chain = np.random.default_rng(seed).standard_normal((n, walkers, ndim))
    return chain, -0.5 * np.sum(chain**2, axis=-1)


def test_mixed_chain_is_converged() -> None:
    chain, lp = _iid()
    v, failed, because = mcmc_verdict(_result(chain, lp), ["a", "b"])
    assert v["status"] == "ok" and failed == [] and v["advice"] == ""
    assert because.startswith("R̂ max")


def test_rhat_above_1_1_fails() -> None:
    chain, lp = _iid()
    # Half the walkers sample N(1.5, 1): between-walker variance 1.5²/4 ≈ 0.56 of the
    # within variance, split R̂ ≈ √1.56 ≈ 1.25 > 1.1. Their ln p stays within the χ²_2
    # range (not "lost"). The ensemble's draws, its walkers end to end (fitting.convergence),
    # then hold two long blocks 1.5 apart: their ESS is low too, as it should be.
    chain[:, 16:, 0] += 1.5
    res = _result(chain, lp)
    assert np.max(res.rhat) > 1.1
    v, failed, because = mcmc_verdict(res, ["a", "b"])
    assert v["status"] == "fail" and failed[0] == "rhat" and set(failed) <= {"rhat", "ess"}
    assert "R̂" in v["reason"] and "(a)" in v["reason"] and because.startswith("not converged")


def test_rhat_between_1_01_and_1_1_warns() -> None:
    chain, lp = _iid()
    # A shift of 0.3 sd of half the walkers: R̂ 1.014 (measured), and the ESS of the walkers'
    # draws end to end 113 (two blocks 0.3 apart; a warning, ≥ 100).
    chain[:, 16:, 1] += 0.3
    v, failed, _ = mcmc_verdict(_result(chain, lp), ["a", "b"])
    assert v["status"] == "warning" and "rhat" in failed and "(b)" in v["reason"]


@pytest.mark.parametrize(("n_stuck", "status"), [(1, "warning"), (5, "fail")])
def test_stuck_walkers_are_named(n_stuck: int, status: str) -> None:
    chain, lp = _iid()
    # Walkers that never move, at an ordinary point of the posterior (so they are not "lost").
    chain[:, :n_stuck, :] = 0.3
    lp[:, :n_stuck] = -0.5 * 2 * 0.3**2
    v, failed, _ = mcmc_verdict(_result(chain, lp), ["a", "b"])
    assert v["status"] == status, v
    assert "stuck" in failed and f"{n_stuck} of 32 walkers stuck" in v["reason"]


def test_lost_walker_is_named() -> None:
    chain, lp = _iid()
    # One walker moves but in a far, improbable region: 2Δln p ≈ 2·40 ≫ χ²_2(1 − 1e-6) ≈ 27.6.
    chain[:, 7, :] += 40.0
    lp[:, 7] -= 40.0
    v, failed, _ = mcmc_verdict(_result(chain, lp), ["a", "b"])
    assert "lost" in failed and "1 of 32 walkers lost (7)" in v["reason"]


def test_short_chain_and_no_mcmc_are_warnings() -> None:
    chain, lp = _iid(n=300)
    res = _result(chain, lp)
    res.tau = np.array([20.0, 1.0])  # 300 steps < 20 τ = 400
    res.ess = np.array([960.0, 9600.0])
    v, failed, _ = mcmc_verdict(res, ["a", "b"])
    assert v["status"] == "warning" and failed == ["length"] and "20τ" in v["reason"]
    v, failed, because = mcmc_verdict(None, ["a"])
    assert v["status"] == "warning" and failed == ["mcmc"] and "Laplace" in v["reason"]


def test_chi2_spread_thresholds() -> None:
    # sd of χ²/dof is √(2/ν): ν = 20000 → 0.01. 1.02 is +2 sd (ok), 1.04 +4 sd (warning: far in
    # sd but residuals only 2 % above σ), 3.0 is +200 sd and √3 = 1.73 > 1.5 (fail).
    assert chi2_verdict({"chi2_red": 1.02, "dof": 20000})["status"] == "ok"
    v = chi2_verdict({"chi2_red": 1.04, "dof": 20000})
    assert v["status"] == "warning" and "+4.0 sd" in v["reason"]
    v = chi2_verdict({"chi2_red": 3.0, "dof": 20000})
    assert v["status"] == "fail" and "+200.0 sd" in v["reason"] and v["advice"]
    assert chi2_verdict({"chi2_red": 0.3, "dof": 20000})["status"] == "fail"


def test_regions_name_where_the_residuals_are_too_large() -> None:
    from brdfdata.directions import uniform_hemisphere
    from brdfdata.rusinkiewicz import to_half_diff
    from fitting.mismatch import region_index
    from fitting.verdicts import regions_verdict

    rng = np.random.default_rng(0)
    wi, wo = uniform_hemisphere(3000, rng), uniform_hemisphere(3000, rng)
    reg = region_index(wi, wo)
    r = rng.standard_normal(3000)  # unit residuals everywhere: a model that fits
    assert regions_verdict(reg, r)["status"] == "ok"
    # The model undershoots at grazing θ_d by 2 σ: the global χ²/dof rises only to ≈ 1.3
    # (a sixth of the samples), but that region's χ²/n ≈ 5 is far outside its spread.
    _, td, _ = to_half_diff(wi, wo)
    r[td > np.radians(60)] += 2.0
    v = regions_verdict(reg, r)
    assert v["status"] == "fail" and "θd 60–90°" in v["reason"], v
    assert "model mostly below the data" in v["reason"]


def _grid():
    return grid_direction_pairs([10, 30, 50, 70], np.arange(2, 81, 6), [180, 150, 110, 60, 0])


BLEND = BlendMaterial(
    weight=0.25,
    first=DiffuseMaterial(reflectance=(0.6, 0.4, 0.2)),
    second=RoughConductorMaterial(alpha=0.2, conductor="none"),
)


def _verdicts(result) -> dict[str, dict]:
    return {v["name"]: v for v in result.verdicts}


def test_lambert_on_a_glossy_material_fails_chi2() -> None:
    wi, wo = _grid()
    table, _ = direct_samples(BLEND, wi, wo, rel_sigma=0.02, floor_sr=1e-3, rng=3, channels="R")
    fit = fit_samples(table, FitOptions(model="lambert", channels=["R"], mcmc=None, seed=3))
    v = _verdicts(fit)["chi2"]
    # A Lambertian misses the Beckmann lobe (peak f ≈ 1 sr⁻¹ over a 0.14 sr⁻¹ base) by many σ.
    assert v["status"] == "fail" and fit.goodness["chi2_red"] > 10, v
    assert "sd from 1" in v["reason"]


def test_discrepancy_piled_at_its_bound_fails() -> None:
    wi, wo = _grid()
    # A Lambertian fitted to a bare Beckmann lobe (no diffuse part): f runs from ≈ 0 to many
    # times any constant, so the model error exceeds 100 % of f̃ and s piles at its bound 1.
    # The low floor keeps σ small next to s·f̃, so s is identified, not lost in the noise.
    lobe = RoughConductorMaterial(alpha=0.3, conductor="none")
    table, _ = direct_samples(lobe, wi, wo, rel_sigma=0.01, floor_sr=1e-4, rng=1, channels="R")
    fit = fit_samples(
        table, FitOptions(model="lambert", channels=["R"], mcmc=McmcOptions(max_steps=1500), seed=1)
    )
    v = _verdicts(fit)["discrepancy"]
    assert v["status"] == "fail" and "piled at its prior bound 1" in v["reason"], v
    assert fit.parameters["discrepancy"]["p2.5"] > 0.9  # the whole 95 % interval at the edge


def test_parameter_at_a_prior_bound_is_named() -> None:
    wi, wo = _grid()
    diffuse = DiffuseMaterial(reflectance=(0.6, 0.6, 0.6))
    table, _ = direct_samples(diffuse, wi, wo, rel_sigma=0.02, floor_sr=1e-3, rng=4, channels="R")
    # The prior stops kd at 0.5; Mitsuba's diffuse has ρ = 0.6, so the posterior piles there.
    priors = PriorsConfig(parameters={"kd": PriorBound(upper=0.5)})
    fit = fit_samples(
        table,
        FitOptions(
            model="lambert", channels=["R"], priors=priors, mcmc=McmcOptions(max_steps=1500), seed=4
        ),
    )
    v = _verdicts(fit)["bounds"]
    assert v["status"] == "warning" and "kd_R at its upper bound 0.5" in v["reason"], v


def test_bounds_and_identified_on_constructed_posteriors() -> None:
    spec = ParameterSpec("kd_R", "kd", "R", "1", 0.0, 1.0, False)
    inside = {"p2.5": 0.40, "p16": 0.45, "median": 0.5, "p84": 0.55, "p97.5": 0.60}
    assert bounds_verdict({"kd_R": inside}, [spec])["status"] == "ok"
    # Half-normal from the bound 0 with sd 0.01: p2.5 = 0.0003, p97.5 = 0.022.
    piled = {"p2.5": 0.0003, "p16": 0.002, "median": 0.0067, "p84": 0.014, "p97.5": 0.022}
    assert "lower bound" in bounds_verdict({"kd_R": piled}, [spec])["reason"]
    assert identified_verdict({"kd_R": inside}, [spec])["status"] == "ok"
    # A flat posterior over the prior: p16 … p84 = 0.16 … 0.84, all of the prior's 68 % span.
    flat = {"p2.5": 0.025, "p16": 0.16, "median": 0.5, "p84": 0.84, "p97.5": 0.975}
    v = identified_verdict({"kd_R": flat}, [spec])
    assert v["status"] == "warning" and "kd_R" in v["reason"]


def test_discrepancy_verdict_on_constructed_posteriors() -> None:
    from fitting.verdicts import discrepancy_verdict

    spec = ParameterSpec("discrepancy", "discrepancy", None, "1", 1e-4, 1.0, True)

    def q(p2, p16, p50, p84, p97):
        return {
            "discrepancy": dict(
                zip(
                    ["p2.5", "p16", "median", "p84", "p97.5"], [p2, p16, p50, p84, p97], strict=True
                )
            )
        }

    assert discrepancy_verdict(q(0.9, 0.97, 0.99, 0.998, 0.9999), [spec])["status"] == "fail"
    # log-uniform over the whole prior: p16 … p84 = 10^(−4+4·0.16) … 10^(−4+4·0.84)
    spread = q(10**-3.9, 10**-3.36, 1e-2, 10**-0.64, 10**-0.1)
    v = discrepancy_verdict(spread, [spec])
    assert v["status"] == "warning" and "whole prior" in v["reason"]
    low = q(1.01e-4, 1.2e-4, 2e-4, 5e-4, 1e-3)
    assert "no model error" in discrepancy_verdict(low, [spec])["reason"]
    v = discrepancy_verdict(q(0.18, 0.19, 0.2, 0.21, 0.22), [spec])
    assert v["status"] == "warning" and "compromise" in v["reason"]
    assert discrepancy_verdict(q(0.018, 0.019, 0.02, 0.021, 0.022), [spec])["status"] == "ok"


def test_energy_above_one_fails_and_below_passes() -> None:
    lam = models.get("lambert")
    # Lambert's albedo is kd exactly (∫ kd/π cos θ dω = kd).
    v = energy_verdict(lam, {"R": {"kd": 1.2}})
    assert v["status"] == "fail" and "1.2" in v["reason"], v
    assert energy_verdict(lam, {"R": {"kd": 0.9}})["status"] == "ok"
    ts = models.get("torrance-sparrow", **TS_MITSUBA)
    # kd + ks·(lobe albedo ≥ 0.92 for m = 0.3, docs/design.md §6) = 0.3 + 0.9·0.92 > 1.1 somewhere.
    v = energy_verdict(ts, {"G": {"kd": 0.3, "ks": 0.9, "m": 0.3}})
    assert v["status"] == "fail" and "(G," in v["reason"]
    assert energy_verdict(ts, {"G": {"kd": 0.3, "ks": 0.5, "m": 0.3}})["status"] == "ok"


def test_censoring_counts_and_treatment() -> None:
    assert censoring_verdict(0, 0, True, 100)["status"] == "ok"
    v = censoring_verdict(70, 3, True, 100)
    assert (
        v["status"] == "ok" and "70 DARK, 3 SATURATED" in v["reason"] and "censored" in v["reason"]
    )
    v = censoring_verdict(70, 3, False, 100)
    assert v["status"] == "warning" and "dropped" in v["reason"] and "--drop-flagged" in v["advice"]


def test_matched_model_with_a_long_chain_is_ok_everywhere() -> None:
    """Torrance-Sparrow as Mitsuba renders it, fitted to Mitsuba's own blend(diffuse,
    roughconductor) with honest σ, run on until R̂ < 1.01 and ESS ≥ 400: every verdict ok."""
    wi, wo = _grid()
    table, _ = direct_samples(BLEND, wi, wo, rel_sigma=0.02, floor_sr=1e-3, rng=2, channels="R")
    fit = fit_samples(
        table,
        FitOptions(
            model="torrance-sparrow",
            model_options=TS_MITSUBA,
            channels=["R"],
            mcmc=McmcOptions(walkers=32, max_steps=8000),
            seed=2,
        ),
    )
    verdicts = _verdicts(fit)
    assert tuple(verdicts) == VERDICT_NAMES
    assert all(v["status"] == "ok" for v in verdicts.values()), fit.verdicts
    assert fit.diagnostics["converged"] is True and fit.diagnostics["failed_criteria"] == []


def test_gonio_fit_prints_verdicts_and_exits_3_on_a_fail(tmp_path) -> None:
    """Through the real CLI: the verdict table, the flag counts, exit 3 on a fail with the fit
    still written, exit 0 with --accept-poor-fit, and --censor kept as a no-op alias."""
    import subprocess
    import sys

    from brdfdata.samples import Flags, write_samples

    wi, wo = _grid()
    table, _ = direct_samples(BLEND, wi, wo, rel_sigma=0.02, floor_sr=1e-3, rng=5, channels="R")
    table.flags = np.zeros(len(table), np.int32)
    table.flags[:7] = Flags.DARK
    table.flags[7:9] = Flags.SATURATED
    path = tmp_path / "samples.parquet"
    write_samples(path, table)

    def gonio(*args: str) -> subprocess.CompletedProcess:
        cmd = [sys.executable, "-m", "gonio.cli", "fit", str(path), "--model", "lambert"]
        return subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=300)

    res = gonio("--no-mcmc", "--out", str(tmp_path / "a"))
    assert res.returncode == 3, res.stdout + res.stderr
    assert (tmp_path / "a" / "fit-lambert.json").exists()  # nothing lost
    assert "7 DARK, 2 SATURATED of 280" in res.stdout and "censored" in res.stdout
    assert "chi2" in res.stdout and "fail" in res.stdout
    last = res.stdout.strip().splitlines()[-1]
    assert last.startswith("fit written, but it failed: chi2") and "--accept-poor-fit" in last
    res = gonio("--no-mcmc", "--accept-poor-fit", "--drop-flagged", "--out", str(tmp_path / "b"))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "dropped (--drop-flagged)" in res.stdout and "accepted" in res.stdout
    res = gonio("--no-mcmc", "--censor", "--accept-poor-fit", "--out", str(tmp_path / "c"))
    assert res.returncode == 0 and "--censor is the default now" in res.stdout
    res = gonio("--censor", "--drop-flagged")
    assert res.returncode == 2 and "contradict" in res.stderr

"""Fit orchestration and the fit-<model>.json contract (docs/design.md §4, issue 7)."""

from __future__ import annotations

import json

import emcee
import h5py
import numpy as np
import pytest

from brdfdata.samples import Flags, SampleTable
from fitting import models
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions
from fitting.priors import ParameterSpace
from fitting.result import FitResultError, read_fit

# The contract, copied from docs/design.md §4 (not imported from the code under test).
TOP = {
    "schema_version",
    "model",
    "options",
    "channels",
    "parameters",
    "diagnostics",
    "goodness",
    "n_samples",
    "wall_time_s",
}
PARAM = {"unit", "map", "median", "p16", "p84", "p2.5", "p97.5"}
DIAG = {"tau", "ess", "acceptance", "converged", "rhat", "stop_reason"}
GOOD = {"chi2", "dof", "chi2_red", "aic", "bic", "n"}
# Optional since issue 18 (readers accept files without them): the verdicts and what
# "converged" rests on.
OPTIONAL_TOP = {"verdicts"}
# budget: fitting.budget notes; mismatch: fitting.mismatch (widening, model error per region)
OPTIONAL_DIAG = {
    "converged_because",
    "failed_criteria",
    "budget",
    "mismatch",
    "precision",
    "ess_tail",
    "steps_needed",
}
VERDICT = {"name", "status", "reason", "advice"}


def lambert_table(rng, n=200, kd=None, mismatch=0.0, rel_noise=0.01) -> SampleTable:
    kd = kd or {"R": 0.6, "G": 0.4}
    parts = []
    for c, k in kd.items():
        ti = rng.uniform(0, 1.4, n)
        to = rng.uniform(0, 1.4, n)
        po = rng.uniform(0, 2 * np.pi, n)
        # Optional model mismatch: an azimuthal ripple the Lambert model cannot describe,
        # RMS fractional size mismatch/√2.
        f = k / np.pi * (1 + mismatch * np.cos(3 * po))
        s = rel_noise * f + 1e-4
        parts.append((ti, np.zeros(n), to, po, np.full(n, c), f + s * rng.standard_normal(n), s))
    cols = [np.concatenate([p[i] for p in parts]) for i in range(7)]
    return SampleTable(*cols, np.zeros(cols[0].size, np.int32))


def test_json_contract_and_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    table = lambert_table(rng)
    res = fit_samples(
        table,
        FitOptions(model="lambert", mcmc=McmcOptions(max_steps=600, walkers=16), seed=1),
        out_dir=tmp_path,
    )
    path = tmp_path / "fit-lambert.json"
    assert path.exists() and (tmp_path / "fit-lambert.h5").exists()
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text  # strict JSON
    d = json.loads(text)
    assert set(d) == TOP | OPTIONAL_TOP
    for v in d["verdicts"]:
        assert set(v) == VERDICT and v["status"] in ("ok", "warning", "fail")
    assert set(d["parameters"]) == {"kd_R", "kd_G", "discrepancy"}
    for p in d["parameters"].values():
        assert set(p) == PARAM
        assert p["p2.5"] <= p["p16"] <= p["median"] <= p["p84"] <= p["p97.5"]
    assert set(d["diagnostics"]) == DIAG | OPTIONAL_DIAG
    for key in ("tau", "ess", "rhat"):
        assert set(d["diagnostics"][key]) == set(d["parameters"])
    assert set(d["goodness"]) == GOOD
    # 1 % noise on 400 rows: float32's rounding (6e-8 of f) moves ln L by ~1e-4 ≪ 0.01, so the
    # MCMC evaluated the model in float32, and says so with what it measured
    precision = d["diagnostics"]["precision"]
    assert precision["mcmc"] == "float32" and precision["rounding_lnl"] < 0.01
    assert d["model"] == "lambert" and d["channels"] == ["R", "G"]
    assert d["n_samples"] == 400 and d["goodness"]["n"] == 400
    assert d["goodness"]["dof"] == 400 - 3
    # Natural units, not log: the discrepancy lies inside its prior [1e-4, 1].
    assert 1e-4 <= d["parameters"]["discrepancy"]["median"] <= 1
    # kd truth within 4 posterior sd (1% noise on 200 samples → sd ≈ 0.04%).
    for c, k in {"R": 0.6, "G": 0.4}.items():
        p = d["parameters"][f"kd_{c}"]
        assert abs(p["median"] - k) < 4 * (p["p84"] - p["p16"]) / 2
    # χ²/dof for a correct model with correct σ: 1 ± √(2/dof) ≈ 1 ± 0.07.
    assert abs(d["goodness"]["chi2_red"] - 1) < 0.3
    back = read_fit(path)
    assert back.to_dict() == d == res.to_dict()
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write left no temp file


def test_laplace_without_mcmc_and_discrepancy_reports_mismatch():
    rng = np.random.default_rng(1)
    table = lambert_table(rng, n=400, mismatch=0.2, rel_noise=0.001)
    res = fit_samples(
        table, FitOptions(model="lambert", mcmc=McmcOptions(max_steps=1500, walkers=16), seed=2)
    )
    # The fitted fractional discrepancy must report the 0.2/√2 ≈ 0.141 RMS mismatch; its
    # ML estimate has relative sd ≈ 1/√(2n) ≈ 2.5%, so ±15% is a wide but failing band.
    s = res.parameters["discrepancy"]["median"]
    assert s == pytest.approx(0.2 / np.sqrt(2), rel=0.15)
    lap = fit_samples(table, FitOptions(model="lambert", mcmc=None, discrepancy=False, seed=2))
    assert lap.diagnostics["stop_reason"] == "no_mcmc" and lap.diagnostics["converged"] is False
    p = lap.parameters["kd_R"]
    # Without the discrepancy term the Laplace interval is the overconfident one: far
    # narrower than with it (σ = 0.1% vs 14% scatter).
    q = res.parameters["kd_R"]
    assert (p["p84"] - p["p16"]) < 0.2 * (q["p84"] - q["p16"])
    # With the discrepancy on, the Laplace interval is inflated by χ²/dof and lands near the
    # MCMC one (both describe ~14% scatter per sample; weights differ slightly: factor 2).
    lap2 = fit_samples(table, FitOptions(model="lambert", mcmc=None, seed=2))
    w2 = lap2.parameters["kd_R"]["p84"] - lap2.parameters["kd_R"]["p16"]
    assert 0.5 < w2 / (q["p84"] - q["p16"]) < 2.0


def test_parameter_naming_shared_and_fixed():
    model = models.get("torrance-sparrow")  # default dielectric Fresnel: ior
    space = ParameterSpace.build(model, ["R", "G", "B"], shared=None, discrepancy=True)
    assert set(space.names) == {
        "kd_R",
        "kd_G",
        "kd_B",
        "ks_R",
        "ks_G",
        "ks_B",
        "m",
        "ior",
        "discrepancy",
    }
    space = ParameterSpace.build(model, ["R", "G"], shared=["m"], fix={"ior": 1.5, "kd_G": 0.1})
    # ior not shared here → per channel, and a bare-name fix holds it in every channel.
    assert set(space.names) == {"kd_R", "ks_R", "ks_G", "m"}
    assert "kd_G" not in space.names and space.fixed["kd_G"] == 0.1
    assert space.fixed["ior_R"] == 1.5 and space.fixed["ior_G"] == 1.5


def test_censored_and_student_t_fits_run():
    rng = np.random.default_rng(3)
    table = lambert_table(rng, n=150)
    flags = np.zeros(len(table), np.int32)
    # Saturate the brightest 5% at their reading: censored, the fit must stay unbiased.
    flags[np.argsort(table.f)[-15:]] = Flags.SATURATED
    table.flags = flags
    for kw in ({"censor": True}, {"likelihood": "student-t"}):
        res = fit_samples(
            table,
            FitOptions(model="lambert", mcmc=McmcOptions(max_steps=400, walkers=16), seed=4, **kw),
        )
        p = res.parameters["kd_R"]
        assert abs(p["median"] - 0.6) < 5 * (p["p84"] - p["p16"]) / 2, (kw, p)


def test_read_fit_errors(tmp_path):
    with pytest.raises(FitResultError, match="no such"):
        read_fit(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(FitResultError, match="not JSON"):
        read_fit(bad)
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"schema_version": 1, "model": "x"}))
    with pytest.raises(FitResultError, match="missing"):
        read_fit(partial)


def test_two_ensembles_rhat_and_time_budget(tmp_path):
    rng = np.random.default_rng(5)
    table = lambert_table(rng, n=100)
    res = fit_samples(
        table,
        FitOptions(
            model="lambert", mcmc=McmcOptions(max_steps=800, walkers=16), seed=6, ensembles=2
        ),
        out_dir=tmp_path,
    )
    d = res.to_dict()["diagnostics"]
    # Both ensembles sample the same posterior: the rank-normalised R̂ across them and their
    # halves in time ≈ 1 (fitting.convergence), and the chains are pooled (2 × 16 walkers).
    assert all(1 - 0.05 < r < 1.1 for r in d["rhat"].values()), d["rhat"]
    assert res.extras["mcmc"].chain.shape[1] == 32
    with h5py.File(tmp_path / "fit-lambert.h5") as h5:
        assert {"mcmc", "mcmc_1"} <= set(h5)
    quick = fit_samples(
        table,
        FitOptions(
            model="lambert",
            mcmc=McmcOptions(max_steps=100_000, walkers=16, time_budget_s=0.0),
            seed=6,
        ),
    )
    assert quick.diagnostics["stop_reason"] == "time_budget"
    assert quick.diagnostics["converged"] is False


def test_fit_resume_continues_only_the_same_problem(tmp_path):
    rng = np.random.default_rng(7)
    table = lambert_table(rng, n=80)
    base = FitOptions(
        model="lambert",
        mcmc=McmcOptions(walkers=16, moves="stretch"),
        seed=8,
    )
    fit_samples(table, base.with_mcmc(max_steps=200), out_dir=tmp_path)
    first = emcee.backends.HDFBackend(str(tmp_path / "fit-lambert.h5"), read_only=True)
    chain0 = first.get_chain()
    second = fit_samples(table, base.with_mcmc(max_steps=400), out_dir=tmp_path)
    after = emcee.backends.HDFBackend(str(tmp_path / "fit-lambert.h5"), read_only=True)
    assert after.iteration == second.extras["mcmc"].iterations == 400
    np.testing.assert_array_equal(after.get_chain()[:200], chain0)
    # Different data → different fingerprint → a fresh chain, not a continuation.
    other = lambert_table(np.random.default_rng(9), n=80)
    third = fit_samples(other, base.with_mcmc(max_steps=150), out_dir=tmp_path)
    assert third.extras["mcmc"].iterations == 150

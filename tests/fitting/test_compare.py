"""Model comparison (issue 7 §6): PSIS-LOO and WAIC against closed forms, the Pareto tail fit
against scipy's generalized Pareto, pointwise log-likelihoods against scipy densities, and
`gonio fit --model all` ranking on data rendered by Mitsuba's own BSDFs."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from scipy import stats

from brdfdata.samples import Flags, SampleTable
from fitting import models
from fitting.compare import (
    ModelScore,
    gpd_fit,
    margin_words,
    psis_loo,
    psis_smooth,
    rank,
    read_compare,
    waic,
)
from fitting.likelihood import Likelihood
from fitting.priors import ParameterSpace

GONIO = [sys.executable, "-m", "gonio.cli"]


@pytest.mark.parametrize("k", [0.1, 0.5, 0.9])
def test_gpd_fit_recovers_the_shape(k: float) -> None:
    # Independent sampler: scipy.stats.genpareto. The ML/Bayes estimator's SE is about
    # (1 + k)/√n ≈ 0.03 for n = 4000; 0.1 is > 3 SE.
    x = np.sort(stats.genpareto.rvs(k, scale=2.0, size=4000, random_state=11))
    k_hat, sigma = gpd_fit(x)
    assert abs(k_hat - k) < 0.1
    assert sigma == pytest.approx(2.0, rel=0.15)


def test_psis_khat_separates_light_and_heavy_tails() -> None:
    # Ratios drawn from a GPD: every tail above a threshold is again GPD with the same k
    # (threshold stability), so k̂ estimates k. PSIS uses M = 3√S = 425 tail draws, SE ≈
    # (1 + k)/√M ≤ 0.11: k = 0.1 and 1.2 sit > 3 SE on either side of the 0.5 / 0.7 limits.
    s = 20000
    light = np.log(stats.genpareto.rvs(0.1, size=(s, 1), random_state=1))
    heavy = np.log(stats.genpareto.rvs(1.2, size=(s, 1), random_state=2))
    lw, k = psis_smooth(np.hstack([light, heavy]))
    assert k[0] < 0.5 and k[1] > 0.7
    # Normalised log weights, and smoothing never raises a weight above the largest raw one.
    np.testing.assert_allclose(np.exp(lw).sum(axis=0), 1.0, rtol=1e-12)
    raw = np.hstack([light, heavy])
    raw_norm = raw - np.log(np.exp(raw - raw.max(0)).sum(0)) - raw.max(0)
    assert np.all(lw.max(axis=0) <= raw_norm.max(axis=0) + 1e-9)


def test_psis_loo_and_waic_match_exact_loo_of_a_conjugate_normal_model() -> None:
    """y_j ~ N(μ, 1), flat prior: posterior μ ~ N(ȳ, 1/n); exact LOO predictive
    p(y_j | y_−j) = N(y_j; ȳ_−j, √(1 + 1/(n−1))), exact lppd_j = ln N(y_j; ȳ, √(1 + 1/n))."""
    rng = np.random.default_rng(5)
    n, s = 20, 4000
    y = rng.normal(0.3, 1.0, n)
    mu = rng.normal(y.mean(), 1 / math.sqrt(n), s)
    ll = stats.norm.logpdf(y[None, :], mu[:, None], 1.0)
    y_minus = (y.sum() - y) / (n - 1)
    exact_loo = stats.norm.logpdf(y, y_minus, math.sqrt(1 + 1 / (n - 1))).sum()
    exact_lppd = stats.norm.logpdf(y, y.mean(), math.sqrt(1 + 1 / n)).sum()
    lo = psis_loo(ll)
    w = waic(ll)
    # Monte-Carlo error of either estimate over 4000 draws: SD 0.017 nats across 20 seeds
    # (measured on fresh seeds, not this one); 0.1 is 6 SD.
    assert lo["elpd"] == pytest.approx(exact_loo, abs=0.1)
    assert lo["p"] == pytest.approx(exact_lppd - exact_loo, abs=0.1)
    assert w["elpd"] == pytest.approx(exact_loo, abs=0.1)
    assert w["waic"] == pytest.approx(-2 * w["elpd"])
    assert lo["khat_max"] < 0.5  # one well-identified mean: light-tailed ratios
    # SE = √(n Var_j elpd_j) (Vehtari et al. 2017 eq. 23), from the pointwise values.
    assert lo["se"] == pytest.approx(math.sqrt(n * np.var(lo["pointwise"], ddof=1)))


def _table(rng, n=60) -> SampleTable:
    ti, to = rng.uniform(0.1, 1.2, n), rng.uniform(0.1, 1.2, n)
    flags = np.zeros(n, np.int32)
    flags[:5] = Flags.SATURATED
    flags[5:9] = Flags.DARK
    return SampleTable(
        theta_i=ti,
        phi_i=np.zeros(n),
        theta_o=to,
        phi_o=rng.uniform(0, 2 * np.pi, n),
        channel=np.where(np.arange(n) % 2 == 0, "R", "G").astype(str),
        f=rng.uniform(0.05, 0.3, n),
        sigma=rng.uniform(0.005, 0.02, n),
        flags=flags,
    )


@pytest.mark.parametrize("kind", ["gaussian", "student-t"])
@pytest.mark.parametrize("censor", [False, True])
def test_pointwise_log_likelihood_matches_scipy(kind: str, censor: bool) -> None:
    rng = np.random.default_rng(2)
    table = _table(rng)
    model = models.get("lambert")
    space = ParameterSpace.build(model, ["R", "G"], discrepancy=True)
    lik = Likelihood(model, table, space, kind=kind, nu=3.0, censor=censor)
    theta = np.column_stack([rng.uniform(0.2, 0.8, (4, 2)), np.log(rng.uniform(0.01, 0.2, 4))])
    pw = lik.pointwise_log_likelihood(theta)
    assert pw.shape == (4, lik.n)
    # The summing code path (a separate implementation, incl. the fast Gaussian one).
    np.testing.assert_allclose(pw.sum(axis=1), lik.log_likelihood(theta), rtol=1e-12)
    # Per sample against scipy, channel by channel in Likelihood.data order.
    s = np.exp(theta[:, 2])
    col = 0
    for d, kd in zip(lik.data, (theta[:, 0], theta[:, 1]), strict=True):
        fhat = kd[:, None] / np.pi * np.ones(d.f.size)
        sd = np.sqrt(d.sigma**2 + (s[:, None] * fhat) ** 2)
        if kind == "gaussian":
            want = stats.norm.logpdf(d.f, fhat, sd)
        else:
            want = stats.t.logpdf(d.f, 3.0, fhat, sd)
        want = np.where(d.kind == 1, stats.norm.logsf(d.f, fhat, sd), want)
        want = np.where(d.kind == 2, stats.norm.logcdf(d.f, fhat, sd), want)
        np.testing.assert_allclose(pw[:, col : col + d.f.size], want, rtol=1e-10)
        col += d.f.size
    assert (lik.data[0].kind != 0).any() == censor


def _score(label: str, pointwise: np.ndarray) -> ModelScore:
    nan = float("nan")
    return ModelScore(
        label, label, {}, [], 1, pointwise.size, float(pointwise.sum()), nan, nan, nan, nan,
        0, nan, nan, nan, nan, nan, nan, pointwise=pointwise,
    )  # fmt: skip


def test_rank_orders_by_elpd_and_gives_the_se_of_the_difference() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(-1.0, 0.3, 50)
    b = a - rng.normal(0.1, 0.05, 50)  # worse by 0.1 nats per sample
    ranked = rank([_score("b", b), _score("a", a)])
    assert [r.label for r in ranked] == ["a", "b"] and [r.rank for r in ranked] == [1, 2]
    assert ranked[1].d_elpd == pytest.approx(b.sum() - a.sum())
    assert ranked[1].d_se == pytest.approx(math.sqrt(50 * np.var(b - a, ddof=1)))
    assert ranked[0].d_elpd == 0.0


def test_an_unreliable_score_is_listed_unranked_and_margins_are_said_in_words() -> None:
    rng = np.random.default_rng(1)
    a = rng.normal(-1.0, 0.3, 50)
    jitter = rng.normal(0.0, 0.05, 50)
    jitter -= jitter.mean()
    close = a - 0.002 - jitter  # 0.1 nats worse in all, SE(Δ) = √50 · 0.05 ≈ 0.35: within 2 SE
    far = a - 0.5 - jitter  # 25 nats worse, the same SE: separated
    bad = _score("bad", a + 10.0)  # the highest elpd, but its PSIS-LOO is unreliable
    bad.why_unranked = "its PSIS-LOO is unreliable: Pareto k̂ > 0.7 at 3 of 50 samples"
    ranked = rank([bad, _score("far", far), _score("a", a), _score("close", close)])
    assert [(r.label, r.rank) for r in ranked] == [
        ("a", 1),
        ("close", 2),
        ("far", 3),
        ("bad", None),
    ]
    assert math.isnan(ranked[3].d_elpd) and math.isnan(ranked[3].d_se)
    assert "not separated" in margin_words(ranked[0], ranked[1])
    assert "a predicts better than far by 25" in margin_words(ranked[0], ranked[2])
    # nothing reliable: nothing is ranked, and compare.json says rank null
    only = rank([bad])
    assert only[0].rank is None and only[0].to_dict()["rank"] is None


def _mitsuba_samples(path: Path, alphas=(0.15, 0.15, 0.15)) -> Path:
    """f from Mitsuba's blendbsdf(diffuse, Beckmann roughconductor) eval, 1% noise, R,G,B;
    channel c from a blend whose roughconductor has alpha ``alphas[c]``."""
    import mitsuba as mi

    from simulator.variant import ensure_variant

    ensure_variant()
    rng = np.random.default_rng(4)
    n = 150
    ti, to = rng.uniform(0.05, 1.2, n), rng.uniform(0.05, 1.2, n)
    dphi = np.where(rng.uniform(size=n) < 0.6, np.pi + rng.normal(0, 0.3, n), rng.uniform(0, 6, n))
    wi = np.stack([np.sin(ti), np.zeros(n), np.cos(ti)], 1)
    wo = np.stack([np.sin(to) * np.cos(dphi), np.sin(to) * np.sin(dphi), np.cos(to)], 1)
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2])
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    cols = {k: [] for k in ("theta_i", "phi_i", "theta_o", "phi_o", "channel", "f", "sigma")}
    for c, ch in enumerate("RGB"):
        bsdf = mi.load_dict(
            {
                "type": "blendbsdf",
                "weight": 0.3,
                "a": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.4, 0.2]}},
                "b": {"type": "roughconductor", "distribution": "beckmann", "alpha": alphas[c],
                      "material": "none"},
            }
        )  # fmt: skip
        v = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2]))
        f = np.asarray(v[c], dtype=np.float64) / wi[:, 2]
        sigma = 0.01 * f + 1e-4
        cols["theta_i"] += list(ti)
        cols["phi_i"] += [0.0] * n
        cols["theta_o"] += list(to)
        cols["phi_o"] += list(np.mod(dphi, 2 * np.pi))
        cols["channel"] += [ch] * n
        cols["f"] += list(f + rng.normal(0, 1, n) * sigma)
        cols["sigma"] += list(sigma)
    pq.write_table(pa.table(cols), path)
    return path


def test_fit_several_models_ranks_the_generating_model_first(tmp_path: Path) -> None:
    samples = _mitsuba_samples(tmp_path / "s.parquet")
    # One priors file for every model: names a model lacks (m for Phong, n for TS) are dropped.
    priors = tmp_path / "priors.toml"
    priors.write_text("[parameters.m]\nupper = 0.8\n[parameters.n]\nlower = 1.5\n")
    res = subprocess.run(
        [*GONIO, "fit", str(samples), "--model", "lambert,phong,phong-normalized,blinn-phong,ts",
         "--no-mcmc", "--compare-shared",
         "--option", "shadowing=smith-rational", "--option", "fresnel=none",
         "--priors", str(priors)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    assert "Model comparison" in res.stdout and "ΔELPD" in res.stdout
    doc = json.loads((tmp_path / "compare.json").read_text())
    rows = doc["models"]
    labels = [r["label"] for r in rows]
    assert set(labels) >= {"lambert", "phong", "phong-normalized", "blinn-phong"}
    assert {"torrance-sparrow", "torrance-sparrow-per-channel"} <= set(labels)
    # The generating family wins (shared or per-channel m: same data, both nest the truth)
    # by many SE over every Phong-type lobe; Lambert comes last.
    assert labels[0].startswith("torrance-sparrow") and labels[1].startswith("torrance-sparrow")
    third = rows[2]
    assert third["d_elpd"] < -5 * third["d_se"]
    assert labels[-1] == "lambert"
    for r in rows:  # AIC/BIC are copied from each fit's JSON goodness
        fit_json = tmp_path / (
            f"fit-{r['label']}.json"
            if r["label"] == r["model"]
            else f"{r['label']}/fit-{r['model']}.json"
        )
        good = json.loads(fit_json.read_text())["goodness"]
        assert r["aic"] == pytest.approx(good["aic"]) and r["bic"] == pytest.approx(good["bic"])
        assert (tmp_path / f"material-{r['label']}.xml").exists()


def test_per_channel_roughness_wins_when_channels_differ(tmp_path: Path) -> None:
    """Mitsuba data whose R, G, B lobes have m = 0.1, 0.15, 0.2: the per-channel-m fit must
    beat the shared-m fit by many SE of the pointwise ELPD difference."""
    from brdfdata.samples import read_samples
    from fitting.compare import candidates, run_comparison
    from fitting.fit import FitOptions

    table = read_samples(_mitsuba_samples(tmp_path / "s.parquet", alphas=(0.1, 0.15, 0.2)))
    opts = {"shadowing": "smith-rational", "fresnel": "none"}
    cands, _ = candidates("torrance-sparrow", opts, ("m",), compare_shared=True)
    base = FitOptions(mcmc=None, n_starts=2)
    ranked, results = run_comparison(table, cands, base, out_dir=tmp_path)
    assert [r.label for r in ranked] == ["torrance-sparrow-per-channel", "torrance-sparrow"]
    assert ranked[1].d_elpd < -5 * ranked[1].d_se
    assert ranked[0].shared == [] and ranked[1].shared == ["m"]
    per = results["torrance-sparrow-per-channel"]
    for ch, m in zip("RGB", (0.1, 0.15, 0.2), strict=True):
        assert per.value(f"m_{ch}", "map") == pytest.approx(m, rel=0.02)
    assert json.loads((tmp_path / "compare.json").read_text())["criterion"] == "elpd_loo"


def _one_line(res: subprocess.CompletedProcess) -> str:
    assert res.returncode != 0 and "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    return lines[0]


def test_fit_bad_likelihood_and_priors_are_one_line(tmp_path: Path) -> None:
    p = tmp_path / "t.parquet"
    pq.write_table(
        pa.table({"theta_i": [0.3] * 4, "phi_i": [0.0] * 4, "theta_o": [0.1, 0.2, 0.3, 0.4],
                  "phi_o": [3.1] * 4, "channel": ["R"] * 4, "f": [0.1] * 4,
                  "sigma": [0.01] * 4}),
        p,
    )  # fmt: skip
    run = lambda *a: subprocess.run([*GONIO, "fit", str(p), *a], capture_output=True, text=True)  # noqa: E731
    assert "--likelihood" in _one_line(run("--likelihood", "cauchy"))
    assert "nope.toml" in _one_line(run("--priors", str(tmp_path / "nope.toml")))
    assert "not a parameter of lambert" in _one_line(run("--model", "lambert", "--shared", "kd,x"))
    assert "give it alone" in _one_line(run("--model", "lambert,all"))
    assert "unknown model 'nope'" in _one_line(run("--model", "lambert,nope"))


def test_a_comparison_whose_loo_fails_ranks_nothing_and_says_why(tmp_path: Path) -> None:
    """Samples of Mitsuba's own BSDF with three gross outliers (30× f at a σ of 2 %): under the
    Gaussian likelihood every fit's PSIS-LOO has Pareto k̂ far above 0.7 (measured: lambert
    max 15 at 19 samples, phong max 4 at 143), so no elpd is an estimate and nothing may be
    ranked — the command says so per model and exits 3; --accept-poor-fit accepts it."""
    from brdfdata.directions import grid_direction_pairs
    from brdfdata.samples import write_samples
    from simulator.scene import BlendMaterial, DiffuseMaterial, RoughConductorMaterial
    from simulator.truth import direct_samples

    wi, wo = grid_direction_pairs([10, 30, 50, 70], np.arange(2, 81, 6), [180, 150, 110, 60, 0])
    blend = BlendMaterial(
        weight=0.25,
        first=DiffuseMaterial(reflectance=(0.6, 0.4, 0.2)),
        second=RoughConductorMaterial(alpha=0.2, conductor="none"),
    )
    table, _ = direct_samples(blend, wi, wo, rel_sigma=0.02, floor_sr=1e-3, rng=5, channels="R")
    table.f = table.f.copy()
    table.f[[5, 77, 150]] *= 30.0
    path = tmp_path / "samples.parquet"
    write_samples(path, table)

    def fit(*args: str) -> subprocess.CompletedProcess:
        cmd = [*GONIO, "fit", str(path), "--model", "lambert,phong", "--no-mcmc", *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=300)

    res = fit("--out", str(tmp_path / "a"))
    assert res.returncode == 3, res.stdout + res.stderr
    out = " ".join(res.stdout.split())  # rich wraps long lines on a narrow pipe
    for name in ("lambert", "phong"):
        assert f"not ranked: {name}: its PSIS-LOO is unreliable: Pareto k̂ > 0.7 at" in out
    assert "no model could be ranked" in out
    rows, skipped = read_compare(tmp_path / "a" / "compare.json")
    assert [r["rank"] for r in rows] == [None, None] and skipped == []
    assert all(r["why_unranked"] and r["d_elpd"] is None for r in rows)
    res = fit("--out", str(tmp_path / "b"), "--accept-poor-fit")
    assert res.returncode == 0 and "accepted (--accept-poor-fit)" in res.stdout, res.stdout

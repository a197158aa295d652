"""Binned samples (fitting.binning, issue 22 "bounded cost"): what binning changes in the
posterior, measured against the unbinned fit of the same data.

The data are Mitsuba's own blend of diffuse and roughconductor (Cu, α = 0.15) at a camera-like
footprint: every pose of the isotropic plan seen by PIXELS pixels whose directions scatter 0.1°
(r.m.s.) around the pose, as the pixels of a camera image of a small sample do. Ground truth is
Mitsuba's BSDF; the comparison is binned against unbinned fit of the same rows, so the model is
not its own judge.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from brdfdata.directions import isotropic_gonio_directions, normalize
from brdfdata.samples import Flags, SampleTable, write_samples
from fitting import models
from fitting.binning import BinOptions, bin_table, binning_bias, read_binned
from fitting.fit import FitOptions, fit_samples
from fitting.likelihood import Likelihood
from fitting.lsq import fit_least_squares
from fitting.priors import ParameterSpace
from simulator.scene import BlendMaterial, DiffuseMaterial, RoughConductorMaterial
from simulator.truth import direct_samples, material_reference_parameters, mitsuba_brdf

OPTIONS = {"distribution": "beckmann", "shadowing": "smith-rational", "fresnel": "conductor"}
PIXELS = 60
SPREAD_RAD = np.radians(0.1)
WIDTH_DEG = 0.2


def _jitter(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Unit vectors scattered by SPREAD_RAD (r.m.s. per tangent axis) around ``w``."""
    return normalize(w + rng.normal(0.0, SPREAD_RAD, w.shape))


@pytest.fixture(scope="module")
def camera_like():
    # A diffuse part keeps every kd off its bound 0, where a linearised shift would not apply.
    mat = BlendMaterial(
        weight=0.4,
        first=DiffuseMaterial(reflectance=(0.6, 0.45, 0.3)),
        second=RoughConductorMaterial(alpha=0.15, conductor="Cu"),
    )
    truth = material_reference_parameters(mat)
    wi0, wo0 = isotropic_gonio_directions()
    rng = np.random.default_rng(7)
    wi = _jitter(np.repeat(wi0, PIXELS, axis=0), rng)
    wo = _jitter(np.repeat(wo0, PIXELS, axis=0), rng)
    keep = (wi[:, 2] > 0.05) & (wo[:, 2] > 0.05)
    table, _ = direct_samples(mat, wi[keep], wo[keep], rel_sigma=0.02, floor_sr=1e-3, rng=8)
    # Rows whose noise made f < 0 (far from the lobe) are refused unflagged by the samples
    # guards when the table is read from a file; both fits here use the same rows without them.
    return mat, truth, table.select(table.f >= 0)


def _lsq(table: SampleTable, truth: dict):
    model = models.get("torrance-sparrow", **OPTIONS)
    fix = {k: v for k, v in truth.items() if k.startswith(("eta_", "k_"))}
    space = ParameterSpace.build(model, ["R", "G", "B"], shared=["m"], fix=fix)
    lik = Likelihood(model, table, space, channels=["R", "G", "B"])
    res = fit_least_squares(lik, n_starts=2, seed=0, loss="linear")
    sd = np.sqrt(np.diag(res.cov))
    return space, lik, res.x, sd


def test_binning_moves_the_posterior_by_less_than_its_curvature_bound(tmp_path, camera_like):
    mat, truth, table = camera_like
    binned, key = bin_table(table, BinOptions(width_deg=WIDTH_DEG), members=True)
    assert np.all(key >= 0)
    assert len(binned) < len(table) / 2, (len(binned), len(table))

    # The bound of fitting.binning: an estimate moves by at most ‖ε/σ̄‖₂ posterior sds, with
    # ε_b = Σw f(ω_j)/Σw − f(ω̄_b) the BRDF's curvature over bin b — here from Mitsuba's BSDF
    # at the member rows and at the bin's mean direction …
    w = 1.0 / table.sigma**2
    f_true = _truth_per_row(mat, table)
    mean_truth = np.bincount(key, w * f_true, len(binned)) / np.bincount(key, w, len(binned))
    bound = float(np.sqrt(np.sum(((mean_truth - _truth_per_row(mat, binned)) / binned.sigma) ** 2)))
    # … and the same bound from the streamed second pass the fit runs (fitting.binning).
    path = write_samples(tmp_path / "s.parquet", table)
    streamed, _ = read_binned(path, BinOptions(width_deg=WIDTH_DEG, batch_rows=4099))
    eps = binning_bias(path, streamed, lambda t: _truth_per_row(mat, t))
    np.testing.assert_allclose(np.linalg.norm(eps), bound, rtol=1e-6)  # sums in another order
    assert 0 < bound, bound

    _, _, x_all, sd_all = _lsq(table, truth)
    space, _, x_bin, sd_bin = _lsq(streamed, truth)
    shift = (x_bin - x_all) / sd_all
    # The optimum moves by at most the bound (the model equals Mitsuba's BSDF to ~1e-5, and
    # the optimiser's tolerance, 1e-8 relative in x, is far below 0.01 sd here).
    assert np.all(np.abs(shift) <= bound + 0.01), (
        dict(zip(space.names, shift, strict=True)),
        bound,
    )
    # The fit measures the same bound itself (second pass, with its model at its optimum:
    # the model equals Mitsuba's BSDF, so to a few per cent of the bound).
    fix = {k: v for k, v in truth.items() if k.startswith(("eta_", "k_"))}
    fit = fit_samples(
        streamed,
        FitOptions(
            model="torrance-sparrow",
            model_options=OPTIONS,
            shared=["m"],
            fix=fix,
            mcmc=None,
            discrepancy=False,
            n_starts=2,
            loss="linear",  # the Gaussian optimum, as the unbinned fits above
            binned_source=path,
        ),
    )
    info = fit.diagnostics["binning"]
    np.testing.assert_allclose(info["uncorrected_bound_sd"], bound, rtol=0.05)
    assert [v["name"] for v in fit.verdicts][-1] == "binning"
    # Its linearised shift of each parameter predicts the measured one. Besides the bias the
    # two estimates differ by noise: binning drops the information in the model's variation
    # within a bin, and the difference of an efficient estimator (every row) and a less
    # efficient one (the bins) has variance sd_bin² − sd_all² (Hausman 1978, Lemma 2.1); so
    # measured − predicted is within 4 of its sds (seven parameters at once), plus 0.01 sd for
    # the linearisation (second order in the 0.14 sd shift) and the optimiser's tolerance.
    predicted = info["uncorrected_shift_sd"]
    noise = np.sqrt(np.abs(sd_bin**2 / sd_all**2 - 1.0))
    for j, name in enumerate(space.names):
        assert abs(shift[j] - predicted[name]) <= 4 * noise[j] + 0.01, (
            name,
            shift[j],
            predicted[name],
            noise[j],
        )
    # The fit removes that bias (each bin's mean corrected by the model's curvature over the
    # bin): its optimum equals the unbinned one to the same tolerance, and the shift it still
    # reports is below the linearisation's 0.01 sd.
    lik = fit.extras["likelihood"]
    x_fit = lik.space.to_internal(np.array([fit.parameters[n]["map"] for n in lik.space.names]))
    corrected = (x_fit - x_all) / sd_all
    assert np.all(np.abs(corrected) <= 4 * noise + 0.01), dict(
        zip(space.names, corrected, strict=True)
    )
    assert info["corrected"] and info["max_shift_sd"] <= 0.01, info
    assert np.max(np.abs(shift)) > 0.1  # … where the uncorrected bins moved m by > 0.1 sd
    # Combining a bin's rows with inverse-variance weights keeps their Fisher information
    # exactly at one geometry; across the 0.1° footprint J varies to second order in
    # (0.1°/α ≈ 0.012)², so the sds agree to far better than 2 %.
    np.testing.assert_allclose(sd_bin, sd_all, rtol=0.02)


def _truth_per_row(mat, table: SampleTable) -> np.ndarray:
    f = mitsuba_brdf(mat, table.wi, table.wo, None)
    return f[np.arange(len(table)), ["RGB".index(c) for c in table.channel]]


def _repeated_table() -> SampleTable:
    """12 geometries × 5 repeats (distinct captures), exact, saturated and dark rows, one σ per
    geometry: binning such a table replaces each repeat group exactly."""
    rng = np.random.default_rng(3)
    ti, to = rng.uniform(0.2, 1.2, 12), rng.uniform(0.2, 1.2, 12)
    po = rng.uniform(-3, 3, 12)
    rep = 5
    flags = np.repeat(
        np.array([0, 0, 0, 0, 0, 0, 0, 0, Flags.DARK, Flags.DARK, Flags.SATURATED, 0]), rep
    )
    f = np.repeat(rng.uniform(0.05, 0.3, 12), rep) * rng.uniform(0.9, 1.1, 12 * rep)
    sigma = np.repeat(rng.uniform(0.005, 0.02, 12), rep)
    dark = flags == Flags.DARK
    f[dark] = 0.0  # read below the detection limit: the bound is 3σ for every repeat
    sat = flags == Flags.SATURATED
    f[sat] = np.repeat(0.25, sat.sum())  # the clip level
    return SampleTable(
        theta_i=np.repeat(ti, rep),
        phi_i=np.zeros(12 * rep),
        theta_o=np.repeat(to, rep),
        phi_o=np.repeat(po, rep),
        channel=np.repeat(np.array(["G"]), 12 * rep),
        f=f,
        sigma=sigma,
        flags=flags.astype(np.int32),
        extra={"capture_id": np.tile(np.arange(rep), 12)},
    )


def test_binned_likelihood_equals_the_rows_likelihood_up_to_a_constant():
    """Exact rows: the inverse-variance merge; censored rows: one bound carrying its count. With
    every repeat at one geometry the two log-likelihoods differ by a constant (the Gaussian
    normalisation) — to rounding, at any parameters."""
    table = _repeated_table()
    binned = bin_table(table, BinOptions(width_deg=0.05))
    assert len(binned) == 12 and set(binned.extra["n_rows"].tolist()) == {5}
    model = models.get("torrance-sparrow", **OPTIONS)
    space = ParameterSpace.build(model, ["G"], shared=["m"])
    rng = np.random.default_rng(4)
    lo, hi = space.bounds
    theta = lo + (hi - lo) * rng.uniform(0.2, 0.8, (6, space.ndim))
    rows = Likelihood(model, table, space, channels=["G"]).log_likelihood(theta)
    bins = Likelihood(model, binned, space, channels=["G"]).log_likelihood(theta)
    diff = rows - bins
    # ln L values are O(10³) here; float64 sums agree to ~1e-12 of that.
    np.testing.assert_allclose(diff - diff[0], 0.0, atol=1e-8)
    # Without the counts the censored rows would count once instead of five times:
    unweighted = bin_table(table, BinOptions(width_deg=0.05))
    unweighted.extra.pop("n_rows")
    no_counts = Likelihood(model, unweighted, space, channels=["G"]).log_likelihood(theta)
    assert np.ptp((rows - no_counts) - (rows - no_counts)[0]) > 1e-3


def test_streamed_binning_equals_binning_in_memory(tmp_path, camera_like):
    """Read in batches of 997 rows (many partial bins merged across batches), the file bins
    exactly as the whole table does."""
    _, _, table = camera_like
    path = write_samples(tmp_path / "s.parquet", table)
    whole = bin_table(table, BinOptions(width_deg=WIDTH_DEG))
    streamed, report = read_binned(path, BinOptions(width_deg=WIDTH_DEG, batch_rows=997))
    assert report.rows == len(table) and report.bins == len(whole)
    order_a = np.lexsort((whole.theta_o, whole.theta_i, whole.channel))
    order_b = np.lexsort((streamed.theta_o, streamed.theta_i, streamed.channel))
    for name in ("f", "sigma", "theta_i", "phi_i", "theta_o", "phi_o"):
        # Sums in another order: equal to a few ulps.
        np.testing.assert_allclose(
            getattr(streamed, name)[order_b], getattr(whole, name)[order_a], rtol=1e-12, atol=1e-14
        )
    assert streamed.source_sha256 is not None


def test_a_bad_row_in_a_later_batch_is_refused_like_a_whole_read(tmp_path, camera_like):
    _, _, table = camera_like
    bad = table.select(np.ones(len(table), bool))
    bad.f[len(bad) - 3] = np.nan
    path = write_samples(tmp_path / "s.parquet", bad)
    with pytest.raises(Exception, match="NaN or inf in f") as info:
        read_binned(path, BinOptions(width_deg=WIDTH_DEG, batch_rows=1000))
    assert "\n" not in str(info.value)


def test_gonio_fit_bins_on_request_and_refuses_a_bad_width(tmp_path, camera_like):
    """The command line: --bin DEG bins (one line says how), the fit JSON records it with its
    verdict; a negative or too small width is one line, exit 2, nothing written."""
    _, _, table = camera_like
    path = write_samples(tmp_path / "s.parquet", table)

    def fit(*extra: str) -> subprocess.CompletedProcess:
        args = ["fit", str(path), "--model", "lambert", "--no-mcmc", "--accept-poor-fit"]
        return subprocess.run(
            [sys.executable, "-m", "gonio.cli", *args, *extra],
            capture_output=True,
            text=True,
            timeout=600,
        )

    for width in ("-1", "0.001"):
        bad = fit("--bin", width, "--out", str(tmp_path / "bad"))
        assert bad.returncode == 2 and bad.stderr.startswith("error: "), bad.stderr
        assert len(bad.stderr.strip().splitlines()) == 1 and not (tmp_path / "bad").exists()
    good = fit("--bin", "0.2", "--out", str(tmp_path / "fit"))
    assert good.returncode == 0, good.stderr
    assert f"binned {len(table):,} rows into" in good.stdout.replace("\n", " ")
    doc = json.loads((tmp_path / "fit" / "fit-lambert.json").read_text())
    info = doc["diagnostics"]["binning"]
    assert info["rows"] == len(table) and info["corrected"] and doc["n_samples"] == info["bins"]
    assert [v["name"] for v in doc["verdicts"]][-1] == "binning"


def test_a_binned_fit_of_merged_duplicates_rereads_the_file_without_refusing_it(tmp_path):
    """The fit's second and third passes reread rows the first pass validated: a file read with
    --merge-duplicates (repeated rows, no capture_id) is not refused there as a duplicate, and a
    file changed between the passes is refused in one line."""
    table = _repeated_table()
    table.extra = {}  # the repeats are now duplicated rows, accepted only when merged
    path = write_samples(tmp_path / "dup.parquet", table)
    binned, _ = read_binned(path, BinOptions(width_deg=0.05), merge_duplicates=True)
    opts = FitOptions(model="lambert", mcmc=None, n_starts=1, binned_source=path)
    fit = fit_samples(binned, opts)
    assert fit.diagnostics["binning"]["corrected"]
    write_samples(path, table.select(np.arange(len(table)) > 0))  # another file, same path
    with pytest.raises(Exception, match="changed while it was being fitted"):
        fit_samples(binned, opts)

"""`gonio report --samples S --fit F.json [--out report.html]`: a report for a fit that did not
come from a run (issue 16, item 3) — here an RGL file imported with `gonio import rgl`."""

from __future__ import annotations

import sys

import pytest
from conftest import data_file


def _run(monkeypatch, capsys, *args):
    from gonio import cli

    monkeypatch.setattr(sys, "argv", ["gonio", *map(str, args)])
    try:
        cli.main()
        code = 0
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr()


@pytest.fixture(scope="module")
def imported_fit(tmp_path_factory):
    """An RGL material imported on a coarse grid and fitted with a short MCMC chain."""
    from brdfdata.formats.convert import ImportOptions, import_samples
    from brdfdata.samples import write_samples
    from fitting.fit import FitOptions, fit_samples
    from fitting.mcmc import McmcOptions

    tmp = tmp_path_factory.mktemp("fitreport")
    grid = "theta_i=10:70:20,theta_o=0:80:10,phi_o=0:180:30"
    table = import_samples(
        "rgl", data_file("rgl_brdf/colodur_napoli_4f_rgb.bsdf"), ImportOptions(grid=grid)
    )
    samples = write_samples(tmp / "samples.parquet", table)
    fit_samples(
        table,
        FitOptions(model="lambert", mcmc=McmcOptions(max_steps=120, walkers=8), seed=0),
        out_dir=tmp,
    )
    return samples, tmp / "fit-lambert.json"


def test_report_of_any_fit(imported_fit, tmp_path, monkeypatch, capsys) -> None:
    samples, fit = imported_fit
    out = tmp_path / "r.html"
    code, io = _run(monkeypatch, capsys, "report", "--samples", samples, "--fit", fit, "--out", out)
    assert code == 0, io.err
    assert io.out.strip().endswith("r.html")
    page = out.read_text()
    assert "<h2>Fit: lambert" in page and "kd_R" in page and "Trace plots" in page
    assert "imported from format: rgl" in page and "colodur_napoli_4f_rgb.bsdf" in page
    assert page.count("data:image/png;base64,") >= 4  # slices, residuals, traces, marginals


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--fit", "{fit}"], "give RUN_DIR, or --samples"),
        (["{run}", "--samples", "{samples}", "--fit", "{fit}"], "give RUN_DIR, or --samples"),
        (["--samples", "{samples}", "--fit", "{samples}"], "cannot read"),
    ],
)
def test_wrong_use_is_one_line(args, fragment, imported_fit, tmp_path, monkeypatch, capsys):
    samples, fit = imported_fit
    filled = [a.format(fit=fit, samples=samples, run=tmp_path) for a in args]
    code, io = _run(monkeypatch, capsys, "report", *filled)
    lines = [ln for ln in io.err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and fragment in lines[0], io.err


def test_fit_of_other_samples_is_refused(imported_fit, tmp_path) -> None:
    from brdfdata.formats.convert import ImportOptions, import_samples
    from brdfdata.samples import write_samples
    from gonio.errors import UserError
    from gonio.report import write_fit_report

    _, fit = imported_fit
    other = import_samples(
        "csv", _one_channel_csv(tmp_path), ImportOptions(sigma="rel=0.05", default_channel="Y")
    )
    path = write_samples(tmp_path / "y.parquet", other)
    with pytest.raises(UserError, match="fitted channel"):
        write_fit_report(path, fit)


def _one_channel_csv(tmp_path):
    p = tmp_path / "y.csv"
    p.write_text("theta_i,phi_i,theta_o,phi_o,f\n0.1,0,0.2,3.1,0.2\n0.3,0,0.4,3.1,0.21\n")
    return p


def test_report_refuses_samples_the_fit_was_not_made_from(imported_fit, tmp_path) -> None:
    """Issue 22, item 2: the fit records its samples file's SHA-256, and a report of it over a
    recalibrated table (same channels and shape, one value changed) is refused in one line;
    the file it was made from is accepted. On the previous code both were reported."""
    import dataclasses

    from brdfdata.samples import read_samples, write_samples
    from fitting.fit import FitOptions, fit_samples
    from fitting.result import FitResultError, read_fit
    from gonio.report import write_fit_report
    from plumbing.hashing import sha256_file

    samples, _ = imported_fit
    table = read_samples(samples)
    assert table.source_sha256 == sha256_file(samples)
    fit_samples(table, FitOptions(model="lambert", mcmc=None, seed=0), out_dir=tmp_path)
    fit = tmp_path / "fit-lambert.json"
    assert read_fit(fit).samples_sha256 == sha256_file(samples)
    write_fit_report(samples, fit, tmp_path / "same.html")  # the samples it was made from
    f = table.f.copy()
    f[0] *= 1.01
    changed = write_samples(tmp_path / "recalibrated.parquet", dataclasses.replace(table, f=f))
    with pytest.raises(FitResultError, match="was fitted to a samples file with SHA-256") as e:
        write_fit_report(changed, fit, tmp_path / "other.html")
    assert "\n" not in str(e.value) and "recalibrated.parquet" in str(e.value)
    assert not (tmp_path / "other.html").exists()


def test_report_shows_a_tempered_fits_modes(imported_fit, tmp_path) -> None:
    """Issue 44 item 1: a tempered fit's modes and ladder (diagnostics.modes, .tempering, as
    fitting.tempered_run writes them) are in the report, in words and as a table of each mode's
    mass and place. The two modes here are written into the fit by hand (the report's input)."""
    import json

    from gonio.report import write_fit_report

    samples, fit = imported_fit
    doc = json.loads(fit.read_text())
    kd = {n: 0.5 for n in doc["parameters"] if n.startswith("kd")}
    doc["diagnostics"]["modes"] = {
        "count": 2,
        "masses": [0.7, 0.3],
        "optima": [kd, {n: 0.25 for n in kd}],
        "words": "2 modes found, 2 with ≥ 1 % of the mass: mode 1 holds 70 %; mode 2 holds 30 %",
    }
    doc["diagnostics"]["tempering"] = {
        "temperatures": 8,
        "betas": [1.0, 0.5],
        "swap_acceptance": [0.41, 0.37],
    }
    tempered = tmp_path / "fit-lambert.json"
    tempered.write_text(json.dumps(doc))
    page = write_fit_report(samples, tempered, tmp_path / "r.html").read_text()
    assert "Posterior modes: 2 modes found" in page
    assert "<td>mode 2</td><td>30.0 %</td>" in page
    assert (
        "parallel tempering: 8 temperatures, swap acceptance between neighbours 0.41, 0.37" in page
    )

"""report.html for a small simulated run: every section is there, images are embedded, and
user-supplied strings (plan name, model-comparison labels) are HTML-escaped."""

from __future__ import annotations

import base64
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from acquisition.config import PlanConfig
from calibration.reduce import ReduceOptions, reduce_run
from fitting.compare import rank, score_fit, write_compare
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions
from gonio.pipeline import AcquireSpec, acquire, config_dir
from gonio.report import write_report
from tests.support.browser import artifacts_dir, check_page, screenshot
from tests.support.report_checks import assert_uncertainty_visible

EVIL = "<script>alert('x')</script>"


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("report") / "run"
    plan = PlanConfig(
        name=f"tiny {EVIL}",
        type="isotropic",
        theta_i_deg=(20.0, 45.0),
        theta_o_deg=(0.0, 15.0, 30.0, 45.0, 60.0),
        delta_phi_deg=(180.0, 120.0),
        exposures_s=(0.002, 0.016),
    )
    res = acquire(
        out, AcquireSpec(rig=config_dir() / "rigs" / "sim.toml", plan=plan, progress=False)
    )
    assert res.outcome.complete
    table = reduce_run(out, ReduceOptions(bin_px=8, mode="center"), progress=False)
    result = fit_samples(
        table,
        FitOptions(
            model="torrance-sparrow",
            model_options={"fresnel": "none", "shadowing": "smith-rational"},
            shared=("m",),
            mcmc=McmcOptions(walkers=16, max_steps=200),
            n_starts=2,
            seed=3,
        ),
        out_dir=out,
    )
    # A comparison table whose label is user-controlled text.
    write_compare(out / "compare.json", rank([score_fit(result, label=EVIL, max_draws=200)]))
    write_report(out, compute_times_s={"acquire (simulate)": res.compute_s})
    return out


def _images(html: str) -> list[Image.Image]:
    uris = re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", html)
    return [Image.open(io.BytesIO(base64.b64decode(u))) for u in uris]


def test_report_has_every_section(run_dir: Path) -> None:
    html = (run_dir / "report.html").read_text()
    for heading in (
        "Measured vs fitted",
        "MCMC diagnostics",
        "Goodness of fit",
        "Residual map over (θh, θd)",
        "Trace plots",
        "Posterior marginals",
        "Corner plot",
        "Preview render",
        "Model comparison",
        "Time",
        "Verdicts",
        "Polar plots per incidence angle",
        "Hemisphere: measured, fitted, residual",
        "Directional albedo and the energy check",
        "Where the samples are",
        "Calibration evidence",
        "Provenance",
        "Coverage: what this model needs of the hemisphere",
    ):
        assert heading in html, heading
    assert "Mitsuba 3 material (XML)" in html and "&lt;bsdf version=" in html
    for cell in ("elpd_loo", "p_loo", "WAIC", "ΔELPD", "AIC", "BIC", "lab time", "R-hat"):
        assert cell in html, cell
    # the precision the model was sampled in, in words (fitting.likelihood.choose_precision)
    assert re.search(r"model evaluated in float(32|64) while sampling \([^)]*points checked", html)
    # slices, residual map, polar, hemisphere, albedo, traces, marginals, corner, preview,
    # sample map, light monitor: eleven PNGs that decode.
    images = _images(html)
    assert len(images) == 11
    for im in images:
        im.load()
        assert im.size[0] > 50 and im.size[1] > 50
    assert "preview not rendered" not in html


def test_preview_render_shows_a_lit_sphere(run_dir: Path) -> None:
    """The 128×128 preview: a lit sphere in front of the dim background (the image centre,
    on the sphere, is brighter than a corner, which only sees the 0.03 environment)."""
    preview = [im for im in _images((run_dir / "report.html").read_text()) if im.size == (128, 128)]
    assert len(preview) == 1
    a = np.asarray(preview[0].convert("RGB"), dtype=float)
    centre = a[54:74, 54:74].mean()
    corner = a[:10, :10].mean()
    assert centre > corner + 30


def test_user_strings_are_escaped(run_dir: Path) -> None:
    html = (run_dir / "report.html").read_text()
    assert "<script" not in html.lower()
    assert "&lt;script&gt;" in html  # the plan name and the comparison label, escaped
    assert html.count("&lt;script&gt;") >= 2


def test_every_parameter_shows_its_uncertainty(run_dir: Path) -> None:
    """Each parameter's cell is 'value ± u' or 'value +u −d' with a non-zero u: the digits follow
    the uncertainty, so a 68 % interval narrower than 1e-4 of the value is still visible."""
    fit = json.loads((run_dir / "fit-torrance-sparrow.json").read_text())
    assert_uncertainty_visible((run_dir / "report.html").read_text(), fit)
    for name, p in fit["parameters"].items():
        assert p["p84"] > p["p16"], name  # the chain moved, so its spread must be shown


def test_verdict_box_heads_the_page(run_dir: Path) -> None:
    """The verdicts come before the first plot, one box per fit, with a status in words."""
    html = (run_dir / "report.html").read_text()
    box = html.index("class='verdict ")
    assert box < html.index("<img")
    assert html.count("class='verdict ") == len(list(run_dir.glob("fit-*.json")))
    assert re.search(r"all checks passed|usable, with warnings|FAILED|not judged", html)


def test_report_renders_in_a_real_browser(run_dir: Path) -> None:
    """Headless Chromium: the page loads without a console error, every image decodes, and the
    screenshot (kept under artifacts/ for CI) shows the verdict box's coloured frame."""
    page = run_dir / "report.html"
    n_img = page.read_text().count("<img ")
    check = check_page(page)
    assert check.errors == []
    assert check.images == n_img and check.broken == 0
    shot = screenshot(page, artifacts_dir() / "report-screenshot.png", 1200, 1400)
    rgb = np.asarray(Image.open(shot).convert("RGB"), dtype=int)
    frames = {  # the verdict box's border colours (gonio.report _CSS), one per status
        "ok": (0x17, 0x6E, 0x1B),
        "warning": (0xB2, 0x6A, 0x00),
        "fail": (0xB0, 0x00, 0x20),
    }
    # a 2 px frame around a box ~1000 px wide: hundreds of exact-colour pixels when drawn
    found = {k: int(np.all(rgb == v, axis=-1).sum()) for k, v in frames.items()}
    assert max(found.values()) > 500, found


def test_the_browser_check_can_fail(tmp_path: Path) -> None:
    """The checker itself: a page with an undecodable image, a console.error and an uncaught
    exception is reported as such (so a pass above means something)."""
    bad = tmp_path / "bad.html"
    bad.write_text(
        "<!doctype html><html><head><meta charset='utf-8'></head><body>"
        "<img src='data:image/png;base64,AAAA'>"
        "<script>console.error('boom'); notDefined();</script></body></html>"
    )
    check = check_page(bad)
    assert check.images == 1 and check.broken == 1
    assert any("boom" in e for e in check.errors)
    assert any("notDefined" in e for e in check.errors)


def test_coverage_names_what_the_samples_leave_empty() -> None:
    """Samples far from the mirror direction: a Torrance-Sparrow fit needs the specular peak,
    and the report's coverage section says, in red, that it is missing."""
    from brdfdata.directions import spherical_to_vector
    from gonio.report.sections import coverage_parts
    from simulator.scene import DiffuseMaterial
    from simulator.truth import direct_samples

    ti, to = np.meshgrid(np.radians([20.0, 40.0]), np.radians([0.0, 10.0, 70.0, 80.0]))
    wi = spherical_to_vector(ti.ravel(), 0.0)
    wo = spherical_to_vector(to.ravel(), np.pi / 2)  # 90° out of the plane: θ_h ≥ 14°
    table, _ = direct_samples(DiffuseMaterial(), wi, wo, channels="G")
    html = "".join(coverage_parts(table, {"model": "torrance-sparrow"}))
    assert "specular: 0 pairs" in html
    assert "class='bad'>The samples leave specular" in html

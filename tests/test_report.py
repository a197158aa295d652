"""report.html for a small simulated run: every section is there, images are embedded, and
user-supplied strings (plan name, model-comparison labels) are HTML-escaped."""

from __future__ import annotations

import base64
import io
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from acquisition.config import PlanConfig
from calibration.reduce import ReduceOptions, reduce_run
from fitting.compare import rank, score_fit, write_compare
from fitting.fit import fit_samples
from gonio.pipeline import acquire, config_dir
from gonio.report import write_report

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
    res = acquire(config_dir() / "rigs" / "sim.toml", None, out, plan_config=plan, progress=False)
    assert res.outcome.complete
    table = reduce_run(out, ReduceOptions(bin_px=8, mode="center"), progress=False)
    result = fit_samples(
        table,
        "torrance-sparrow",
        {"fresnel": "none", "shadowing": "smith-rational"},
        shared=("m",),
        walkers=16,
        steps=200,
        n_starts=2,
        seed=3,
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
    ):
        assert heading in html, heading
    assert "Mitsuba 3 material (XML)" in html and "&lt;bsdf version=" in html
    for cell in ("elpd_loo", "p_loo", "WAIC", "ΔELPD", "AIC", "BIC", "lab time", "R-hat"):
        assert cell in html, cell
    # slices, residual map, traces, marginals, corner, preview: six PNGs that decode.
    images = _images(html)
    assert len(images) == 6
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

"""Per-texel samples from a simulated acquisition of a textured sample (issue 20, items 1–2).

The simulated rig renders configs/scenes/textured.toml's material (Mitsuba bitmaps for kd, ks
and m, simulator.texture) on a coarse 4 × 4 grid so that a short run is enough; `gonio calibrate
--per-texel` maps every pixel to its texel. Each sample is compared with the truth at its own
(ω_i, ω_o) and texel: Mitsuba's own textured BSDF evaluated at the texel's centre
(simulator.texture.textured_brdf) — independent of the calibration code under test.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from acquisition.config import PlanConfig
from acquisition.operator import AutoOperator
from brdfdata.samples import read_samples
from calibration.reduce import ReduceOptions, reduce_run
from calibration.texels import TexelGrid
from gonio.pipeline import AcquireSpec, acquire
from plumbing.errors import UserError
from simulator.scene import load_scene
from simulator.texture import textured_brdf
from tests.support.paths import REPO

RIG = REPO / "configs" / "rigs" / "sim.toml"
TEXELS = 4
TEXEL_MM = 50.0 / TEXELS  # the rig's 50 mm sample


@pytest.fixture(scope="module")
def textured_run(tmp_path_factory: pytest.TempPathFactory):
    base = tmp_path_factory.mktemp("textured")
    text = (REPO / "configs" / "scenes" / "textured.toml").read_text()
    scene_path = base / "textured4.toml"
    scene_path.write_text(text.replace("texels = 32", f"texels = {TEXELS}"))
    plan = PlanConfig.model_validate(
        {
            "name": "texels",
            "type": "isotropic",
            "theta_i_deg": [35.0],
            "theta_o_deg": [10.0, 40.0],
            "delta_phi_deg": [180.0, 120.0],
            "exposures_s": [0.004, 0.03],
            "order": "nearest",
        }
    )
    out = base / "run"
    spec = AcquireSpec(
        rig=RIG, scene=scene_path, progress=False, plan=plan, operator=AutoOperator()
    )
    assert acquire(out, spec).outcome.complete
    return out, load_scene(scene_path)


def test_every_pixel_gets_its_texel_and_matches_mitsuba(textured_run) -> None:
    run, scene = textured_run
    reduce_run(run, ReduceOptions(bin_px=1, texel_mm=TEXEL_MM))
    table = read_samples(run / "samples-texels.parquet")
    texel = table.extra["texel"]
    assert json.loads(table.metadata["gonio.texels"])["n_x"] == TEXELS
    good = (table.flags == 0) & (texel >= 0)
    # Every texel of the grid is seen (the sample fills a third of the 64 px frame per pose).
    assert set(texel[good].tolist()) == set(range(TEXELS * TEXELS))
    snr = table.f / table.sigma
    sel = good & (snr > 30)
    assert sel.sum() > 2000
    lut = {"R": 0, "G": 1, "B": 2}
    f_true = textured_brdf(scene.material, table.wi[sel], table.wo[sel], texel[sel])
    ch = np.array([lut[c] for c in table.channel[sel]])
    truth = f_true[np.arange(ch.size), ch]
    rel = np.abs(table.f[sel] / truth - 1.0)
    # SNR > 30: σ/f < 3.3 %, so the median |error| of honest Gaussian errors is < 0.67·3.3 %
    # = 2.2 %. A pixel given a neighbouring texel would be off by the texel-to-texel spread of
    # kd (×1.5–6), so a wrong texel index for more than a few percent of pixels fails at once.
    assert np.median(rel) <= 0.022
    assert np.mean(rel > 0.2) < 0.02


def test_texel_index_of_points() -> None:
    grid = TexelGrid(texel_m=0.0125, size_m=0.05)
    pts = np.array([[-0.0249, -0.0249, 0], [0.0249, -0.0249, 0], [0.0, 0.0, 0], [0.03, 0, 0]])
    # corner (0, 0) → 0; (3, 0) → 3; the centre is texel (2, 2) → 10; off the sample → −1.
    assert grid.index(pts).tolist() == [0, 3, 10, -1]


def test_per_texel_never_replaces_samples_made_otherwise(textured_run) -> None:
    run, _ = textured_run
    reduce_run(run, ReduceOptions(bin_px=1, texel_mm=TEXEL_MM))
    # The same options again: re-made in place.
    reduce_run(run, ReduceOptions(bin_px=1, texel_mm=TEXEL_MM))
    with pytest.raises(UserError, match="other calibration options"):
        reduce_run(run, ReduceOptions(bin_px=1, texel_mm=TEXEL_MM / 2))


def test_calibrate_command_per_texel(textured_run) -> None:
    import subprocess
    import sys

    run, _ = textured_run
    gonio = [sys.executable, "-m", "gonio.cli", "calibrate", str(run), "--per-texel"]
    ok = subprocess.run([*gonio, str(TEXEL_MM)], capture_output=True, text=True, timeout=300)
    assert ok.returncode == 0, ok.stderr
    assert f"in {TEXELS * TEXELS} texels" in ok.stdout
    # Another texel size would replace samples made otherwise: refused in one line.
    bad = subprocess.run([*gonio, str(TEXEL_MM / 2)], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2
    assert bad.stderr.strip().count("\n") == 0 and "other calibration options" in bad.stderr

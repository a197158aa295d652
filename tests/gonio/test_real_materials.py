"""Calibration on real reflectance: measured RGL materials through the simulated rig.

Four materials of the RGL database (Dupuy & Jakob 2018; data/rgl_brdf, provenance in
data/README.md) — white paper (near-Lambertian), a matte red wall paint, a satin vinyl film and a
metallic gold vinyl film (sharp lobe) — are rendered by Mitsuba's `measured` plugin, acquired
with a small isotropic plan, reduced with mode="center" (one pixel per region with its own exact
directions), and every sample is compared with Mitsuba's own BSDF at that sample's (ω_i, ω_o)
(simulator.render.Renderer.truth_bsdf) — independent of the calibration code under test.

The gold film's published tensor has slightly negative blue values near the mirror direction
(≈ 4.5% of its rgb entries). Mitsuba renders that as negative radiance, the simulated sensor
clips the mean photo-electrons at 0, so the reduced f there is ≈ 0 ± σ (flagged dark). Such
samples have no meaningful relative error: they are excluded from the relative metric, counted,
and checked to be consistent with zero signal.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from conftest import data_dir, data_file

from acquisition.config import PlanConfig
from brdfdata.directions import spherical_to_vector
from brdfdata.samples import Flags
from calibration.reduce import ReduceOptions, reduce_run
from gonio.pipeline import AcquireSpec, acquire
from simulator.render import Renderer
from simulator.scene import load_scene
from tests.support.paths import REPO

SCENES = REPO / "configs" / "scenes"
RIG = REPO / "configs" / "rigs" / "sim.toml"
RGL = ("paper_white", "colodur_napoli_4f", "satin_rosaline", "vch_golden_yellow")

# 2 × 4 × 3 = 24 poses, including the mirror configuration (θ_o = θ_i, Δφ = 180°) where the gold
# lobe peaks (f ≈ 10 sr⁻¹, ~1000× its off-specular level). Brackets over 80×. A 1 W/sr lamp at
# 0.5 m, f/4, 5 µm pixels, QE 0.6 give ≈ 8e6 e/s per sr⁻¹ of f at normal incidence: the gold
# peak at θ_i = 25° collects ≈ 1.5e4 e in 0.2 ms (full well 3e4 e), and 16 ms reaches the
# 2500 e of SNR 50 for f ≳ 0.02/cos θ_i sr⁻¹.
PLAN = {
    "name": "rgl",
    "type": "isotropic",
    "theta_i_deg": [25.0, 50.0],
    "theta_o_deg": [0.0, 25.0, 50.0, 70.0],
    "delta_phi_deg": [180.0, 135.0, 90.0],
    "exposures_s": [0.0002, 0.002, 0.016],
    "order": "nearest",
}


def _scene_with_shared_data(name: str, tmp: Path) -> Path:
    """The shipped scene with its .bsdf path pointed at the file the data resolver finds."""
    with open(SCENES / f"rgl_{name}.toml", "rb") as fh:
        spec = tomllib.load(fh)
    bsdf = data_file(f"rgl_brdf/{name}_rgb.bsdf")
    assert Path(spec["material"]["filename"]).name == bsdf.name
    spec["material"]["filename"] = str(bsdf)
    path = tmp / f"rgl_{name}.toml"
    path.write_bytes(tomli_w.dumps(spec).encode())
    return path


_RUNS: dict[str, tuple] = {}


@pytest.fixture(scope="module")
def rgl_run(tmp_path_factory: pytest.TempPathFactory):
    """name → (sample table, truth f_r per sample); each material acquired once per module."""

    def get(name: str):
        if name not in _RUNS:
            tmp = tmp_path_factory.mktemp(name)
            scene_path = _scene_with_shared_data(name, tmp)
            res = acquire(
                tmp / "run",
                AcquireSpec(
                    rig=RIG, scene=scene_path, progress=False, plan=PlanConfig.model_validate(PLAN)
                ),
            )
            assert res.outcome.complete
            table = reduce_run(tmp / "run", ReduceOptions(bin_px=2, mode="center"))
            renderer = Renderer(load_scene(scene_path))
            wi = spherical_to_vector(table.theta_i, table.phi_i)
            wo = spherical_to_vector(table.theta_o, table.phi_o)
            f = renderer.truth_bsdf(wi, wo)
            idx = np.array([{"R": 0, "G": 1, "B": 2}[c] for c in table.channel.astype(str)])
            _RUNS[name] = (table, f[np.arange(len(idx)), idx], renderer)
        return _RUNS[name]

    yield get
    _RUNS.clear()


@pytest.mark.parametrize("name", RGL)
def test_calibration_on_real_reflectance(rgl_run, name: str) -> None:
    table, truth, _ = rgl_run(name)
    saturated = (table.flags & Flags.SATURATED) != 0
    snr = table.f / table.sigma
    sel = ~saturated & (snr > 50)
    # Truth ≤ 0 (gold's negative published values) has no relative error: never selected,
    # because zero signal cannot reach SNR 50 (its handling is checked in the next test).
    assert not np.any(sel & (truth <= 0))
    assert sel.sum() > 1500, sel.sum()
    assert set(table.channel[sel].astype(str)) == {"R", "G", "B"}
    # The brackets reach the brightest point the plan sees (the gold mirror peak) unsaturated.
    assert not saturated.any()
    assert truth[sel].max() >= 0.95 * truth.max()
    f, t, sigma = table.f[sel], truth[sel], table.sigma[sel]
    rel = np.abs(f / t - 1.0)
    # Acceptance (issue 10): 3% median. With SNR > 50, σ/f < 2% and the median |error| of honest
    # Gaussian noise is < 0.67·2% = 1.4%; 3% leaves room for no systematic error larger than
    # ~1.5% (geometry, radiometry, interpolation between the measured tensor's nodes is the
    # same in render and truth).
    assert np.median(rel) <= 0.03, np.median(rel)
    z = (f - t) / sigma
    # σ honest: with N > 1500 the sample std has standard error ≈ 1/√(2N) < 2%, so [0.8, 1.25]
    # fails only for a wrong noise model; |mean| > 0.15 (≈ 6/√N) is a systematic bias.
    assert 0.8 <= np.std(z) <= 1.25, np.std(z)
    assert abs(np.mean(z)) <= 0.15, np.mean(z)


def test_gold_negative_published_values_are_handled(rgl_run) -> None:
    table, truth, renderer = rgl_run("vch_golden_yellow")
    neg = truth <= 0
    # The plan does probe the negative region (blue near the mirror direction) ...
    assert neg.sum() > 0
    assert set(table.channel[neg].astype(str)) == {"B"}
    # ... Mitsuba passes the negative BSDF on as negative radiance (no clamp in `measured`) ...
    light = spherical_to_vector(np.radians(25.0), 0.0) * 0.5
    camera = spherical_to_vector(np.radians(25.0), np.pi) * 0.5
    img = renderer.render(light, camera)
    assert img[..., 2].min() < 0
    # ... and the sensor clips the mean signal at zero electrons, so the reduced value is zero
    # plus noise: every such sample is within 5σ of 0 (Gaussian, a few hundred samples: the
    # chance of a 5σ excursion is ~1e-4) and flagged dark (SNR < 3 on average: |f| ≈ σ).
    z0 = table.f[neg] / table.sigma[neg]
    assert np.all(np.abs(z0) < 5.0), np.abs(z0).max()
    assert np.mean((table.flags[neg] & Flags.DARK) != 0) > 0.9
    assert np.all(np.isfinite(table.f)) and np.all(np.isfinite(table.sigma))


def test_shipped_rgl_scenes_load_and_name_their_data(configs) -> None:
    data = data_dir("rgl_brdf")
    for name in RGL:
        scene = load_scene(configs / "scenes" / f"rgl_{name}.toml")
        assert scene.material.type == "measured"
        assert Path(scene.material.filename).name == f"{name}_rgb.bsdf"
        assert (data / f"{name}_rgb.bsdf").is_file()

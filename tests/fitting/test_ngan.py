"""Ngan et al. 2005 published fits (fitting.ngan): the reader, the exact mapping of their
Cook-Torrance onto our torrance-sparrow, the shipped scenes, and a parameter-recovery check
through the simulated rig.

Ground truth: the published values quoted in docs/design.md §6 (from the paper's tables via bbm),
and an independent transcription of bbm's NganCookTorrance formula (include/bsdfmodel/ngan.h,
microfacet.h, ndf/beckmann.h, maskingshadowing/vgroove.h, fresnel_schlick.h) written here in plain
numpy — not fitting.models.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import data_dir, data_file

from acquisition.config import PlanConfig
from brdfdata.samples import Flags
from calibration.reduce import ReduceOptions, reduce_run
from fitting import models
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions
from fitting.ngan import (
    COOK_TORRANCE_OPTIONS,
    NGAN_MODELS,
    ngan_cook_torrance_parameters,
    ngan_fits_path,
    ngan_scene_material,
    read_ngan_fits,
)
from gonio.pipeline import AcquireSpec, acquire
from simulator.scene import ModelMaterial, load_scene
from tests.support.paths import REPO

# docs/design.md §6: Ngan, Durand & Matusik 2005, Cook-Torrance fits (Beckmann m, Schlick F0).
PUBLISHED_CT = {
    "nickel": (0.0424, 0.733),
    "teflon": (0.139, 0.0203),
    "red-plastic": (0.262, 0.085),
    "gold-metallic-paint": (0.241, 0.663),
}


def _fits(model: str) -> dict:
    return read_ngan_fits(data_file(f"brdf_fits/ngan_{model}.fit"))


def test_cook_torrance_published_values() -> None:
    fits = _fits("cooktorrance")
    assert len(fits) == 86  # the MERL database
    for name, (m, f0) in PUBLISHED_CT.items():
        e = fits[name]
        assert e["lobe"] == "NganCookTorrance"
        assert e["roughness"] == m
        assert e["eta"] == f0
        assert len(e["albedo"]) == 3 and len(e["diffuse_albedo"]) == 3
    # Ngan's `eta` is a normal-incidence reflectance F0 ∈ [0, 1], not an index of refraction.
    assert all(0.0 <= e["eta"] <= 1.0 for e in fits.values())


def test_every_ngan_table_reads_the_same_86_materials() -> None:
    names = set(_fits("cooktorrance"))
    for model in NGAN_MODELS:
        fits = _fits(model)
        assert set(fits) == names, model
        for e in fits.values():
            assert all(np.isfinite(v) for v in e["diffuse_albedo"])
    bp = _fits("blinnphong")
    assert bp["nickel"]["lobe"] == "NganBlinnPhong"
    # As printed in bbm's fits/ngan_blinnphong.fit (material "blue-acrylic", the first line).
    assert bp["blue-acrylic"]["sharpness"] == 13700.0
    assert bp["blue-acrylic"]["albedo"] == (0.0016, 0.00115, 0.000709)
    assert bp["blue-acrylic"]["diffuse_albedo"] == (0.0147, 0.0332, 0.064)


def _bbm_ngan_cook_torrance(entry: dict, c: int, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """bbm's Aggregate(Lambertian, NganCookTorrance), channel c, transcribed independently:
    ρ_d/π + albedo · D · G · F / (π cos θ_i cos θ_o), D = exp(−tan²θ_h/α²)/(π α² cos⁴θ_h),
    G = min(1, 2 h_z i_z/(i·h), 2 h_z o_z/(o·h)), F = R0 + (1 − R0)(1 − ½(i·h + o·h))⁵."""
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    cos2 = h[:, 2] ** 2
    a = entry["roughness"]
    d = np.exp(-(h[:, 0] ** 2 + h[:, 1] ** 2) / a**2 / cos2) / (a * a * cos2 * cos2) / np.pi
    ih, oh = np.sum(wi * h, axis=1), np.sum(wo * h, axis=1)
    g = np.minimum(1.0, np.minimum(2 * h[:, 2] * wi[:, 2] / ih, 2 * h[:, 2] * wo[:, 2] / oh))
    r0 = entry["eta"]
    f = r0 + (1.0 - r0) * (1.0 - 0.5 * (ih + oh)) ** 5
    spec = entry["albedo"][c] * d * g * f / np.pi / (wi[:, 2] * wo[:, 2])
    return entry["diffuse_albedo"][c] / np.pi + spec


def test_cook_torrance_mapping_is_exact_for_all_86_materials() -> None:
    rng = np.random.default_rng(5)
    n = 400
    ct, phi = rng.uniform(0.05, 1.0, (2, n)), rng.uniform(0, 2 * np.pi, (2, n))
    st = np.sqrt(1 - ct**2)
    wi = np.stack([st[0] * np.cos(phi[0]), st[0] * np.sin(phi[0]), ct[0]], -1)
    wo = np.stack([st[1] * np.cos(phi[1]), st[1] * np.sin(phi[1]), ct[1]], -1)
    # Include exact mirror pairs so the lobe peaks (where D matters most) are compared too.
    wo[:50] = wi[:50] * [-1, -1, 1]
    model = models.get("torrance-sparrow", **COOK_TORRANCE_OPTIONS)
    for name, entry in _fits("cooktorrance").items():
        p = ngan_cook_torrance_parameters(entry)
        for c in range(3):
            params = {k: (v[c] if isinstance(v, tuple) else v) for k, v in p.items()}
            ours = model.evaluate(params, wi, wo)
            ref = _bbm_ngan_cook_torrance(entry, c, wi, wo)
            # Same formula in float64 on both sides: only round-off differs.
            np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=0, err_msg=f"{name} [{c}]")


def test_scene_material_and_shipped_scenes(configs) -> None:
    data = data_dir("brdf_fits").parent  # the data root holding brdf_fits/
    for name in ("nickel", "teflon"):
        mat = ngan_scene_material(name, data_dir=data)
        ModelMaterial.model_validate(mat)  # a valid scene [material] table
        scene = load_scene(configs / "scenes" / f"ngan_{name}.toml")
        assert scene.material.model == "torrance-sparrow"
        assert scene.material.options == COOK_TORRANCE_OPTIONS
        assert set(scene.material.parameters) == set(mat["parameters"])
        for k, v in mat["parameters"].items():
            np.testing.assert_allclose(scene.material.parameters[k], v, rtol=1e-15)
        m, f0 = PUBLISHED_CT[name]
        assert scene.material.parameters["m"] == m
        assert scene.material.parameters["f0"] == f0
    assert ngan_fits_path("cooktorrance", data) == data / "brdf_fits" / "ngan_cooktorrance.fit"


def test_errors_are_clear(tmp_path) -> None:
    data = data_dir("brdf_fits").parent  # the data root holding brdf_fits/
    with pytest.raises(KeyError, match="unobtainium"):
        ngan_scene_material("unobtainium", data_dir=data)
    with pytest.raises(ValueError, match="only 'cooktorrance'"):
        ngan_scene_material("nickel", model="blinnphong", data_dir=data)
    with pytest.raises(ValueError, match="unknown Ngan model"):
        ngan_fits_path("torrance", data)
    bad = tmp_path / "ngan_x.fit"
    bad.write_text("# header\nnickel = Lambertian(albedo = [1, 2, 3])\n")
    with pytest.raises(ValueError, match=r"ngan_x.fit:2"):
        read_ngan_fits(bad)
    with pytest.raises(ValueError, match="not a Cook-Torrance"):
        ngan_cook_torrance_parameters(_fits("blinnphong")["nickel"])


def test_teflon_fit_recovers_ngan_roughness(tmp_path) -> None:
    """Simulate MERL teflon as Ngan fitted it, acquire it with a small plan, and fit the same
    model back: Ngan's m (and F0) must lie inside the posterior 95% interval."""
    plan = PlanConfig.model_validate(
        {
            "name": "ngan",
            "type": "isotropic",
            "theta_i_deg": [20.0, 45.0],
            # The specular lobe (m = 0.139: ~8° wide in θ_o) is sampled around θ_o = θ_i.
            "theta_o_deg": [0.0, 15.0, 20.0, 30.0, 45.0, 60.0],
            "delta_phi_deg": [180.0, 150.0],
            "exposures_s": [0.002, 0.016],
            "order": "nearest",
        }
    )
    out = tmp_path / "run"
    res = acquire(
        out,
        AcquireSpec(
            rig=REPO / "configs" / "rigs" / "sim.toml",
            scene=REPO / "configs" / "scenes" / "ngan_teflon.toml",
            progress=False,
            plan=plan,
        ),
    )
    assert res.outcome.complete
    # bin 16: ~370 samples keep the MCMC short; "center" keeps each sample's exact directions.
    table = reduce_run(out, ReduceOptions(bin_px=16, mode="center"))
    assert np.all(table.flags & Flags.SATURATED == 0)
    fit = fit_samples(
        table,
        FitOptions(
            model="torrance-sparrow",
            model_options=COOK_TORRANCE_OPTIONS,
            mcmc=McmcOptions(max_steps=600),
            seed=3,
        ),
    )
    p = fit.parameters
    m, f0 = PUBLISHED_CT["teflon"]
    assert p["m"]["p2.5"] <= m <= p["m"]["p97.5"], p["m"]
    assert p["f0"]["p2.5"] <= f0 <= p["f0"]["p97.5"], p["f0"]
    # And the interval is informative (a fit that learnt nothing would pass the line above):
    # the data pin m to better than ±5%.
    assert p["m"]["p97.5"] - p["m"]["p2.5"] < 0.1 * m


def test_nickel_sharp_metal_lobe_through_the_rig(tmp_path) -> None:
    """Ngan's nickel (m = 0.0424: a lobe ~3° wide, peak f ≈ 8 sr⁻¹, diffuse 0.01 sr⁻¹) acquired
    and calibrated: every well-exposed sample agrees with the scene's own BSDF at its exact
    directions (Renderer.truth_bsdf of the wrapped model; independent of the calibration)."""
    from brdfdata.directions import spherical_to_vector
    from simulator.render import Renderer

    plan = PlanConfig.model_validate(
        {
            "name": "nickel",
            "type": "isotropic",
            "theta_i_deg": [25.0, 50.0],
            "theta_o_deg": [0.0, 25.0, 50.0, 70.0],
            "delta_phi_deg": [180.0, 135.0, 90.0],
            # 0.2 ms keeps the mirror peak below full well (≈ 8e6 e/s per sr⁻¹, 3e4 e).
            "exposures_s": [0.0002, 0.002, 0.016],
            "order": "nearest",
        }
    )
    scene_path = REPO / "configs" / "scenes" / "ngan_nickel.toml"
    out = tmp_path / "run"
    res = acquire(
        out,
        AcquireSpec(
            rig=REPO / "configs" / "rigs" / "sim.toml", scene=scene_path, progress=False, plan=plan
        ),
    )
    assert res.outcome.complete
    table = reduce_run(out, ReduceOptions(bin_px=2, mode="center"))
    renderer = Renderer(load_scene(scene_path))
    f_all = renderer.truth_bsdf(
        spherical_to_vector(table.theta_i, table.phi_i),
        spherical_to_vector(table.theta_o, table.phi_o),
    )
    idx = np.array([{"R": 0, "G": 1, "B": 2}[c] for c in table.channel.astype(str)])
    truth = f_all[np.arange(len(idx)), idx]
    assert not np.any(table.flags & Flags.SATURATED)
    sel = table.f / table.sigma > 50
    # The lobe is what reaches SNR 50 here: the diffuse floor alone (kd/π ≤ 0.011 sr⁻¹) stays
    # below it, so every selected sample has a lobe contribution on top of its channel's floor,
    # and the brightest point of the lobe is among them.
    floor = np.array([0.0342, 0.0256, 0.014])[idx] / np.pi  # kd per channel, ngan_nickel.toml
    assert sel.sum() > 1000
    assert np.all(truth[sel] > floor[sel]) and truth[sel].max() >= 0.95 * truth.max()
    rel = np.abs(table.f[sel] / truth[sel] - 1.0)
    # As for the RGL materials: SNR > 50 ⇒ median |error| < 1.4% for honest noise; 3% bound.
    assert np.median(rel) <= 0.03, np.median(rel)
    z = (table.f[sel] - truth[sel]) / table.sigma[sel]
    # N > 1000: std of z has standard error < 2.3%; a mean beyond 0.2 (≈ 6/√N) is a bias.
    assert 0.8 <= np.std(z) <= 1.25 and abs(np.mean(z)) <= 0.2, (np.std(z), np.mean(z))

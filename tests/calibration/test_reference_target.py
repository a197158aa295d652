"""Reference-target radiometry (calibration.reference) on a simulated RAW run.

The simulated lab (configs/scenes/raw.toml: DNG, Bayer, noise, darks, PRNU, vignetting) records
the plan's calibration phases: darks, a flat, then the operator swaps the sample for the rig
file's reference target (Lambertian, ρ = 0.99) and it is imaged at three poses. The lamp's
*certificate* in the rig config is deliberately 20 % high (1.2 W/sr; the simulated lamp emits
1.0 W/sr, scene file).

Truth at every sample's own (ω_i, ω_o) is Mitsuba's own BSDF of the rendered material
(Renderer.truth_bsdf = bsdf.eval / cos θ, independent of the calibration code). A second target,
Mitsuba's roughplastic (diffuse base under a rough coating — not Lambertian, like Spectralon), is
imaged at the same poses by a retake (`gonio capture reference`, the rig file now describing it);
its "calibration certificate" is a (θ_i, θ_o, Δφ) table of Mitsuba's own BSDF of that target, as
a standards lab would tabulate it.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from acquisition.clock import VirtualClock
from acquisition.config import PlanConfig, ReferenceConfig, load_rig
from acquisition.operator import AutoOperator
from brdfdata.directions import spherical_to_vector
from brdfdata.samples import Flags
from calibration.darks import calibration_frames
from calibration.reduce import CalibrationError, ReduceOptions, reduce_run
from calibration.reference import FRefTable, load_f_ref_table
from gonio.pipeline import AcquireSpec, acquire, capture_calibration
from simulator.camera import SimCamera
from simulator.render import Renderer
from simulator.scene import RoughPlasticMaterial, load_scene, world_scene
from tests.support.paths import REPO

SCENE = REPO / "configs" / "scenes" / "raw.toml"
EXPOSURES_S = [0.002, 0.016]
CERTIFICATE_ERROR = 1.2  # the rig config claims 1.2× the lamp's true intensity
TARGET = RoughPlasticMaterial(alpha=0.4, diffuse_reflectance=(0.95, 0.9, 0.85))


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("ref") / "run"
    plan = PlanConfig.model_validate(
        {
            "name": "reference",
            "type": "isotropic",
            "theta_i_deg": [30.0, 55.0],
            "theta_o_deg": [0.0, 20.0, 40.0, 60.0],
            "delta_phi_deg": [180.0, 120.0, 60.0],
            "exposures_s": EXPOSURES_S,
            "order": "nearest",
            "calibration": {"dark": {}, "flat": {}, "reference": {}},
        }
    )
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    scene = load_scene(SCENE)
    # The certificate, not the lamp: the scene (what Mitsuba renders) keeps the true value.
    wrong = tuple(CERTIFICATE_ERROR * i for i in scene.light.intensity_W_sr)
    rig = rig.model_copy(update={"light": rig.light.model_copy(update={"intensity_W_sr": wrong})})
    res = acquire(
        out, AcquireSpec(scene=scene, progress=False, rig=rig, plan=plan, operator=AutoOperator())
    )
    assert res.outcome.complete
    refs = calibration_frames(out, "reference")
    # Three reference poses × every exposure, recorded raw in the run (docs/design.md §4).
    assert len(refs) == 3 * len(EXPOSURES_S)
    assert all((out / e["path"]).exists() for e in refs)
    return out, Renderer(scene)


def _truth(table, renderer: Renderer) -> np.ndarray:
    wi = spherical_to_vector(table.theta_i, table.phi_i)
    wo = spherical_to_vector(table.theta_o, table.phi_o)
    f = renderer.truth_bsdf(wi, wo)
    idx = np.array([{"R": 0, "G": 1, "B": 2}[c] for c in table.channel.astype(str)])
    return f[np.arange(len(idx)), idx]


def _good(table) -> np.ndarray:
    # SNR > 50 (σ/f < 2 %) and unsaturated, as in tests/calibration/test_calibration_accuracy.py.
    return ((table.flags & (Flags.SATURATED | Flags.MASKED)) == 0) & (table.f / table.sigma > 50)


def _reduce(run_dir: Path, radiometry: str, out: Path):
    return reduce_run(
        run_dir, ReduceOptions(bin_px=2, mode="center", radiometry=radiometry), out=out
    )


def test_reference_method_recovers_mitsuba_brdf_despite_a_wrong_certificate(run, tmp_path) -> None:
    run_dir, renderer = run
    table = _reduce(run_dir, "reference", tmp_path / "ref.parquet")
    sel = _good(table)
    assert sel.sum() > 3000
    truth = _truth(table, renderer)[sel]
    ratio = table.f[sel] / truth
    # The bound of the certified method (test_calibration_accuracy): SNR > 50 gives a median
    # |error| ≈ 0.67σ < 1.4 % for honest noise, so 2 % leaves no room for a 20 % scale error.
    assert np.median(np.abs(ratio - 1.0)) <= 0.02
    # The scale itself: the median ratio of > 3000 samples has a statistical error ≈ 1.25σ/√N
    # ≲ 0.05 %; 0.5 % is ten times that and 40× below the certificate's error.
    assert abs(np.median(ratio) - 1.0) < 0.005, np.median(ratio)
    # σ is statistical only and honest (same bounds as the certified method's acceptance test:
    # std of N > 3000 unit residuals is 1 ± 0.013); the shared scale error (≲ 3e-4 relative,
    # below) shifts the mean z by at most 3e-4/(σ/f ≥ 5e-3) = 0.06, inside the 0.1 bound.
    z = (table.f[sel] - truth) / table.sigma[sel]
    assert 0.8 <= np.std(z) <= 1.25 and abs(np.mean(z)) <= 0.1, (np.std(z), np.mean(z))
    meta = json.loads(table.metadata["gonio.calibration"])
    assert meta["radiometry"] == "reference"
    assert table.metadata["gonio.absolute"] == "true"
    rel = np.array(meta["reference"]["rel_sigma"])
    # The reference scale's own σ is reported: averaging ~3 × 500 superpixels per channel at
    # SNR ~100 gives ~3e-4; it must be positive and far below the samples' σ/f ≥ 0.5 %.
    assert np.all(rel > 0) and np.all(rel < 0.003), rel
    # …and goes to the budget as one error shared by every sample of a channel, not into σ.
    scale = [
        c for c in json.loads(table.metadata["gonio.budget"]) if c["component"].startswith("scale")
    ]
    assert len(scale) == 1 and "every sample" in scale[0]["shared_by"]
    np.testing.assert_allclose(
        [scale[0]["relative_sigma"][c] for c in meta["reference"]["channels"]], rel
    )
    # The arms' angle errors are named too, and marked as not carried by the fit.
    arms = [
        c for c in json.loads(table.metadata["gonio.budget"]) if c["component"].startswith("arm")
    ]
    assert len(arms) == 2 and all(c["propagated"] is False for c in arms)
    # So is the camera's non-linearity: not a scale (it bends bright and dim samples
    # differently), named with the datasheet's size or as unstated, never carried as a scale.
    lin = [
        c for c in json.loads(table.metadata["gonio.budget"]) if c["component"].startswith("lin")
    ]
    assert len(lin) == 1 and lin[0]["propagated"] is False and lin[0]["relative_sigma"] is None
    # The recovered effective intensity is the lamp's true one (the camera model is right in the
    # simulator), within 5σ of the reported uncertainty.
    k = np.array(meta["reference"]["k_W_sr"])
    sig = np.array(meta["reference"]["sigma_W_sr"])
    true_i = np.array(load_scene(SCENE).light.intensity_W_sr)
    assert np.all(np.abs(k - true_i) < 5 * sig + 1e-4), (k, sig)


def test_certified_method_inherits_the_certificate_error(run, tmp_path) -> None:
    run_dir, renderer = run
    table = _reduce(run_dir, "certified", tmp_path / "cert.parquet")
    sel = _good(table)
    ratio = table.f[sel] / _truth(table, renderer)[sel]
    # f ∝ 1/I_certified: a 20 % high certificate gives f/f_true = 1/1.2 (statistics as above).
    assert abs(np.median(ratio) * CERTIFICATE_ERROR - 1.0) < 0.005, np.median(ratio)
    assert np.median(np.abs(ratio - 1.0)) > 0.15  # far outside the 2 % bound
    # "auto" picks the reference captures when the run has them.
    auto = _reduce(run_dir, "auto", tmp_path / "auto.parquet")
    assert json.loads(auto.metadata["gonio.calibration"])["radiometry"] == "reference"


def test_without_reference_captures_certified_stays_the_default(run, tmp_path) -> None:
    run_dir, _ = run
    bare = tmp_path / "bare"
    shutil.copytree(run_dir, bare, ignore=shutil.ignore_patterns("reference"))
    # The same run as if the plan had had no reference phase: its rows go from the manifest.
    with sqlite3.connect(bare / "manifest.sqlite") as db:
        db.execute("DELETE FROM calibration_captures WHERE kind = 'reference'")
        db.execute("DELETE FROM calibration_takes WHERE kind = 'reference'")
    table = _reduce(bare, "auto", tmp_path / "a.parquet")
    assert json.loads(table.metadata["gonio.calibration"])["radiometry"] == "certified"
    with pytest.raises(CalibrationError, match="no reference-target captures"):
        _reduce(bare, "reference", tmp_path / "b.parquet")


def _f_ref_table(renderer: Renderer) -> FRefTable:
    """The target's "certificate": Mitsuba's own f_r on a 1.5° × 1.5° × 7.5° grid of
    (θ_i, θ_o, Δφ) covering the reference poses (θ ≤ 51°)."""
    ti = np.radians(np.arange(0.0, 52.5, 1.5))
    dp = np.radians(np.arange(0.0, 187.5, 7.5))
    g = np.meshgrid(ti, ti, dp, indexing="ij")
    wi = spherical_to_vector(g[0].ravel(), np.zeros(g[0].size))
    wo = spherical_to_vector(g[1].ravel(), g[2].ravel())
    return FRefTable((ti, ti, dp), renderer.truth_bsdf(wi, wo).reshape(*g[0].shape, 3))


def _retake(run_dir: Path, dest: Path, reference: ReferenceConfig) -> Path:
    """A copy of the run with a new reference take of TARGET (the world's true target) that the
    rig file describes as `reference` — `gonio capture reference` with a new certificate."""
    shutil.copytree(run_dir, dest)
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml").model_copy(
        update={"reference": reference}
    )
    scene = load_scene(SCENE).model_copy(update={"reference_target": TARGET})
    n = capture_calibration(
        dest, "reference", rig_config=rig, scene_config=scene, operator=AutoOperator()
    )
    assert n == 3 * len(EXPOSURES_S)
    return dest


def test_non_lambertian_reference_with_a_calibrated_table(run, tmp_path) -> None:
    run_dir, renderer = run
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    scene = world_scene(load_scene(SCENE), rig)
    cam = SimCamera(scene, VirtualClock(), lambda: (None, None), lambda: 1.0)
    target_renderer = cam.reference_renderer(TARGET)
    table_f = _f_ref_table(target_renderer)

    # The table's interpolation is exact enough where the reference poses look: random
    # directions inside its range, compared with Mitsuba directly (linear interpolation error
    # ≈ h²/8 · f''/f ≲ 1e-3 for this broad lobe at h = 1.5°).
    rng = np.random.default_rng(3)
    a = rng.uniform(0.0, np.radians(50.0), (500, 2))
    p = rng.uniform(0.0, 2 * np.pi, (500, 2))
    wi, wo = spherical_to_vector(a[:, 0], p[:, 0]), spherical_to_vector(a[:, 1], p[:, 1])
    assert np.max(np.abs(table_f(wi, wo) / target_renderer.truth_bsdf(wi, wo) - 1.0)) < 2e-3

    # The tabulated target: a new take in a copy of the run (the newest take is used).
    csv = tmp_path / "certificate.csv"
    table_f.write_csv(csv)
    tab_run = _retake(
        run_dir, tmp_path / "table", ReferenceConfig(type="table", table=str(csv), size_m=0.05)
    )
    # The table travels with the run and reads back to the same values.
    stored = load_f_ref_table(tab_run / "calibration" / "reference" / "f_ref-t02.csv")
    assert np.allclose(stored.values, table_f.values, rtol=1e-8)
    assert {e["take"] for e in calibration_frames(tab_run, "reference")} == {2}

    table = _reduce(tab_run, "reference", tmp_path / "t.parquet")
    sel = _good(table)
    ratio = table.f[sel] / _truth(table, renderer)[sel]
    assert np.median(np.abs(ratio - 1.0)) <= 0.02
    assert abs(np.median(ratio) - 1.0) < 0.005, np.median(ratio)

    # The same captures described as a Lambertian target of the base's albedo are wrong:
    # roughplastic at 0°/45° is ≈ 17 % below ρ/π (Fresnel transmission in and out of the
    # coating) — the reason a calibrated f_ref(θ) table is needed.
    lam_run = _retake(
        run_dir,
        tmp_path / "lambert",
        ReferenceConfig(albedo=TARGET.diffuse_reflectance, size_m=0.05),
    )
    wrong = _reduce(lam_run, "reference", tmp_path / "l.parquet")
    sel = _good(wrong)
    ratio = wrong.f[sel] / _truth(wrong, renderer)[sel]
    assert abs(np.median(ratio) - 1.0) > 0.05, np.median(ratio)


def test_f_ref_table_files(tmp_path) -> None:
    """CSV and TOML tables: a 2-D grid is interpolated linearly; outside it is an error."""
    from calibration.darks import CalibrationFrameError

    csv = tmp_path / "spectralon.csv"
    csv.write_text(
        "# made-up certificate\ntheta_i_deg,theta_o_deg,f\n"
        "0,0,0.30\n0,60,0.27\n40,0,0.31\n40,60,0.25\n"
    )
    t = load_f_ref_table(csv)
    wi = spherical_to_vector(np.radians([20.0]), np.array([0.0]))
    wo = spherical_to_vector(np.radians([30.0]), np.array([2.0]))
    # Bilinear at the cell centre = mean of the four corners, in every channel.
    assert np.allclose(t(wi, wo), np.mean([0.30, 0.27, 0.31, 0.25]))
    with pytest.raises(CalibrationFrameError, match="outside the f_ref table"):
        t(spherical_to_vector(np.radians([50.0]), np.array([0.0])), wo)
    toml = tmp_path / "t.toml"
    toml.write_text(
        "".join(
            f"[[point]]\ntheta_i_deg = {a}\ntheta_o_deg = {b}\nf = [{v}, {v}, {2 * v}]\n"
            for a, b, v in [(0, 0, 0.1), (0, 10, 0.2), (10, 0, 0.3), (10, 10, 0.4)]
        )
    )
    t2 = load_f_ref_table(toml)
    wi = spherical_to_vector(np.radians([10.0]), np.array([0.0]))
    wo = spherical_to_vector(np.radians([10.0]), np.array([1.0]))
    assert np.allclose(t2(wi, wo), [[0.4, 0.4, 0.8]])
    bad = tmp_path / "bad.csv"
    bad.write_text("theta_i_deg,theta_o_deg,f\n0,0,0.3\n0,60,0.2\n40,0,0.3\n")
    with pytest.raises(CalibrationFrameError, match="regular grid"):
        load_f_ref_table(bad)

"""Shared errors as nuisance parameters of the fit (fitting.nuisance, issue 17 item 3).

Ground truth: Mitsuba's own BSDF of the demo's diffuse + Beckmann blend (simulator.truth), and
for the arms' zeros the simulated rig, whose world turns the axes by the stated errors.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest

from brdfdata.directions import isotropic_gonio_directions, spherical_to_vector, vector_to_spherical
from fitting.fit import FitOptions, fit_samples
from fitting.mcmc import McmcOptions
from fitting.nuisance import shared_errors, shifted_directions
from simulator.truth import direct_samples, material_reference_parameters
from tests.support.blend import MATERIAL, OPTIONS  # the blend of the budget test
from tests.support.paths import REPO


def test_an_arm_zero_turns_directions_about_the_arms_own_axis() -> None:
    """δ on an arm's elevation turns its directions about the horizontal axis normal to the
    arm's plane: from the normal, toward the arm's azimuth (not the pixel's); elsewhere θ + δ
    at the same φ; an inplane camera on the light's side moves the other way; a camera-azimuth
    zero turns φ_o. Exact rotations: 1e-12."""
    d = math.radians(0.5)
    up = np.array([[0.0, 0.0, 1.0]])
    arm = np.array([math.radians(30.0)])
    # a pixel's direction at the normal whose own φ says nothing: it moves toward the arm's φ
    wi, _ = shifted_directions(up, up, arm, arm, {"light_theta": d}, "two-arm")
    assert np.allclose(wi, spherical_to_vector(np.full(1, d), arm), atol=1e-12)
    w = spherical_to_vector(np.radians([40.0]), arm)
    wi, wo = shifted_directions(w, w, arm, arm, {"camera_theta": d}, "two-arm")
    assert np.allclose(wi, w, atol=1e-12)  # the light arm did not move
    t, p = vector_to_spherical(wo)
    assert t[0] == pytest.approx(math.radians(40.0) + d, abs=1e-12)
    assert p[0] == pytest.approx(arm[0], abs=1e-12)
    # inplane: the camera on the light's side (same azimuth) comes down as the axis turns up
    _, wo = shifted_directions(w, w, arm, arm, {"camera_theta": d}, "inplane")
    assert vector_to_spherical(wo)[0][0] == pytest.approx(math.radians(40.0) - d, abs=1e-12)
    _, wo = shifted_directions(w, w, arm, arm, {"camera_phi": d}, "two-arm")
    assert vector_to_spherical(wo)[1][0] == pytest.approx(arm[0] + d, abs=1e-12)


def test_budget_components_become_nuisances_only_with_a_size() -> None:
    budget = [
        {"component": "scale (certificate)", "relative_sigma": {"G": 0.015}},
        {"component": "scale (lamp distance: 2σ_r/r)", "relative_sigma": {"G": 0.012}},
        {"component": "arm angles: encoder zeros (rig file estimate)", "kinematics": "inplane",
         "sigma_deg": {"light_theta": 0.2, "camera_theta": 0.3, "camera_phi": 0.2}},
        {"component": "arm angles: gear backlash and arm sag", "sigma_deg": None},
    ]  # fmt: skip
    shared = shared_errors(budget, ["G"])
    assert shared.scale_sigma == {"G": pytest.approx(math.hypot(0.015, 0.012), rel=1e-12)}
    # an inplane rig has no azimuth arms: no camera_phi_zero
    assert shared.angle_sigma_deg == {"light_theta_zero": 0.2, "camera_theta_zero": 0.3}
    assert shared.kinematics == "inplane"
    assert (
        shared_errors([{"component": "arm angles: encoder zeros", "sigma_deg": None}], ["G"])
        is None
    )


@pytest.fixture(scope="module")
def truth_table():
    wi, wo = isotropic_gonio_directions()
    table, _ = direct_samples(MATERIAL, wi, wo, rel_sigma=0.01, floor_sr=1e-3, channels="G", rng=3)
    return table, material_reference_parameters(MATERIAL)


def test_a_shared_scale_is_marginalised_by_the_chain(truth_table) -> None:
    """With a 2 % scale in the budget the chain samples ln s at its prior (the data cannot see
    s apart from the amplitudes): sd 0.02 within the chain's Monte-Carlo error (ESS ≥ 200:
    the sd's relative error is ≤ 1/√(2·200) = 5 %, bound 3 of those); kd's and ks's systematic
    part is their value × 2 % (law of total variance, first order in 2 %: within 15 %), their
    statistical part what the fit without a budget gives (within 25 %: two chains' sds); m,
    a shape parameter, gets no systematic part (< 10 % of its spread)."""
    table, _truth = truth_table
    opt = FitOptions(model="torrance-sparrow", model_options=OPTIONS, n_starts=2, seed=1,
                     mcmc=McmcOptions(walkers=24, max_steps=2000))  # fmt: skip
    budget = [{"component": "scale (test)", "type": "B", "relative_sigma": {"G": 0.02}}]
    with_budget = dataclasses.replace(
        table, metadata={**table.metadata, "gonio.budget": json.dumps(budget)}
    )
    fit = fit_samples(with_budget, opt)
    plain = fit_samples(table, opt)
    draws = fit.extras["space"].to_natural(fit.extras["draws"])
    i = fit.extras["space"].index("scale_G")
    ess = fit.diagnostics["ess"]["scale_G"]
    assert ess >= 200, ess
    assert np.std(np.log(draws[:, i])) == pytest.approx(0.02, rel=0.15)
    for name in ("kd_G", "ks_G"):
        p = fit.parameters[name]
        assert p["sd_sys"] == pytest.approx(0.02 * p["median"], rel=0.15), name
        stat = 0.5 * (plain.parameters[name]["p84"] - plain.parameters[name]["p16"])
        assert p["sd_stat"] == pytest.approx(stat, rel=0.25), name
        assert p["sd_stat"] ** 2 + p["sd_sys"] ** 2 == pytest.approx(p["sd_total"] ** 2)
    assert fit.parameters["m"]["sd_sys"] < 0.1 * fit.parameters["m"]["sd_total"]
    assert any("marginalised as nuisance" in w for w in fit.diagnostics["budget"])
    # The report's parameter table shows the split for every model parameter and says the
    # intervals hold the shared errors (they were marginalised), not "statistical only".
    from gonio.report.sections import parameter_table

    html_table = parameter_table(fit.to_dict(), {})
    assert "median ± 68 % (all errors)" in html_table and "systematic σ" in html_table
    assert "statistical only" not in html_table
    assert "(statistical)" in parameter_table(plain.to_dict(), {})


#: One realization, six quantities checked: a 95 % statement about the six together
#: (Bonferroni: each within its central 1 − 0.05/6 interval, |z| ≤ 2.64). Six separate 95 %
#: checks fail by chance on one realization in four — which this test did when the world's
#: camera began turning with its arm at θ_o = 0 (issue 43: the images there changed, so did the
#: realization; the three zeros sat 2.25, 2.42 and 2.34 sd high, together, as correlated
#: nuisances do). Over 12 other noise seeds the zeros' mean errors were +0.002 ± 0.003° (light
#: θ), +0.003 ± 0.003° (camera θ), +0.001 ± 0.006° (camera φ), 0 of 36 intervals missed.
Z_FAMILY_95 = 2.64


def _z(p: dict, truth: float) -> float:
    """(truth − median) in posterior sd, the sd from the central 95 % interval's width."""
    return (truth - p["median"]) / ((p["p97.5"] - p["p2.5"]) / 3.92)


def test_the_fit_recovers_the_arms_zero_errors_of_a_simulated_rig() -> None:
    """A simulated world whose arms' zeros are off by +0.5° (light elevation), −0.4° (camera
    elevation) and +0.5° (camera azimuth), on a rig file that states σ 0.3° for each and no
    calibrate-rig: the fit's nuisance estimates are within 20 % of the world's errors (the
    issue's bound for a first-order model: arms turned about the sample's centre, the
    irradiance's cos θ_i with them; measured 2–11 %) and, with kd, ks and m, hold the truth
    at 95 % together (Z_FAMILY_95), and the model fits (χ²/dof < 1.2: its spread at ≈ 6000
    samples is 0.018, so 1.2 is 11 sd — a slack for the footprint's own small effects)."""
    from acquisition.config import PlanConfig, load_rig
    from calibration.reduce import ReduceOptions, reduce_run
    from gonio.pipeline import AcquireSpec, acquire
    from simulator.scene import load_scene
    from simulator.truth import reference_parameters

    zeros = {"light_theta": 0.5, "camera_theta": -0.4, "camera_phi": 0.5}
    base = load_scene(REPO / "configs" / "scenes" / "demo.toml")
    scene = base.model_copy(
        update={"geometry": base.geometry.model_copy(update={"axis_zero_error_deg": zeros})}
    )
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    rig = rig.model_copy(
        update={
            "geometry": rig.geometry.model_copy(
                update={"axis_zero_sigma_deg": dict.fromkeys(zeros, 0.3)}
            )
        }
    )
    plan = PlanConfig(name="zeros", theta_i_deg=(25.0, 50.0), theta_o_deg=(0.0, 20.0, 40.0, 60.0),
                      delta_phi_deg=(180.0, 120.0), exposures_s=(0.002, 0.016))  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        acquire(run, AcquireSpec(rig=rig, plan=plan, scene=scene, progress=False, announce=False))
        table = reduce_run(run, ReduceOptions(bin_px=2, mode="center"))
    opt = FitOptions(model="torrance-sparrow", model_options=OPTIONS, channels=["G"],
                     mcmc=McmcOptions(walkers=24, max_steps=600), n_starts=2, seed=0)  # fmt: skip
    fit = fit_samples(table, opt)
    for axis, err in zeros.items():
        p = fit.parameters[f"{axis}_zero"]
        assert p["median"] == pytest.approx(err, rel=0.2), (axis, p["median"], err)
        assert abs(_z(p, err)) <= Z_FAMILY_95, (axis, p, err)
    truth = reference_parameters(base)
    for name in ("kd_G", "ks_G", "m"):
        p = fit.parameters[name]
        assert abs(_z(p, truth[name])) <= Z_FAMILY_95, (name, p, truth[name])
    assert fit.goodness["chi2_red"] < 1.2, fit.goodness
    # Not carried, the zeros are model error: χ²/dof far above 1, and the mismatch widening
    # makes m's interval at least 10 times wider than the one that carries them.
    old = fit_samples(table, opt.replace(shared_errors=False))
    assert old.goodness["chi2_red"] > 5, old.goodness

    def width(f) -> float:
        return f.parameters["m"]["p97.5"] - f.parameters["m"]["p2.5"]

    assert width(old) > 10 * width(fit), (width(old), width(fit))


#: Each shared error alone in the simulated world, at about 2σ of its budget (so its effect,
#: 0.3–3 % of f, stands far above DN rounding), with the value the fit's nuisance takes.
_WORLD_ERRORS = {
    "light_theta_zero": ({"axis_zero_error_deg": {"light_theta": 0.4}}, 0.4),
    "camera_theta_zero": ({"axis_zero_error_deg": {"camera_theta": 0.4}}, 0.4),
    "camera_phi_zero": ({"axis_zero_error_deg": {"camera_phi": 0.4}}, 0.4),
    "sample_tilt_y": ({"sample_tilt_deg": {"y": 0.4}}, 0.4),
    "camera_theta_sag": ({"compliance_deg": {"camera_theta": 0.4}}, 0.4),
    "camera_theta_play": ({"backlash_deg": {"camera_theta": 0.6}}, 0.6),
    "light_distance_mm": ({"light_distance_error_m": 0.006}, 6.0),
    # the world's dome is its own normal map (simulator.render.normal_texture), the fit's a tilt
    # per row at the pixel's point, R = the rig file's half side (25 mm)
    "sample_bow_um": ({"sample_bow_m": 0.0002}, 200.0),
    # 50 mm: ten times a lens' unknown pupil, so the effect (~1 %) stands above DN rounding
    "camera_distance_mm": ({"camera_distance_error_m": 0.05}, 50.0),
}


def test_the_nuisance_model_moves_f_as_the_simulated_world_does(tmp_path) -> None:
    """The fit's model of each shared error (fitting.nuisance.measured_geometry: the arms'
    directions turned, the lamp moved along its arm, the irradiance's cos θ_i and 1/r²) against
    the simulated world with that error alone (a noise-free run through the real acquisition
    and calibration, paired sample by sample with a run without it): the regression slope of
    the world's Δ ln f on the model's, over every sample of G, must be 1 within 3 % (the
    rotations are exact; what is left is second order in the angles and the pixel's point
    moving, ~0.1 % of the effect, and DN rounding), and the residual below a tenth of the
    effect. The model's f is gonio's Torrance-Sparrow at the scene's own parameters."""
    from fitting import models
    from fitting.nuisance import arm_deltas, arm_rows, measured_geometry, to_si
    from simulator.scene import GeometryTruth, load_scene
    from simulator.truth import reference_parameters
    from tests.support.effect_runs import effect_run, paired_rows

    truth = reference_parameters(load_scene(REPO / "configs" / "scenes" / "demo.toml"))
    model = models.get("torrance-sparrow", **OPTIONS)
    base = effect_run(tmp_path / "base", 0.0)
    rows = arm_rows(base, bow_half_side_m=0.025)
    for name, (world, value) in _WORLD_ERRORS.items():
        other = effect_run(tmp_path / name, 0.0, GeometryTruth(**world))
        a, b, good = paired_rows(base, other)
        good &= (base.f[a] > 0) & (base.channel[a].astype(str) == "G")
        # Away from the sample's edge (20 of its 25 mm half side): a camera further away sees
        # a smaller sample, so a pixel the lab puts just inside the edge sees the holder.
        good &= np.max(np.abs(rows["point"][a][:, :2]), axis=1) < 0.020
        idx = a[good]
        sub = {k: v[idx] for k, v in rows.items()}
        delta = {k: v[0] for k, v in arm_deltas(sub, {name: to_si(name, [value])}).items()}
        wi, wo, ratio = measured_geometry(base.wi[idx], base.wo[idx], sub, delta, "two-arm")
        params = {
            p: np.full(idx.size, truth[f"{p}_G" if p != "m" else p]) for p in ("kd", "ks", "m")
        }
        d_model = np.log(
            model.evaluate(params, wi, wo)
            * ratio
            / model.evaluate(params, base.wi[idx], base.wo[idx])
        )
        d_world = np.log(other.f[b][good] / base.f[a][good])
        slope = float(np.sum(d_model * d_world) / np.sum(d_model**2))
        resid = np.sqrt(np.mean((d_world - slope * d_model) ** 2))
        size = np.sqrt(np.mean(d_model**2))
        print(f"{name}: world/model slope {slope:.3f}, effect {100 * size:.2f} %, "
              f"residual {100 * resid:.3f} %")  # fmt: skip
        assert abs(slope - 1.0) < 0.03, (name, slope)
        assert resid < 0.1 * size, (name, resid, size)


def test_a_stated_bow_is_carried_with_positions_and_named_without() -> None:
    """The budget's "sample flatness (bow)" becomes the nuisance sample_bow_um (µm, prior σ
    from the rig file) only where the rows' places on the sample are known (the arms'
    positions); a rig that states no bow gets the component named as left out."""
    from acquisition.config import load_rig
    from calibration.reduce import _bow_component
    from fitting.budget import left_out_words

    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    stated = rig.model_copy(update={"sample": rig.sample.model_copy(update={"bow_sigma_m": 1e-4})})
    comp = _bow_component(stated)
    assert comp["bow_sigma_m"] == 1e-4 and comp["half_side_m"] == pytest.approx(0.025)
    shared = shared_errors([comp], ["G"], positions=True)
    assert shared.angle_sigma_deg == {"sample_bow_um": pytest.approx(100.0)}
    assert shared.bow_half_side_m == pytest.approx(0.025)
    assert shared.carried == ("sample flatness (bow)",)
    assert shared_errors([comp], ["G"], positions=False) is None
    unstated = _bow_component(rig)
    assert unstated["propagated"] is False
    assert "sample flatness (bow)" in left_out_words([unstated])[0]
    assert left_out_words([comp], shared.carried) == []


def test_the_flat_falloff_nuisance_divides_f_as_the_worlds_flat_does(tmp_path) -> None:
    """The fit's flat-source factor 1/(1 − a ρ/ρ_corner) (fitting.likelihood, ρ per row from its
    pixel and the intrinsics calibration writes into the budget) against the world's flat
    source of fall-off a = 5 % (simulator.camera.flat_source_profile, its own pixel grid and
    intrinsics): noise-free runs with and without it, paired sample by sample; the regression
    slope of the world's Δ ln f on the model's must be 1 within 3 % (what is left: the block's
    mean profile against its centre's, < 1e-4 of a, and DN rounding, ~0.05 % of f)."""
    from acquisition.config import load_rig
    from fitting.budget import read_budget
    from fitting.nuisance import arm_rows
    from tests.support.effect_runs import effect_run, paired_rows

    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    rig = rig.model_copy(
        update={"calibration": rig.calibration.model_copy(
            update={"flat_source_falloff_sigma": 0.02})}
    )  # fmt: skip
    falloff = 0.05
    base = effect_run(tmp_path / "base", 0.0, flat_falloff=0.0, rig=rig)
    bent = effect_run(tmp_path / "bent", 0.0, flat_falloff=falloff, rig=rig)
    shared = shared_errors(read_budget(base.metadata), ["G"], positions=True)
    assert "flat field source (fall-off)" in shared.carried
    assert shared.angle_sigma_deg["flat_falloff_pct"] == pytest.approx(2.0)
    rows = arm_rows(base, flat_field=shared.flat_field)
    a, b, good = paired_rows(base, bent)
    good &= base.f[a] > 0
    d_model = -np.log(1.0 - falloff * rows["field_r2"][a][good])
    d_world = np.log(bent.f[b][good] / base.f[a][good])
    slope = float(np.sum(d_model * d_world) / np.sum(d_model**2))
    print(f"flat falloff: world/model slope {slope:.3f}, effect up to "
          f"{100 * d_model.max():.2f} %")  # fmt: skip
    assert d_model.max() > 0.01
    assert abs(slope - 1.0) < 0.03, slope


def test_the_ambient_nuisance_adds_to_f_as_the_worlds_room_light_does(tmp_path) -> None:
    """The fit's additive term L_a·A · r²/(I cos θ_i) (fitting.likelihood, per row from the
    arms' positions and the intensity calibration writes into the budget) against the world's
    ambient light (a Mitsuba `constant` emitter of 0.02 W m⁻² sr⁻¹): noise-free runs with and
    without it, paired sample by sample. The world's Δf over the model's per-unit term is
    L_a·A(ω_o), A the sample's directional albedo: its median over L_a must lie in (0, 1], and
    its spread is A's variation with ω_o (the demo's diffuse + Beckmann blend: within 15 % of
    the median for 90 % of the samples), far less than the term's own range (×1.6 here)."""
    from acquisition.config import load_rig
    from fitting.budget import read_budget
    from fitting.likelihood import ChannelData, _ambient_rows
    from fitting.nuisance import arm_rows
    from simulator.scene import StrayLightSpec
    from tests.support.effect_runs import effect_run, paired_rows

    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    rig = rig.model_copy(
        update={"light": rig.light.model_copy(update={"ambient_sigma_W_m2_sr": 5e-4})}
    )
    radiance = 0.02
    base = effect_run(tmp_path / "base", 0.0, rig=rig)
    lit = effect_run(tmp_path / "lit", 0.0, rig=rig,
                     stray_light=StrayLightSpec(radiance_W_m2_sr=(radiance,) * 3))  # fmt: skip
    shared = shared_errors(read_budget(base.metadata), ["G"], positions=True)
    assert "ambient light (not from the lamp)" in shared.carried
    assert shared.angle_sigma_deg["ambient_mW"] == pytest.approx(0.5)
    a, b, good = paired_rows(base, lit)
    good &= (base.f[a] > 0) & (base.channel[a].astype(str) == "G")
    idx = a[good]
    rows = {k: v[idx] for k, v in arm_rows(base).items()}
    d = ChannelData("G", base.wi[idx], base.wo[idx], base.f[idx], base.sigma[idx],
                    base.theta_i[idx], base.theta_o[idx], np.zeros(idx.size, np.int8),
                    arm=rows)  # fmt: skip
    _ambient_rows(d, shared.ambient_intensity)
    albedo = (lit.f[b][good] - base.f[idx]) / d.arm["ambient_per_W"] / radiance
    med = float(np.median(albedo))
    spread = np.quantile(np.abs(albedo / med - 1.0), 0.9)
    term = d.arm["ambient_per_W"]
    print(f"ambient: L_a·A / L_a median {med:.3f}, 90 % within {100 * spread:.1f} %; the term "
          f"spans ×{term.max() / term.min():.2f}")  # fmt: skip
    assert 0.0 < med <= 1.0
    assert spread < 0.15

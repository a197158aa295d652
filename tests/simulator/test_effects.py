"""The "Effects" acceptance (issue 4): every optional effect is absent from the plan and never
executed when disabled, and enabling it changes the output only as expected.

Instruments: the sensor records each stage it runs (``Sensor.stage_counts``); the renderer reports
what Mitsuba actually loaded, read back from the Mitsuba scene object (``Renderer.loaded``:
integrator class, emitter classes, shapes) and counts render-side effects per render
(``Renderer.effect_counts``).

Expected changes come from independent physics computed here in numpy: cos⁴ vignetting from the
pixel rays, the dark-current offset dark·t/K, Poisson and read-noise variances, the CFA site
channels, ρ·L_amb for stray light on a Lambertian sample, the shadow of a rim from ray/plane
geometry, and the closed-form irradiance of a Lambertian disk lamp on a parallel plane.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from simulator.planner import plan_effects
from simulator.render import Renderer
from simulator.scene import Scene, SensorSpec
from simulator.sensor import Sensor, bayer_select, cos4_vignetting

VARIANT = None  # the planner's own choice (llvm_ad_rgb when usable)
RHO = 0.5
SIZE_M = 0.05
HALF = SIZE_M / 2


def _sph(theta_deg, phi_deg, r=1.0):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return r * np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def _scene(**kw) -> Scene:
    base = {
        "material": {"type": "diffuse", "reflectance": [RHO, RHO, RHO]},
        "sample": {"size_m": SIZE_M},
        "light": {"intensity_W_sr": [1.0, 1.0, 1.0]},
        # 0.7 m overhead, 3.6° wide: every pixel sees the sample (half-width 2.05° at 0.7 m).
        "camera": {"resolution": [33, 33], "fov_deg": 3.6},
    }
    base.update(kw)
    return Scene.model_validate(base)


CAM = np.array([0.0, 0.0, 0.7])


@functools.cache
def _base_renderer() -> Renderer:
    return Renderer(_scene())


# --- sensor effects -------------------------------------------------------------------------

INTR = {"fx": 200.0, "fy": 200.0, "cx": 31.5, "cy": 31.5}
QUIET = dict(noise=False, read_noise_e=0.0, black_level_dn=64.0, gain_e_per_dn=2.0)
SENSOR_EFFECTS = {
    "vignetting": {"vignetting": True},
    "prnu": {"prnu": 0.01},
    "dsnu": {"dsnu_e": 20.0},
    "dark_current": {"dark_current_e_s": 1000.0},
    "bayer": {"bayer": "RGGB"},
    "shot_noise": {"noise": True},
    "read_noise": {"noise": True, "read_noise_e": 10.0},
}


def _flat(level_w=0.02):
    # A flat radiance with a different value per channel (so a CFA mix-up shows).
    return np.broadcast_to(np.array([1.0, 0.7, 0.4]) * level_w, (64, 64, 3)).copy()


def _sensor(spec: SensorSpec, seed=0) -> Sensor:
    return Sensor(spec, 4.0, rng=seed, intrinsics=INTR)


@pytest.mark.parametrize("effect", list(SENSOR_EFFECTS))
def test_disabled_sensor_effect_absent_and_never_run(effect):
    off = SensorSpec(**QUIET)
    on = SensorSpec(**{**QUIET, **SENSOR_EFFECTS[effect]})
    scene_off = _scene(sensor=off.model_dump())
    scene_on = _scene(sensor=on.model_dump())
    assert effect not in plan_effects(scene_off, variant="scalar_rgb").sensor_stages
    assert effect in plan_effects(scene_on, variant="scalar_rgb").sensor_stages
    s_off, s_on = _sensor(off), _sensor(on)
    for _ in range(3):
        s_off.capture(_flat(), 0.01)
        s_on.capture(_flat(), 0.01)
    assert s_off.stage_counts[effect] == 0
    assert s_on.stage_counts[effect] == 3
    # The plan lists exactly what ran, in order.
    assert s_on.executed_stages == plan_effects(scene_on, variant="scalar_rgb").sensor_stages


def _e(dn, spec):
    return (dn.astype(float) - spec.black_level_dn) * spec.gain_e_per_dn


def test_vignetting_is_cos4_of_the_chief_ray():
    off = SensorSpec(**QUIET)
    on = SensorSpec(**{**QUIET, "vignetting": True})
    L = _flat(0.05)
    e_off = _e(_sensor(off).capture(L, 0.01), off)
    e_on = _e(_sensor(on).capture(L, 0.01), on)
    # Independent cos α: angle between each pixel's ray (u−cx, v−cy, f) and the optical axis.
    vv, uu = np.mgrid[0:64, 0:64]
    d = np.stack([(uu - 31.5) / 200.0, (vv - 31.5) / 200.0, np.ones_like(uu, float)], -1)
    cos_a = 1.0 / np.linalg.norm(d, axis=-1)
    # Rounding to DN: ±0.5 DN = ±1 e⁻ on each of two ~20k e⁻ values.
    np.testing.assert_allclose(e_on, e_off * cos_a[..., None] ** 4, atol=2.0 + 1e-9)
    assert np.ptp(cos_a) > 0.01  # the check can see vignetting at all
    np.testing.assert_allclose(cos4_vignetting((64, 64), INTR), cos_a**4, rtol=1e-12)


def test_prnu_dsnu_dark_change_only_as_expected():
    # ~20k e⁻ in red, ~8k in blue: DN rounding (±1 e⁻) is ≤ 1.3e-4 of the signal.
    L = _flat(0.05)
    t = 0.19
    off = SensorSpec(**QUIET)
    e0 = _e(_sensor(off).capture(L, t), off)
    assert 5e3 < e0.min() and e0.max() < off.full_well_e
    # PRNU: multiplicative with mean 1 and spread σ = prnu (Gaussian fixed pattern).
    spec = SensorSpec(**{**QUIET, "prnu": 0.01})
    ratio = _e(_sensor(spec).capture(L, t), spec) / e0
    # N = 12288 samples: mean within 5σ/√N + rounding (≤ 2/8000) of 1, std within 10% (std
    # error 1/√(2N) ≈ 0.6%).
    assert abs(ratio.mean() - 1) < 5 * 0.01 / np.sqrt(ratio.size) + 2.5e-4
    assert abs(ratio.std() / 0.01 - 1) < 0.1
    # DSNU: additive, mean 0, σ = dsnu_e.
    spec = SensorSpec(**{**QUIET, "dsnu_e": 20.0})
    diff = _e(_sensor(spec).capture(L, t), spec) - e0
    # ±1 e⁻ rounding per value on top of the 5σ/√N sampling error of the mean.
    assert abs(diff.mean()) < 5 * 20.0 / np.sqrt(diff.size) + 2.0
    assert abs(diff.std() / 20.0 - 1) < 0.1
    # Dark current: a uniform offset dark·t electrons (±1 e⁻ rounding per value).
    spec = SensorSpec(**{**QUIET, "dark_current_e_s": 1000.0})
    diff = _e(_sensor(spec).capture(L, 0.02), spec) - _e(_sensor(off).capture(L, 0.02), off)
    np.testing.assert_allclose(diff, 1000.0 * 0.02, atol=2.0 + 1e-9)


def test_shot_and_read_noise_variances():
    # Low signal (~100, 70, 40 e⁻) so read noise is a large share of the variance.
    L = _flat(5e-3)
    quiet = SensorSpec(**QUIET)
    mu_e = _e(_sensor(quiet).capture(L, 0.01), quiet)
    shot = SensorSpec(**{**QUIET, "noise": True})
    both = SensorSpec(**{**QUIET, "noise": True, "read_noise_e": 10.0})
    e_shot = _e(_sensor(shot, seed=1).capture(L, 0.01), shot)
    e_both = _e(_sensor(both, seed=2).capture(L, 0.01), both)
    q = shot.gain_e_per_dn**2 / 12.0  # DN rounding variance in e⁻²
    for c in range(3):
        mu = mu_e[..., c].mean()
        # Poisson: Var = μ; plus read noise σ². Sample variance of N = 4096: rel. σ √(2/N) ≈ 2%
        # → 10% is 5σ.
        assert abs(e_shot[..., c].var() / (mu + q) - 1) < 0.1
        assert abs(e_both[..., c].var() / (mu + 100.0 + q) - 1) < 0.1
        assert abs(e_shot[..., c].mean() / mu - 1) < 0.02


def test_bayer_takes_the_site_channel():
    L = _flat(0.05)
    off = SensorSpec(**QUIET)
    on = SensorSpec(**{**QUIET, "bayer": "RGGB"})
    rgb = _sensor(off).capture(L, 0.01)
    mosaic = _sensor(on).capture(L, 0.01)
    assert mosaic.shape == (64, 64)
    # RGGB: (even, even) red, (odd, odd) blue, the rest green — written out independently.
    np.testing.assert_array_equal(mosaic[0::2, 0::2], rgb[0::2, 0::2, 0])
    np.testing.assert_array_equal(mosaic[1::2, 1::2], rgb[1::2, 1::2, 2])
    np.testing.assert_array_equal(mosaic[0::2, 1::2], rgb[0::2, 1::2, 1])
    np.testing.assert_array_equal(mosaic[1::2, 0::2], rgb[1::2, 0::2, 1])
    np.testing.assert_array_equal(bayer_select(rgb, "RGGB"), mosaic)


# --- render-side effects --------------------------------------------------------------------


def test_baseline_loads_no_optional_effect():
    r = _base_renderer()
    plan = r.plan
    assert plan.render_effects == []
    assert (plan.integrator, plan.spp) == ("direct", 1)
    assert r.loaded["integrator"] == "DirectIntegrator"
    assert r.loaded["emitters"] == ["PointLight"]
    assert r.loaded["shapes"] == ["Rectangle:sample"]
    before = dict(r.effect_counts)
    r.render(_sph(30, 0, 0.5), CAM)
    assert r.effect_counts["render"] == before.get("render", 0) + 1
    for eff in ("stray_light", "holder", "path_integrator", "light_area", "light_spot",
                "beam_profile", "sample_bow"):  # fmt: skip
        assert r.effect_counts[eff] == 0


def test_stray_light_adds_exactly_rho_l_amb_on_lambertian():
    l_amb = (0.02, 0.05, 0.1)
    r = Renderer(_scene(stray_light={"radiance_W_m2_sr": l_amb}))
    assert "stray_light" in r.plan.render_effects
    assert "ConstantBackgroundEmitter" in r.loaded["emitters"]
    # Lambertian, no holder: BSDF sampling returns exactly ρ·L_amb, so no spp is needed.
    assert r.spp == 1
    base = _base_renderer()
    for light in (_sph(0, 0, 0.5), _sph(60, 45, 0.4)):
        with_amb = r.render(light, CAM)
        without = base.render(light, CAM)
        # ∫ ρ/π · L_amb · cos θ dω over the hemisphere = ρ·L_amb; float32 → 1e-5 relative.
        np.testing.assert_allclose(
            with_amb - without, np.broadcast_to(RHO * np.array(l_amb), without.shape), rtol=2e-4
        )
    assert r.effect_counts["stray_light"] == 2
    # The lamp level scales the lamp only, never the ambient term.
    half = r.render(_sph(0, 0, 0.5), CAM, intensity_scale=0.5)
    full_lamp = base.render(_sph(0, 0, 0.5), CAM)
    np.testing.assert_allclose(half, 0.5 * full_lamp + RHO * np.array(l_amb), rtol=2e-4)


def _shadowed(points, light, wall_x, height):
    """Points on z = 0 whose ray to the light crosses the +x wall's inner face below its top."""
    t = (wall_x - points[..., 0]) / (light[0] - points[..., 0])  # ray parameter at x = wall_x
    z = t * light[2]
    return (light[0] > wall_x) & (z < height)


def test_black_holder_shadows_only_pixels_in_its_shadow():
    h = 0.01
    holder = {"rim_height_m": h, "wall_thickness_m": 0.005, "reflectance": [0.0, 0.0, 0.0]}
    r = Renderer(_scene(holder=holder))
    # A black rim only shadows: the direct integrator suffices, spp stays 1.
    assert (r.plan.integrator, r.plan.spp) == ("direct", 1)
    assert r.loaded["integrator"] == "DirectIntegrator"
    assert sum(s.startswith("Cube:holder") for s in r.loaded["shapes"]) == 4
    light = _sph(60.0, 0.0, 0.5)  # from +x: the +x wall shadows a 16 mm strip
    img = r.render(light, CAM)
    ref = _base_renderer().render(light, CAM)
    geo = r.pixel_geometry(light, CAM)
    shadow = _shadowed(geo["point_m"], light, HALF, h)
    # Keep pixel centres off the shadow edge (1e-4 m ≈ 1/30 pixel footprint).
    edge = np.abs(geo["point_m"][..., 0] - (HALF - h * (light[0] - HALF) / light[2]))
    clear = edge > 1e-4
    assert shadow[clear].sum() > 50 and (~shadow[clear]).sum() > 50
    np.testing.assert_array_equal(img[clear & shadow], 0.0)
    np.testing.assert_allclose(img[clear & ~shadow], ref[clear & ~shadow], rtol=1e-6)
    assert r.effect_counts["holder"] == 1 and r.effect_counts["path_integrator"] == 0


def test_reflecting_holder_uses_path_and_only_adds_light():
    h = 0.01
    black = {"rim_height_m": h, "wall_thickness_m": 0.005, "reflectance": [0.0, 0.0, 0.0]}
    white = {**black, "reflectance": [0.8, 0.8, 0.8]}
    scene = _scene(holder=white)
    r = Renderer(scene)
    plan = r.plan
    assert plan.integrator == "path" and plan.max_depth >= 3
    assert r.loaded["integrator"] == "PathIntegrator"
    assert r.loaded["max_depth"] == plan.max_depth
    assert plan.spp > 1 and "path_integrator" in plan.render_effects
    light = _sph(60.0, 0.0, 0.5)
    img = r.render(light, CAM)
    # Same spp: at spp > 1 the stratified sampler averages over the pixel area.
    dark = Renderer(_scene(holder=black), spp=r.spp).render(light, CAM)
    geo = r.pixel_geometry(light, CAM)
    shadow = _shadowed(geo["point_m"], light, HALF, h)
    # Interreflection only adds light (every path contribution is ≥ 0) ...
    assert np.all(img >= dark * (1 - 1e-6) - 1e-9)
    # ... and lights the rim's shadow, which direct lighting leaves black.
    assert img[shadow].mean() > 0
    assert img[~shadow].mean() > dark[~shadow].mean()
    # The indirect light is a small fraction: it cannot exceed what the wall could send at
    # most, ρ_s · ρ_h · (lamp irradiance on the wall face) / π over ≤ half the hemisphere.
    e_wall = 1.0 * abs(light[0] - HALF) / np.linalg.norm(light - [HALF, 0, h / 2]) ** 3
    assert img[shadow].max() <= RHO * 0.8 * e_wall / np.pi


def _disk_irradiance(L, a, height, rho):
    """Irradiance at a point of a plane parallel to a Lambertian disk (radius a, radiance L),
    at height ``height`` and lateral offset ρ from its axis (Howell, view factor C-41):
    E = πL/2 · (1 − (h² + ρ² − a²) / √((h² + ρ² + a²)² − 4a²ρ²))."""
    s = height**2 + rho**2
    return np.pi * L / 2 * (1 - (s - a**2) / np.sqrt((s + a**2) ** 2 - 4 * a**2 * rho**2))


def test_area_light_spp_from_noise_target_and_disk_irradiance():
    # Point lamp: deterministic, spp 1, no area emitter loaded.
    base = _base_renderer()
    assert base.spp == 1 and "AreaLight" not in base.loaded["emitters"]
    a, d, eps = 0.1, 0.5, 0.01
    scene = _scene(
        light={"type": "area", "radius_m": a, "intensity_W_sr": [1.0, 1.0, 1.0]},
        render={"target_rel_noise": eps, "nominal_light_distance_m": d},
    )
    r = Renderer(scene)
    assert "AreaLight" in r.loaded["emitters"] and r.plan.spp > 1
    assert r.plan.spp == r.spp and "light_area" in r.plan.render_effects
    # Camera off axis and below the lamp, so the 10 cm disk does not hide the sample.
    cam = _sph(45.0, 0.0, 0.6)
    img = r.render([0.0, 0.0, d], cam)[..., 1]
    geo = r.pixel_geometry([0.0, 0.0, d], cam)
    rho_xy = np.hypot(geo["point_m"][..., 0], geo["point_m"][..., 1])
    L = 1.0 / (np.pi * a**2)  # I = L·A along the normal
    truth = RHO / np.pi * _disk_irradiance(L, a, d, rho_xy)
    # At spp > 1 a pixel averages its footprint (≈ 1 mm here): stay 2 mm inside the edge.
    m = geo["on_sample"] & np.all(np.abs(geo["point_m"][..., :2]) < HALF - 0.002, axis=-1)
    assert m.sum() > 500
    rel = img[m] / truth[m] - 1
    # The planned spp meets the noise target (rms relative error per pixel ≤ ε) ...
    assert np.sqrt(np.mean(rel**2)) <= eps
    # ... and the disk differs from the point lamp as 1/(1 + (a/d)²) on axis (docs/design.md §7):
    point = RHO / np.pi * 1.0 / d**2
    assert abs(truth[16, 16] / point - 1 / (1 + (a / d) ** 2)) < 1e-9
    assert abs(img[16, 16] / point - 1 / (1 + (a / d) ** 2)) < 3 * eps
    assert rho_xy[16, 16] < 1e-9  # the centre pixel sees the origin


def test_spot_light_equals_point_inside_beam_and_is_dark_outside_cutoff():
    spot = {"type": "spot", "cutoff_deg": 1.5, "beam_width_deg": 1.0, "intensity_W_sr": [1, 1, 1]}
    r = Renderer(_scene(light=spot))
    assert r.spp == 1 and r.loaded["emitters"] == ["SpotLight"]
    light = np.array([0.0, 0.0, 0.5])
    img = r.render(light, CAM)
    ref = _base_renderer().render(light, CAM)
    geo = r.pixel_geometry(light, CAM)
    gamma = np.degrees(np.arccos(geo["wi"][..., 2]))  # angle off the spot axis (−z)
    inside, outside = gamma < 0.98, gamma > 1.52
    assert inside.sum() > 20 and outside.sum() > 20
    np.testing.assert_allclose(img[inside], ref[inside], rtol=1e-5)
    np.testing.assert_array_equal(img[outside], 0.0)
    between = ~inside & ~outside
    assert np.all(img[between] <= ref[between] * (1 + 1e-5))


def test_planned_path_depth_loses_less_than_the_noise_target():
    # Energy beyond the planned depth (truncation bias) must stay under target_rel_noise: compare
    # with a render at the cap depth 16 (same seed and spp), averaged over the image.
    white = {"rim_height_m": 0.01, "wall_thickness_m": 0.005, "reflectance": [0.9, 0.9, 0.9]}
    scene = _scene(holder=white, material={"type": "diffuse", "reflectance": [0.9, 0.9, 0.9]})
    r = Renderer(scene)
    deep = Renderer(scene, plan=dataclasses.replace(r.plan, max_depth=16))
    assert r.plan.max_depth < 16 and deep.loaded["max_depth"] == 16
    light = _sph(60.0, 0.0, 0.5)
    a, b = r.render(light, CAM).mean(), deep.render(light, CAM).mean()
    assert b >= a * (1 - 1e-6)  # deeper paths only add energy (up to sampling differences)
    assert (b - a) / b <= scene.render.target_rel_noise


def test_a_beam_profile_with_stray_light_is_refused():
    """Mitsuba's projector takes no new intensity once loaded, and with stray light the lamp's
    level must change inside the scene: the combination is refused when the scene is read."""
    import pydantic

    from simulator.scene import Scene

    data = {"light": {"type": "point", "beam_falloff": 0.05},
            "stray_light": {"radiance_W_m2_sr": [0.01, 0.01, 0.01]}}  # fmt: skip
    with pytest.raises(pydantic.ValidationError, match="beam_falloff cannot be combined"):
        Scene.model_validate(data)
    Scene.model_validate({"light": data["light"]})  # either alone is fine
    Scene.model_validate({"stray_light": data["stray_light"]})

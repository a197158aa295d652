"""Simulated camera renderer: radiometry, camera model and ground-truth BSDF against analytic truth.

Truth here never comes from the renderer's own arithmetic: Lambertian radiance is ρ/π·I·cosθ_i/r²
computed from geometry in numpy; the camera model is checked by locating a small sample in the
rendered image; BSDF truth is Lambert's ρ/π or Mitsuba's own bsdf.eval.
"""

from __future__ import annotations

import functools
import os
import sys

import numpy as np
import pytest

from simulator import variant as variant_mod
from simulator.planner import plan_effects
from simulator.render import Renderer, camera_intrinsics, world_to_camera_cv
from simulator.scene import (
    BlendMaterial,
    CameraSpec,
    DiffuseMaterial,
    RoughConductorMaterial,
    RoughPlasticMaterial,
    SampleSpec,
    Scene,
    SensorSpec,
)

RHO = (0.8, 0.5, 0.2)
I_W_SR = (10.0, 7.0, 3.0)


def _sph(theta_deg, phi_deg, r=1.0):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return r * np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


@functools.cache
def _lambert_renderer():
    # Odd resolution: the centre pixel's ray passes exactly through the camera target.
    scene = Scene(
        material=DiffuseMaterial(reflectance=RHO),
        sample=SampleSpec(size_m=0.2),
        light={"intensity_W_sr": I_W_SR},
        camera=CameraSpec(resolution=(33, 33), fov_deg=10.0),
    )
    return Renderer(scene)


@pytest.mark.parametrize("theta_i_deg", [0.0, 30.0, 60.0, 80.0])
def test_lambertian_radiance_centre_and_every_pixel(theta_i_deg):
    r = _lambert_renderer()
    light = _sph(theta_i_deg, 200.0, r=0.5)
    cam = _sph(35.0, 20.0, r=0.7)
    img = r.render(light, cam)
    # Centre pixel sees the origin: L = ρ/π · I · cos θ_i / r² (rendering equation, point light).
    d = light / np.linalg.norm(light)
    truth_centre = np.array(RHO) / np.pi * np.array(I_W_SR) * d[2] / (light @ light)
    # 1e-3: the renderer is float32 (~1e-6) and exact for a point light at one centred sample.
    np.testing.assert_allclose(img[16, 16], truth_centre, rtol=1e-3)

    # Every pixel: intersect its documented pinhole ray with z = 0 and evaluate the same formula.
    origin, dirs = r.pixel_rays(cam)
    t = -origin[2] / dirs[..., 2]
    p = origin + t[..., None] * dirs
    to_light = light - p
    r2 = np.einsum("...k,...k", to_light, to_light)
    cos_i = to_light[..., 2] / np.sqrt(r2)
    truth = np.array(RHO) / np.pi * np.array(I_W_SR) * (cos_i / r2)[..., None]
    on_sample = np.all(np.abs(p[..., :2]) < 0.1 - 0.005, axis=-1)  # stay off the sample edge
    geo = r.pixel_geometry(light, cam)
    np.testing.assert_allclose(geo["point_m"][on_sample], p[on_sample], atol=1e-12)
    np.testing.assert_allclose(geo["wi"][on_sample, 2], cos_i[on_sample], rtol=1e-12)
    assert np.all(geo["on_sample"][on_sample])
    assert on_sample.sum() > 500
    np.testing.assert_allclose(img[on_sample], truth[on_sample], rtol=1e-3)


def test_camera_model_projects_a_point_to_its_pixel():
    # A 1 cm sample, integrated with the 8×8 midpoint rule per pixel; the intensity centroid of
    # its image must sit on the OpenCV projection of the sample centre. Perspective and the 1/r²
    # gradient over 1 cm shift the centroid by ≈ 0.01 px, hence the 0.05 px tolerance.
    scene = Scene(
        sample=SampleSpec(size_m=0.01), camera=CameraSpec(resolution=(80, 60), fov_deg=20.0)
    )
    r = Renderer(scene, spp=64)
    k = camera_intrinsics(scene)
    vv, uu = np.mgrid[0:60, 0:80]
    cases = [
        ((0.2, -0.3, 0.5), (0.03, 0.05, -0.01)),
        ((-0.1, 0.25, 0.4), (-0.02, -0.03, 0.0)),
        ((0.0, 0.001, 0.6), (0.02, 0.015, 0.0)),  # near-normal view: the up = +y branch
    ]
    for cam, target in cases:
        img = r.render((0.0, 0.0, 0.5), cam, target)[..., 1]
        w = img / img.sum()
        rot, t = world_to_camera_cv(cam, target)
        x = rot @ np.zeros(3) + t
        u_pred = k["fx"] * x[0] / x[2] + k["cx"]
        v_pred = k["fy"] * x[1] / x[2] + k["cy"]
        assert abs((w * uu).sum() - u_pred) < 0.05, (cam, target)
        assert abs((w * vv).sum() - v_pred) < 0.05, (cam, target)
    # Target off the sample: the sample is not at the image centre (the test can fail).
    assert abs(u_pred - k["cx"]) > 3


def test_truth_bsdf_lambert_and_horizon():
    r = _lambert_renderer()
    rng = np.random.default_rng(1)
    wi = rng.normal(size=(200, 3))
    wo = rng.normal(size=(200, 3))
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    f = r.truth_bsdf(wi, wo)
    above = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    np.testing.assert_allclose(
        f[above], np.broadcast_to(np.array(RHO) / np.pi, f[above].shape), rtol=1e-6
    )
    assert np.all(f[~above] == 0)


def test_truth_bsdf_matches_rendered_radiance_glossy():
    # roughplastic is not constant, so dividing by the wrong cosine (θ_o instead of θ_i) or
    # swapping ω_i/ω_o conventions would show up as a factor cos θ_i / cos θ_o ≈ 2.
    scene = Scene(
        material=RoughPlasticMaterial(alpha=0.3, diffuse_reflectance=(0.3, 0.4, 0.5)),
        sample=SampleSpec(size_m=0.2),
        camera=CameraSpec(resolution=(33, 33), fov_deg=10.0),
    )
    r = Renderer(scene)
    light = _sph(70.0, 180.0, r=0.5)
    cam = _sph(30.0, 0.0, r=0.7)
    img = r.render(light, cam)
    wi = light / np.linalg.norm(light)
    wo = cam / np.linalg.norm(cam)
    f = r.truth_bsdf(wi[None], wo[None])[0]
    truth = f * np.array(scene.light.intensity_W_sr) * wi[2] / (light @ light)
    np.testing.assert_allclose(img[16, 16], truth, rtol=1e-3)

    # Every pixel on the sample: truth at that pixel's own (ω_i, ω_o) and distance.
    geo = r.pixel_geometry(light, cam)
    on = geo["on_sample"] & np.all(np.abs(geo["point_m"][..., :2]) < 0.095, axis=-1)
    f_px = r.truth_bsdf(geo["wi"][on], geo["wo"][on])
    cos_i = geo["wi"][on][:, 2]
    truth_px = (
        f_px * np.array(scene.light.intensity_W_sr) * (cos_i / geo["r_light_m"][on] ** 2)[:, None]
    )
    assert on.sum() > 500
    np.testing.assert_allclose(img[on], truth_px, rtol=1e-3)


def test_blend_convention():
    # blend = (1 − w)·first + w·second: checked against Lambert for both nested albedos.
    w = 0.25
    scene = Scene(
        material=BlendMaterial(
            weight=w,
            first=DiffuseMaterial(reflectance=(0.8, 0.8, 0.8)),
            second=DiffuseMaterial(reflectance=(0.2, 0.4, 0.0)),
        )
    )
    r = Renderer(scene)
    f = r.truth_bsdf(np.array([[0.0, 0.6, 0.8]]), np.array([[0.0, 0.0, 1.0]]))[0]
    expect = ((1 - w) * np.array([0.8, 0.8, 0.8]) + w * np.array([0.2, 0.4, 0.0])) / np.pi
    np.testing.assert_allclose(f, expect, rtol=1e-6)


def test_intensity_scale_is_linear():
    r = _lambert_renderer()
    a = r.render(_sph(30, 0, 0.5), _sph(20, 90, 0.7))
    b = r.render(_sph(30, 0, 0.5), _sph(20, 90, 0.7), intensity_scale=2.5)
    np.testing.assert_allclose(b, 2.5 * a, rtol=1e-6)


def test_variant_override_and_probe(monkeypatch):
    monkeypatch.setenv(variant_mod.ENV_OVERRIDE, "scalar_rgb")
    variant_mod.choose_variant.cache_clear()
    try:
        assert variant_mod.choose_variant() == "scalar_rgb"
    finally:
        variant_mod.choose_variant.cache_clear()
    ok, reason = variant_mod.probe_variant("scalar_rgb", env=dict(os.environ))
    assert ok, reason
    ok, reason = variant_mod.probe_variant("no_such_variant", env=dict(os.environ))
    assert not ok and reason


def test_planner_lists_only_enabled_stages():
    plain = plan_effects(Scene(sensor=SensorSpec(noise=False, read_noise_e=0)), variant="x")
    assert plain.integrator == "direct" and plain.spp == 1
    assert plain.sensor_stages == ["irradiance", "photons", "full_well", "adc"]
    assert set(plain.cost_estimate_ms) == {"render", *plain.sensor_stages}
    full = plan_effects(
        Scene(
            sensor=SensorSpec(
                vignetting=True, bayer="RGGB", prnu=0.01, dark_current_e_s=5, dsnu_e=1
            )
        ),
        variant="llvm_ad_rgb",
    )
    for st in ("vignetting", "bayer", "prnu", "dark_current", "dsnu", "shot_noise", "read_noise"):
        assert st in full.sensor_stages and st not in plain.sensor_stages
    assert "total" in full.describe()


def _beckmann_rational_g1(cos_t, alpha):
    """Walter et al. 2007, eq. 27 (the rational Smith G1 Mitsuba uses for Beckmann)."""
    tan_t = np.sqrt(1 - cos_t**2) / cos_t
    a = 1.0 / (alpha * tan_t)
    g = (3.535 * a + 2.181 * a**2) / (1 + 2.276 * a + 2.577 * a**2)
    return np.where(a < 1.6, g, 1.0)


def _ggx_g1(cos_t, alpha):
    tan2 = (1 - cos_t**2) / cos_t**2
    return 2.0 / (1.0 + np.sqrt(1.0 + alpha**2 * tan2))


@pytest.mark.parametrize("distribution", ["beckmann", "ggx"])
def test_truth_bsdf_roughconductor_matches_published_microfacet_formula(distribution):
    # Independent microfacet BRDF (Walter et al. 2007): f = F·D·G1(i)·G1(o) / (4 cosθ_i cosθ_o),
    # F ≡ 1 for the "none" conductor. Float32 evaluation in Mitsuba → rtol 1e-4.
    alpha = 0.3
    r = Renderer(Scene(material=RoughConductorMaterial(alpha=alpha, distribution=distribution)))
    rng = np.random.default_rng(4)
    th_i, th_o = rng.uniform(0.05, 1.3, (2, 300))
    ph_i, ph_o = rng.uniform(0, 2 * np.pi, (2, 300))
    wi = np.stack([np.sin(th_i) * np.cos(ph_i), np.sin(th_i) * np.sin(ph_i), np.cos(th_i)], -1)
    wo = np.stack([np.sin(th_o) * np.cos(ph_o), np.sin(th_o) * np.sin(ph_o), np.cos(th_o)], -1)
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    c_h = h[:, 2]
    tan2_h = (1 - c_h**2) / c_h**2
    if distribution == "beckmann":
        d = np.exp(-tan2_h / alpha**2) / (np.pi * alpha**2 * c_h**4)
        g = _beckmann_rational_g1(wi[:, 2], alpha) * _beckmann_rational_g1(wo[:, 2], alpha)
    else:
        d = alpha**2 / (np.pi * c_h**4 * (alpha**2 + tan2_h) ** 2)
        g = _ggx_g1(wi[:, 2], alpha) * _ggx_g1(wo[:, 2], alpha)
    expect = d * g / (4 * wi[:, 2] * wo[:, 2])
    f = r.truth_bsdf(wi, wo)
    np.testing.assert_allclose(f, np.repeat(expect[:, None], 3, axis=1), rtol=1e-4, atol=1e-6)


def test_roughconductor_eta_k_fresnel_at_normal_incidence():
    # docs/design.md §6: Au (η, k) → F0 = (0.9667, 0.8022, 0.3240). At ω_i = ω_o = +z: D = 1/(π α²),
    # G = 1, so f = F0 / (4 π α²).
    alpha = 0.2
    au = RoughConductorMaterial(
        alpha=alpha, eta=(0.1431, 0.3750, 1.4425), k=(3.9832, 2.3857, 1.6032)
    )
    r = Renderer(Scene(material=au))
    f = r.truth_bsdf(np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, 1.0]]))[0]
    np.testing.assert_allclose(f * 4 * np.pi * alpha**2, [0.9667, 0.8022, 0.3240], atol=1e-4)


def test_variant_falls_back_with_one_note(monkeypatch, caplog):
    # A failing probe (as with LLVM 15/16) must give scalar_rgb and log the reason exactly once.
    calls = []

    def failing_probe(variant, env=None, timeout_s=120.0):
        calls.append(env)
        return False, "probe exit code -6: simulated abort"

    monkeypatch.delenv(variant_mod.ENV_OVERRIDE, raising=False)
    monkeypatch.setenv(variant_mod.PROBED_ENV, "")  # no parent's answer (and restored after)
    monkeypatch.setattr(variant_mod, "probe_variant", failing_probe)
    variant_mod.choose_variant.cache_clear()
    try:
        with caplog.at_level("WARNING", logger=variant_mod.__name__):
            assert variant_mod.choose_variant() == "scalar_rgb"
            assert variant_mod.choose_variant() == "scalar_rgb"
    finally:
        variant_mod.choose_variant.cache_clear()
    notes = [r for r in caplog.records if "llvm variant unavailable" in r.getMessage()]
    assert len(notes) == 1 and "simulated abort" in notes[0].getMessage()
    assert calls  # the probe really was consulted
    # the answer is passed on to the processes this one starts, which do not probe again
    assert os.environ[variant_mod.PROBED_ENV] == f"llvm_ad_rgb=scalar_rgb@{sys.executable}"
    calls.clear()
    variant_mod.choose_variant.cache_clear()
    try:
        assert variant_mod.choose_variant() == "scalar_rgb" and calls == []
        # an answer for another interpreter is not taken
        monkeypatch.setenv(variant_mod.PROBED_ENV, "llvm_ad_rgb=llvm_ad_rgb@/elsewhere/python")
        variant_mod.choose_variant.cache_clear()
        assert variant_mod.choose_variant() == "scalar_rgb" and calls  # probed again
    finally:
        variant_mod.choose_variant.cache_clear()

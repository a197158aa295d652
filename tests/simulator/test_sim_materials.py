"""Simulator materials: a measured RGL tensor BSDF and a `fitting.models` model as a Python BSDF.

Independent truth: for the model material, the pixel radiance Mitsuba renders (its own direct
integrator, ray tracing and light sampling) is compared with `fitting.models`' evaluate at the
per-pixel geometry computed in numpy, L = f_r · I · cos θ_i / r². For the measured material the
rendered radiance is compared with Mitsuba's `measured` plugin evaluated directly (bsdf.eval), a
different code path from the integrator's.
"""

from __future__ import annotations

import functools
import shutil
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from conftest import data_file

from fitting import models
from plumbing.config import ConfigError
from simulator.render import (
    Renderer,
    SceneLoadError,
    board_renderer,
    camera_intrinsics,
    reference_target_scene,
    world_to_camera_cv,
)
from simulator.scene import (
    CameraSpec,
    MeasuredMaterial,
    ModelMaterial,
    SampleSpec,
    Scene,
    load_scene,
)

I_W_SR = (2.0, 1.5, 1.0)


def _sph(theta_deg, phi_deg, r=1.0):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return r * np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def _flat_scene(material) -> Scene:
    return Scene(
        material=material,
        sample=SampleSpec(size_m=0.2),
        light={"intensity_W_sr": I_W_SR},
        camera=CameraSpec(resolution=(33, 33), fov_deg=10.0),
    )


def _point_lit_truth(r: Renderer, light, cam, f_of):
    """(mask, truth radiance) for every pixel well inside the sample: f·I·cos θ_i / r²."""
    geo = r.pixel_geometry(light, cam)
    m = geo["on_sample"] & np.all(np.abs(geo["point_m"][..., :2]) < 0.1 - 0.005, axis=-1)
    f = f_of(geo["wi"][m], geo["wo"][m])  # (N, 3)
    truth = f * np.array(I_W_SR) * (geo["wi"][m, 2] / geo["r_light_m"][m] ** 2)[:, None]
    return m, truth


# --- measured RGL tensor ------------------------------------------------------------------------


@functools.cache
def _paper_renderer(path: str) -> Renderer:
    return Renderer(_flat_scene(MeasuredMaterial(filename=path)))


def test_measured_paper_truth_finite_positive_and_matches_render():
    path = data_file("rgl_brdf/paper_white_rgb.bsdf")
    r = _paper_renderer(str(path))
    rng = np.random.default_rng(3)
    # Directions up to 80° from the normal (the tensor's data extend to grazing; stay inside).
    n = 300
    ti, to = np.arccos(rng.uniform(0.18, 1, n)), np.arccos(rng.uniform(0.18, 1, n))
    pi_, po = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n)

    def d(t, p):
        return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)

    f = r.truth_bsdf(d(ti, pi_), d(to, po))
    assert np.all(np.isfinite(f))
    assert np.all(f > 0)
    # White paper is a bright near-diffuse reflector: albedo ~0.6–0.9, so f ≈ ρ/π ~ 0.2–0.3 sr⁻¹
    # over most of the hemisphere (a loose sanity band, not a fitted value).
    med = np.median(f)
    assert 0.1 < med < 0.5

    light, cam = _sph(40.0, 190.0, 0.5), _sph(30.0, 15.0, 0.7)
    img = r.render(light, cam)
    m, truth = _point_lit_truth(r, light, cam, r.truth_bsdf)
    assert m.sum() > 500
    # 1e-3: float32 rendering of a deterministic point light at one centred sample per pixel.
    np.testing.assert_allclose(img[m], truth, rtol=1e-3)


def test_relative_measured_path_resolved_against_scene_file(tmp_path):
    src = data_file("rgl_brdf/paper_white_rgb.bsdf")
    (tmp_path / "data").mkdir()
    shutil.copy(src, tmp_path / "data" / "paper.bsdf")
    (tmp_path / "scenes").mkdir()
    toml = tmp_path / "scenes" / "paper.toml"
    toml.write_text('[material]\ntype = "measured"\nfilename = "../data/paper.bsdf"\n')
    scene = load_scene(toml)
    assert scene.material.filename == str((tmp_path / "data" / "paper.bsdf").resolve())
    # A misspelt key is an error naming it (extra="forbid"), not silently ignored.
    toml.write_text('[material]\ntype = "measured"\nfilename = "a"\nfilname = "x.bsdf"\n')
    with pytest.raises(ConfigError, match="filname"):
        load_scene(toml)


def test_shipped_scene_files_load(configs):
    for name in ("paper.toml", "effects.toml", "model_ts.toml"):
        scene = load_scene(configs / "scenes" / name)
        assert scene.name
    paper = load_scene(configs / "scenes" / "paper.toml")
    assert paper.material.filename.endswith("paper_white_rgb.bsdf")


# --- fitting.models wrapped as a Python Mitsuba BSDF ----------------------------------------------

MODEL_CASES = [
    ("torrance-sparrow", {}, {"kd": (0.5, 0.3, 0.1), "ks": 0.4, "m": 0.25, "ior": 1.5}),
    (
        "torrance-sparrow",
        {"distribution": "ggx", "shadowing": "smith-correlated", "fresnel": "schlick"},
        {"kd": 0.2, "ks": (0.9, 0.6, 0.3), "m": 0.3, "f0": 0.04},
    ),
    ("blinn-phong", {}, {"kd": 0.4, "ks": 0.3, "n": 30.0}),
]


@pytest.mark.parametrize(("name", "options", "params"), MODEL_CASES)
def test_model_bsdf_render_matches_fitting_evaluate(name, options, params):
    mat = ModelMaterial(model=name, options=options, parameters=params)
    r = Renderer(_flat_scene(mat))
    model = models.get(name, **options)

    def f_model(wi, wo):
        out = np.empty((wi.shape[0], 3))
        for c in range(3):
            pc = {k: (v[c] if isinstance(v, tuple) else v) for k, v in params.items()}
            out[:, c] = model.evaluate(pc, wi, wo, backend="numpy")
        return out

    # Two geometries: near the specular peak (glossy lobe dominates) and off it.
    for light, cam in [
        (_sph(35.0, 180.0, 0.5), _sph(35.0, 0.0, 0.7)),
        (_sph(60.0, 120.0, 0.6), _sph(20.0, 300.0, 0.7)),
    ]:
        img = r.render(light, cam)
        m, truth = _point_lit_truth(r, light, cam, f_model)
        assert m.sum() > 500
        # 1e-3 relative: float32 rendering at one centred sample per pixel; the truth uses
        # the numpy reference backend, the BSDF the numba kernel.
        np.testing.assert_allclose(img[m], truth, rtol=1e-3)
    # truth_bsdf goes through the same Python BSDF's eval and must divide cos θ_i back out.
    wi, wo = _sph(50.0, 10.0)[None], _sph(20.0, 200.0)[None]
    np.testing.assert_allclose(r.truth_bsdf(wi, wo), f_model(wi, wo), rtol=1e-5)


def test_model_bsdf_missing_parameter_is_an_error():
    with pytest.raises(Exception, match="set parameters"):
        Renderer(_flat_scene(ModelMaterial(model="torrance-sparrow", parameters={"kd": 0.3})))


@pytest.mark.parametrize(
    ("material", "message"),
    [
        (
            'type = "model"\nmodel = "torrance-sparrow"\noptions = {distribution = "nope"}',
            "distribution='nope'; choose one of",
        ),
        (
            'type = "model"\nmodel = "lambert"\nparameters = {kd = 0.5, zz = 1.0}',
            "zz: not a parameter of lambert",
        ),
        (
            'type = "model"\nmodel = "lambert"\nparameters = {kd = [0.5, 1.5, 0.5]}',
            "outside lambert's range [0, 1]",
        ),
        ('type = "model"\nmodel = "nomodel"', "unknown model 'nomodel'"),
        ('type = "measured"\nfilename = "nothere.bsdf"', "no such file"),
    ],
)
def test_scene_values_mitsuba_would_refuse_at_render_are_refused_on_load(
    tmp_path, material, message
):
    """Issue 22: found only at the first render, these left a run directory that failed the
    same way on every resume; now load_scene refuses them in one line naming file and key."""
    path = tmp_path / "scene.toml"
    path.write_text(f"[material]\n{material}\n")
    with pytest.raises(ConfigError) as info:
        load_scene(path)
    line = str(info.value)
    assert "\n" not in line and line.startswith(f"{path}: material.") and message in line


def test_a_material_mitsuba_refuses_is_one_line_before_any_render():
    """An unknown conductor preset is found only by Mitsuba (its list of spectra ships inside
    the library): the renderer, built with the devices before a run directory exists, says so
    in one line instead of an internal error."""
    with pytest.raises(SceneLoadError) as info:
        Renderer(_flat_scene({"type": "roughconductor", "conductor": "Unobtainium"}))
    line = str(info.value)
    assert "\n" not in line and "Unobtainium" in line and "roughconductor" in line


def test_builtin_scene_renders_while_a_model_bsdf_is_alive():
    # drjit's symbolic virtual calls trace every live BSDF instance, so a live Python BSDF used
    # to break *other* scenes; the renderer must switch them to wavefront mode.
    keep = Renderer(_flat_scene(ModelMaterial(model="lambert", parameters={"kd": 0.5})))
    r = Renderer(_flat_scene({"type": "diffuse", "reflectance": [0.5, 0.5, 0.5]}))
    light, cam = _sph(30.0, 0.0, 0.5), _sph(20.0, 90.0, 0.7)
    img = r.render(light, cam)
    m, truth = _point_lit_truth(r, light, cam, lambda wi, wo: np.full((len(wi), 3), 0.5 / np.pi))
    np.testing.assert_allclose(img[m], truth, rtol=1e-3)
    # and the model scene agrees with it (Lambert kd = ρ): the same physics through both BSDFs.
    np.testing.assert_allclose(keep.render(light, cam), img, rtol=1e-5)


# --- calibration captures rendered by Mitsuba -------------------------------------------------


def test_charuco_board_on_sample_plane_detects_where_the_pinhole_projects_it():
    # Truth is independent of the renderer: OpenCV's ChArUco detector finds the corners in the
    # Mitsuba image, and the documented pinhole model (camera_intrinsics, world_to_camera_cv)
    # projects the board's corner positions there. A mirrored texture would not decode, a wrong
    # offset or scale would shift every corner by pixels.
    board = SimpleNamespace(
        kind="charuco", cols=8, rows=6, square_m=0.03, marker_m=0.022, dictionary="DICT_5X5_100"
    )
    # Uniform light: stray light only (radiance ρ·L_amb), the lamp switched off.
    scene = Scene.model_validate(
        {
            "light": {"intensity_W_sr": [0.0, 0.0, 0.0]},
            "stray_light": {"radiance_W_m2_sr": [1.0, 1.0, 1.0]},
            "camera": {"resolution": [640, 480], "fov_deg": 35.0},
        }
    )
    target = board_renderer(scene, board)
    cb = cv2.aruco.CharucoBoard(
        (8, 6), 0.03, 0.022, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100)
    )
    det = cv2.aruco.CharucoDetector(
        cb, cv2.aruco.CharucoParameters(), cv2.aruco.DetectorParameters()
    )
    k = camera_intrinsics(scene)
    for cam, aim in [
        ((0.0, 0.0, 0.5), (0.0, 0.0, 0.0)),
        ((0.15, -0.1, 0.45), (0.01, 0.0, 0.0)),
        ((-0.2, 0.1, 0.4), (0.0, 0.01, 0.0)),
    ]:
        img = target.renderer.render((0.0, 0.0, 1.0), cam, aim)
        gray = np.clip(img[..., 1] / 0.85 * 230, 0, 255).astype(np.uint8)
        corners, ids, _, _ = det.detectBoard(gray)
        assert ids is not None and len(ids) >= 25, cam
        ids = np.asarray(ids).ravel()
        world = target.board_to_world(cb.getChessboardCorners()[ids])
        rot, t = world_to_camera_cv(cam, aim)
        x = world @ rot.T + t
        uv = np.stack(
            [k["fx"] * x[:, 0] / x[:, 2] + k["cx"], k["fy"] * x[:, 1] / x[:, 2] + k["cy"]]
        )
        err = np.asarray(corners).reshape(-1, 2) - uv.T
        # Sub-pixel corner refinement on a 4×4-supersampled render: ~0.1 px is typical;
        # 0.25 px rms / 0.1 px mean would still catch a half-texel or 1 mm placement error
        # (1 mm ≈ 1.4 px here).
        assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.25, cam
        assert np.all(np.abs(err.mean(axis=0)) < 0.1), cam


def test_reference_target_is_lambertian_with_its_albedo():
    scene = reference_target_scene(
        _flat_scene(ModelMaterial(model="lambert", parameters={"kd": 0.5})), 0.9
    )
    r = Renderer(scene)
    wi, wo = _sph(70.0, 0.0)[None], _sph(10.0, 180.0)[None]
    np.testing.assert_allclose(r.truth_bsdf(wi, wo), 0.9 / np.pi, rtol=1e-6)
    light, cam = _sph(45.0, 0.0, 0.5), _sph(30.0, 200.0, 0.7)
    m, truth = _point_lit_truth(r, light, cam, lambda wi, wo: np.full((len(wi), 3), 0.9 / np.pi))
    np.testing.assert_allclose(r.render(light, cam)[m], truth, rtol=1e-3)


_SCALAR_SCRIPT = """
import json, sys
import numpy as np
from fitting import models
from simulator.render import Renderer
from simulator.scene import Scene
params = {"kd": 0.3, "ks": 0.6, "m": 0.3, "ior": 1.5}
scene = Scene.model_validate({
    "material": {"type": "model", "parameters": params},
    "sample": {"size_m": 0.2},
    "light": {"intensity_W_sr": [1.0, 1.0, 1.0]},
    "camera": {"resolution": [9, 9], "fov_deg": 10.0},
})
r = Renderer(scene, variant="scalar_rgb")
light, cam = np.array([-0.25, 0.05, 0.4]), np.array([0.3, 0.0, 0.55])
img = r.render(light, cam)
geo = r.pixel_geometry(light, cam)
m = geo["on_sample"]
f = models.get("torrance-sparrow").evaluate(params, geo["wi"][m], geo["wo"][m], backend="numpy")
truth = f * geo["wi"][m, 2] / geo["r_light_m"][m] ** 2
print(json.dumps({"variant": r.variant, "n": int(m.sum()),
                  "rel": float(np.max(np.abs(img[m][:, 1] / truth - 1)))}))
"""


def test_model_bsdf_in_scalar_variant():
    # scalar_rgb calls the Python BSDF per ray with scalar types (a different code path from
    # llvm's arrays); a child interpreter keeps this process's variant untouched.
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ, GONIO_MITSUBA_VARIANT="scalar_rgb")
    out = subprocess.run(
        [sys.executable, "-c", _SCALAR_SCRIPT],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["variant"] == "scalar_rgb" and res["n"] > 40
    assert res["rel"] < 1e-3  # same float32 bound as the llvm test

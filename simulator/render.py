"""Mitsuba 3 radiance renderer for the simulated gonioreflectometer camera.

One Mitsuba scene is loaded per material; each pose only moves the lamp and the camera
through ``mi.traverse`` + ``params.update()`` (no reload, no re-tracing of kernels), which is what
makes a 64×64 capture cost a few ms in ``llvm_ad_rgb`` (docs/design.md §7).

Radiometry: pixels are radiance L in W m⁻² sr⁻¹ (the ``hdrfilm`` value with a ``box`` pixel filter;
no exposure, no vignetting — the sensor model adds those). With a point light of radiant intensity
I (W sr⁻¹) and the ``direct`` integrator a surface point returns exactly
    L = f_r(ω_i, ω_o) · I · cos θ_i / r²                                  (rendering equation)
at 1 spp, because the light has no area to sample.

Optional effects (only loaded when the scene asks, see simulator.planner): a spot lamp or an area
lamp (disk/square facing the sample), a holder rim of four boxes (shadows; interreflection →
``path`` integrator), and ambient stray light (a ``constant`` environment emitter).

Pixel sampling: a ``stratified`` sampler with ``jitter=False``. At spp = 1 every pixel is sampled
exactly through its centre (so the per-pixel geometry in ``pixel_rays`` is exact); at spp = n² the
pixel is integrated with the n×n midpoint rule over its area.

Camera model (verified by tests/simulator/test_sim_render.py): an ideal pinhole, no distortion,
square pixels, horizontal field of view ``scene.camera.fov_deg`` spanning the full image width,
principal point at the image centre. In OpenCV convention (pixel centres at integer coordinates, x
to the right, y down, z forward):
    fx = fy = (W/2) / tan(fov_x/2),  cx = W/2 − 1/2,  cy = H/2 − 1/2.
Camera orientation: on the simulated rig, the arms' own forward kinematics (simulator.arms) gives
the camera's ``to_world`` (``camera_to_world``: the image turns with the arm, at θ_o = 0 too). A
free-standing camera placed by its position alone (tests, previews) looks at the target with
``up = +z`` (the sample normal), or ``+y`` within ~2.6° of the normal (``look_at_up``). Mitsuba's
camera frame has columns (left, up, forward); the OpenCV frame is (−left, −up, forward):
``world_to_camera_cv``.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from dataclasses import dataclass

import numpy as np

from plumbing.errors import UserError
from simulator.bsdf_eval import eval_fr
from simulator.materials import material_dict, model_bsdfs_alive, needs_wavefront
from simulator.scene import Scene
from simulator.variant import ensure_variant


class SceneLoadError(UserError, RuntimeError):
    """Mitsuba refused the scene a scene file describes (e.g. an unknown conductor name). One
    line; raised while the devices are built, before a run directory exists."""


def check_material(scene: Scene) -> None:
    """Load the scene's sample material in Mitsuba alone, before any device or run exists, so
    what only Mitsuba knows (its conductor presets) is one line before a plan is announced.
    Python-model and textured materials are checked by their scene types and skipped here."""
    import mitsuba as mi

    kinds = {scene.material.type}
    for key in ("first", "second"):
        part = getattr(scene.material, key, None)
        if part is not None:
            kinds.add(part.type)
    if kinds & {"model", "textured"}:
        return
    ensure_variant()
    try:
        mi.load_dict(material_dict(scene.material))
    except RuntimeError as exc:
        raise _refused(scene, exc) from None


def _refused(scene: Scene, exc: RuntimeError) -> SceneLoadError:
    return SceneLoadError(
        f"scene {scene.name!r}: Mitsuba cannot load its {scene.material.type} material "
        f"({_mitsuba_reason(exc)}); check the scene file's [material]"
    )


def _mitsuba_reason(exc: RuntimeError) -> str:
    """The last reason in Mitsuba's nested message, without its source-file locations."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    text = re.sub(r"\[[\w./]+\.(?:cpp|h|py):\d+\]\s*", "", text)
    return ": ".join(text.rsplit(": ", 2)[-2:])  # e.g. '"data/ior/X.eta.spd": file does not exist!'


__all__ = [
    "Renderer",
    "camera_intrinsics",
    "look_at_up",
    "camera_frame",
    "world_to_camera_cv",
    "material_dict",
    "holder_walls",
    "BoardTarget",
    "board_renderer",
    "reference_target_scene",
]


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def holder_walls(scene: Scene) -> list[tuple[tuple[float, float, float], tuple[float, ...]]]:
    """The holder rim as four axis-aligned boxes: (centre_m, half_extent_m) each.

    Inner faces at ±w with w = sample half-side + gap; walls ``wall_thickness_m`` thick and
    ``rim_height_m`` tall, standing on the sample plane z = 0 (the x-walls span the corners).
    """
    h = scene.holder
    if h is None:
        return []
    w = scene.sample.size_m / 2.0 + h.gap_m
    t, z = h.wall_thickness_m, h.rim_height_m / 2.0
    out = []
    for s in (1.0, -1.0):
        out.append(((s * (w + t / 2), 0.0, z), (t / 2, w + t, z)))
        out.append(((0.0, s * (w + t / 2), z), (w, t / 2, z)))
    return out


#: The beam texture's half field of view: the sample, board and reference target (≤ 50 mm at
#: ≥ 0.1 m from the lamp) lie well inside it; outside it the projector gives no light.
BEAM_HALF_FOV_DEG = 30.0
#: Texels per side: 0.12° each, so bilinear interpolation of the smooth profile errs by
#: ~Δ² I''/8 < 1e-5 of I₀ for falloffs of a few % over a few degrees.
BEAM_TEXELS = 512


def _texel_centres(n: int) -> np.ndarray:
    """Centres of n texels spanning [−1, 1] (a bitmap's uv ∈ [0, 1] mapped to 2uv − 1)."""
    return 2.0 * (np.arange(n) + 0.5) / n - 1.0


def _bitmap_texture(mi, data: np.ndarray) -> dict:  # the mitsuba module
    """A Mitsuba bitmap texture of raw float values, bilinear and clamped at its edges."""
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(data),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": "clamp",
    }


def beam_texture(light) -> np.ndarray:
    """The `projector` texture that makes a pinhole lamp of radiant intensity
    I(ψ) = I₀ · light.beam_profile(ψ). Mitsuba's projector (src/emitters/projector.cpp) returns
    π · T(uv) / (z² cos ψ) for a point at local depth z, i.e. an intensity π T / cos³ψ (its
    constant texture lights a plane at z = 1 evenly), so T = I(ψ) cos³ψ / π. Texel centres map
    to tan ψ_x,y = (2u − 1) tan(fov/2)."""
    n = BEAM_TEXELS
    t = _texel_centres(n) * math.tan(math.radians(BEAM_HALF_FOV_DEG))
    tx, ty = np.meshgrid(t, t)
    cos_psi = 1.0 / np.sqrt(1.0 + tx**2 + ty**2)
    rel = light.beam_profile(np.arccos(cos_psi)) * cos_psi**3 / math.pi
    i0 = np.asarray(light.intensity_W_sr, float)
    return np.ascontiguousarray((rel[..., None] * i0).astype(np.float32))


#: Texels per side of a bowed sample's normal map: the dome's slopes are linear in x and y, so
#: bilinear interpolation reproduces them exactly between texel centres.
NORMAL_TEXELS = 256


def normal_texture(sagitta_m: float, half_extent_m: tuple[float, float]) -> np.ndarray:
    """Mitsuba `normalmap` texture of the dome (simulator.scene.bow_slopes): per texel the unit
    normal (−h_x, −h_y, 1)/‖·‖ stored as (n + 1)/2. Column ix ↔ x, row iy ↔ y (simulator.texture:
    the rectangle's uv = (local + 1)/2, bitmap rows grow with v)."""
    from simulator.scene import bow_slopes

    hx, hy = half_extent_m
    x = _texel_centres(NORMAL_TEXELS) * hx
    y = _texel_centres(NORMAL_TEXELS) * hy
    gx, gy = bow_slopes(sagitta_m, min(hx, hy), *np.meshgrid(x, y))
    normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return np.ascontiguousarray(((normal + 1.0) / 2.0).astype(np.float32))


def look_at_up(camera_pos_m, target_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Up vector used for the camera: +z, or +y when the view is (nearly) along ±z."""
    d = np.asarray(target_m, float) - np.asarray(camera_pos_m, float)
    n = np.linalg.norm(d)
    if n == 0:
        raise ValueError("camera position equals the target: the view direction is undefined")
    # cos 2.6° ≈ 0.999: beyond that cross(up, dir) becomes ill-conditioned.
    if abs(d[2] / n) > 0.999:
        return np.array([0.0, 1.0, 0.0])
    return np.array([0.0, 0.0, 1.0])


def camera_frame(camera_pos_m, target_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4×4 camera-to-world matrix exactly as Mitsuba's ``Transform4f.look_at`` builds it.

    Columns: left = normalize(up × dir), up' = dir × left, dir = normalize(target − origin), origin.
    """
    o = np.asarray(camera_pos_m, float)
    d = np.asarray(target_m, float) - o
    d = d / np.linalg.norm(d)
    up = look_at_up(o, target_m)
    left = np.cross(up, d)
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


def world_to_camera_cv(
    camera_pos_m, target_m=(0.0, 0.0, 0.0), camera_to_world: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with x_cam = R·X_world + t in OpenCV axes (x right, y down, z forward), for the
    camera posed by `camera_to_world` (4×4, Mitsuba's frame), else looking at `target_m`."""
    m = camera_frame(camera_pos_m, target_m) if camera_to_world is None else camera_to_world
    axes = np.stack([-m[:3, 0], -m[:3, 1], m[:3, 2]], axis=1)  # camera→world rotation (CV axes)
    r = axes.T
    t = -r @ m[:3, 3]
    return r, t


def _class_name(obj) -> str:
    """Mitsuba plugin class of a loaded object, e.g. "PointLight" (from its string form)."""
    return str(obj).split("[", 1)[0].strip()


def camera_intrinsics(scene: Scene) -> dict:
    """Pinhole intrinsics (pixels, OpenCV convention) of the simulated camera.

    fx = fy = (W/2)/tan(fov_x/2) (Mitsuba ``fov_axis='x'``: the fov spans the full width);
    principal point at the centre of the image, i.e. (W/2 − 1/2, H/2 − 1/2) when pixel centres
    sit at integer coordinates.
    """
    w, h = scene.camera.resolution
    fx = (w / 2.0) / np.tan(np.radians(scene.camera.fov_deg) / 2.0)
    return {"fx": fx, "fy": fx, "cx": w / 2.0 - 0.5, "cy": h / 2.0 - 0.5, "width": w, "height": h}


class Renderer:
    """Radiance images of the flat sample for arbitrary light and camera positions.

    Parameters
    ----------
    scene : simulator.scene.Scene
    spp : int, optional
        samples per pixel; must be a perfect square (stratified midpoint grid). 1 = pixel centre,
        exact for a point or spot light with the ``direct`` integrator. Default: the plan's spp.
    variant : str, optional
        Mitsuba variant; default ``choose_variant()`` (llvm_ad_rgb if usable, else scalar_rgb).
    plan : simulator.planner.SimPlan, optional
        the effect plan (default ``plan_effects(scene)``): integrator, depth and spp come from it,
        and only the emitters/shapes the scene asks for are loaded.

    Instrumentation (for tests that prove a disabled effect never ran): ``loaded`` describes what
    was actually loaded into Mitsuba (read back from the Mitsuba scene object: integrator class,
    emitter classes, shape ids), and ``effect_counts`` counts per render call which render-side
    effects were in the rendered scene.
    """

    def __init__(
        self,
        scene: Scene,
        spp: int | None = None,
        variant: str | None = None,
        plan=None,
        *,
        sample_bsdf: dict | None = None,
        sample_extent_m: tuple[float, float] | None = None,
    ):
        import mitsuba as mi

        if variant is None:
            self.variant = ensure_variant()
        else:
            self.variant = variant
            if mi.variant() != variant:
                mi.set_variant(variant)
        if plan is None:
            from simulator.planner import plan_effects

            plan = plan_effects(scene, variant=self.variant)
        self.plan = plan
        if spp is None:
            spp = plan.spp
        n = int(round(np.sqrt(spp)))
        if n * n != spp or spp < 1:
            raise ValueError(f"spp must be a perfect square ≥ 1 (got {spp})")
        self.spp = spp
        self.scene = scene
        self._mi = mi
        self._wavefront = needs_wavefront(scene.material)
        half = scene.sample.size_m / 2.0
        # A calibration target replaces the sample's BSDF and extent (see board_renderer).
        hx, hy = (half, half) if sample_extent_m is None else (e / 2.0 for e in sample_extent_m)
        self.sample_half_extent_m = (hx, hy)
        desc = self._scene_dict(sample_bsdf)
        # optimize=False: Mitsuba would otherwise merge shapes that share an identical BSDF
        # (e.g. a holder as white as the sample) into one mesh, and the sample's BSDF is needed.
        try:
            self._scene = self._with_flags(mi.load_dict, desc, optimize=False)
        except RuntimeError as exc:
            raise _refused(scene, exc) from None
        self._params = mi.traverse(self._scene)
        shapes = list(self._scene.shapes())
        self._bsdf = next(s for s in shapes if s.id() == "sample").bsdf()
        self.intrinsics = camera_intrinsics(scene)
        self.loaded = {
            "integrator": _class_name(self._scene.integrator()),
            "emitters": sorted(_class_name(e) for e in self._scene.emitters()),
            # Mitsuba keeps the dict key as id for analytic shapes; meshes (the holder's cubes)
            # report an empty id, so count shapes by their class as well.
            "shapes": sorted(f"{_class_name(s)}:{s.id()}" for s in shapes),
            "spp": spp,
            "max_depth": plan.max_depth if plan.integrator == "path" else None,
        }
        self.effect_counts: Counter[str] = Counter()
        self._render_effects = ["render", f"light_{scene.light.type}"]
        if scene.light.beam_falloff:
            self._render_effects.append("beam_profile")
        if scene.geometry.sample_bow_m:
            self._render_effects.append("sample_bow")
        if scene.holder is not None:
            self._render_effects.append("holder")
        if scene.stray_light is not None:
            self._render_effects.append("stray_light")
        if plan.integrator == "path":
            self._render_effects.append("path_integrator")

    def _scene_dict(self, sample_bsdf: dict | None) -> dict:
        """The Mitsuba scene description: integrator (what the effect plan asks), pinhole
        sensor with a box filter, the lamp, the sample rectangle, and the optional holder walls
        and stray-light environment."""
        mi, scene, plan, spp = self._mi, self.scene, self.plan, self.spp
        w, h = scene.camera.resolution
        hx, hy = self.sample_half_extent_m
        T = mi.ScalarTransform4f
        to_world = T().look_at(origin=[0.0, 0.0, 1.0], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
        if plan.integrator == "path":
            # rr_depth beyond max_depth: no Russian roulette (its extra noise buys nothing here).
            integrator = {"type": "path", "max_depth": plan.max_depth, "rr_depth": 1000}
        else:
            # bsdf_samples=0 when every light is a delta light (BSDF sampling can never hit it);
            # an area light or the stray-light environment is also reached by BSDF sampling.
            integrator = {
                "type": "direct",
                "emitter_samples": 1,
                "bsdf_samples": plan.bsdf_samples,
            }
        desc = {
            "type": "scene",
            "integrator": integrator,
            "sensor": {
                "type": "perspective",
                "fov": float(scene.camera.fov_deg),
                "fov_axis": "x",
                "near_clip": 1e-4,
                "far_clip": 1e4,
                "to_world": to_world,
                "sampler": {"type": "stratified", "sample_count": spp, "jitter": False},
                "film": {
                    "type": "hdrfilm",
                    "width": int(w),
                    "height": int(h),
                    "pixel_format": "rgb",
                    "rfilter": {"type": "box"},  # radiometry: no negative/overlapping lobes
                },
            },
            "light": self._light_dict(),
            "sample": {
                "type": "rectangle",  # one-sided, normal +z, default extent [-1, 1]²
                "to_world": T().scale([hx, hy, 1.0]),
                "bsdf": sample_bsdf if sample_bsdf is not None else self._sample_material(),
            },
        }
        for k, (centre, ext) in enumerate(holder_walls(scene)):
            desc[f"holder_{k}"] = {
                "type": "cube",  # closed box [-1, 1]³, outward normals
                "to_world": T().translate(list(centre)).scale(list(ext)),
                "bsdf": {"type": "diffuse", "reflectance": _rgb(scene.holder.reflectance)},
            }
        if scene.stray_light is not None:
            # sampling_weight 0: emitter sampling always picks the lamp (a point/spot lamp stays
            # deterministic at 1 spp); the environment is found by BSDF sampling (MIS weight 1),
            # which for a Lambertian sample returns exactly ρ·L_amb per sample.
            desc["stray_light"] = {
                "type": "constant",
                "radiance": _rgb(scene.stray_light.radiance_W_m2_sr),
                "sampling_weight": 0.0,
            }
        return desc

    def _sample_material(self) -> dict:
        """The sample's BSDF; with a bowed sample (scene geometry.sample_bow_m) wrapped in
        Mitsuba's `normalmap`, whose texture holds the dome's unit normals (module
        `normal_texture`). The rectangle's shading frame is the world's (+x, +y, +z), so the
        map's normals are the sample frame's."""
        desc = material_dict(self.scene.material)
        bow = self.scene.geometry.sample_bow_m
        if not bow:
            return desc
        texture = normal_texture(bow, self.sample_half_extent_m)
        return {"type": "normalmap", "normalmap": _bitmap_texture(self._mi, texture), "bsdf": desc}

    def _light_dict(self) -> dict:
        light = self.scene.light
        dummy = self._mi.ScalarTransform4f().look_at(
            origin=[0.0, 0.0, 1.0], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0]
        )
        if light.type == "point" and light.beam_falloff > 0:
            return {
                "type": "projector",
                "to_world": dummy,
                "fov": 2.0 * BEAM_HALF_FOV_DEG,
                "fov_axis": "x",
                "irradiance": _bitmap_texture(self._mi, beam_texture(light)),
            }
        if light.type == "point":
            return {
                "type": "point",
                "position": [0.0, 0.0, 1.0],
                "intensity": _rgb(light.intensity_W_sr),
            }
        if light.type == "spot":
            beam = (
                light.beam_width_deg
                if light.beam_width_deg is not None
                else 0.75 * (light.cutoff_deg)
            )
            return {
                "type": "spot",
                "to_world": dummy,
                "intensity": _rgb(light.intensity_W_sr),
                "cutoff_angle": float(light.cutoff_deg),
                "beam_width": float(min(beam, light.cutoff_deg)),
            }
        # Area lamp: a one-sided shape emitting along its +z normal, turned to face the sample.
        return {
            "type": "disk" if light.shape == "disk" else "rectangle",
            "to_world": dummy.scale([light.radius_m, light.radius_m, 1.0]),
            "emitter": {"type": "area", "radiance": _rgb(light.radiance_W_m2_sr)},
        }

    def _with_flags(self, fn, *args, **kwargs):
        """Call ``fn`` in drjit wavefront mode if a Python-model BSDF needs concrete arrays —
        this scene's, or any other alive in the process (symbolic calls trace every instance)."""
        if self.variant.startswith("scalar") or not (self._wavefront or model_bsdfs_alive()):
            return fn(*args, **kwargs)
        import drjit as dr

        with (
            dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False),
            dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False),
        ):
            return fn(*args, **kwargs)

    def render(
        self,
        light_pos_m,
        camera_pos_m,
        camera_target_m=(0.0, 0.0, 0.0),
        intensity_scale: float = 1.0,
        seed: int = 0,
        camera_to_world: np.ndarray | None = None,
    ) -> np.ndarray:
        """Radiance image (H, W, 3) float32 in W m⁻² sr⁻¹ for one light/camera pose.

        ``camera_to_world``: the camera's pose (4×4, Mitsuba's camera frame; simulator.arms),
        else a camera at ``camera_pos_m`` looking at ``camera_target_m`` (`look_at_up`).

        ``intensity_scale`` multiplies the lamp's radiant intensity. With no stray light radiance
        is linear in it, so it is applied to the image (exact, no parameter update); stray light
        does not scale with the lamp, so then the lamp's emission parameter is updated instead.
        """
        mi = self._mi
        p = self._params
        light = self.scene.light
        lp = [float(v) for v in light_pos_m]
        if light.type == "point" and not light.beam_falloff:
            p["light.position"] = mi.Point3f(*lp)
        else:
            # Spot and area lamps face the sample centre (the rig aims the lamp at it).
            tw = mi.ScalarTransform4f().look_at(
                origin=lp, target=[0.0, 0.0, 0.0], up=[float(v) for v in look_at_up(lp)]
            )
            if light.type == "area":
                tw = tw.scale([light.radius_m, light.radius_m, 1.0])
            p["light.to_world"] = mi.Transform4f(tw) if hasattr(mi, "Transform4f") else tw
        scale_in_scene = self.scene.stray_light is not None
        if scale_in_scene:  # never with a beam profile (simulator.scene.Scene refuses it)
            key, base = (
                ("light.emitter.radiance.value", light.radiance_W_m2_sr)
                if light.type == "area"
                else ("light.intensity.value", light.intensity_W_sr)
            )
            p[key] = mi.Color3f(*[float(b) * float(intensity_scale) for b in base])
        if camera_to_world is None:
            tw = mi.ScalarTransform4f().look_at(
                origin=[float(v) for v in camera_pos_m],
                target=[float(v) for v in camera_target_m],
                up=[float(v) for v in look_at_up(camera_pos_m, camera_target_m)],
            )
        else:
            tw = mi.ScalarTransform4f(np.asarray(camera_to_world, dtype=np.float64).tolist())
        p["sensor.to_world"] = mi.Transform4f(tw) if hasattr(mi, "Transform4f") else tw
        p.update()
        img = self._with_flags(mi.render, self._scene, spp=self.spp, seed=seed)
        out = np.asarray(img, dtype=np.float32)
        if intensity_scale != 1.0 and not scale_in_scene:
            out = out * np.float32(intensity_scale)
        self.effect_counts.update(self._render_effects)
        return out

    def pixel_rays(self, camera_pos_m, camera_target_m=(0.0, 0.0, 0.0), camera_to_world=None):
        """World-space ray (origin, unit directions (H, W, 3)) through every pixel centre of the
        camera `render` would use (the same `camera_to_world` or look-at)."""
        k = self.intrinsics
        u = np.arange(k["width"], dtype=float)
        v = np.arange(k["height"], dtype=float)
        uu, vv = np.meshgrid(u, v)
        d_cam = np.stack(
            [(uu - k["cx"]) / k["fx"], (vv - k["cy"]) / k["fy"], np.ones_like(uu)], axis=-1
        )
        r, _ = world_to_camera_cv(camera_pos_m, camera_target_m, camera_to_world)
        d = d_cam @ r  # R^T applied to row vectors: camera → world
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.asarray(camera_pos_m, float), d

    def pixel_geometry(
        self, light_pos_m, camera_pos_m, camera_target_m=(0.0, 0.0, 0.0), camera_to_world=None
    ) -> dict:
        """Exact geometry of every pixel centre's view of the sample plane (for truth and tests).

        Returns a dict of arrays: ``point_m`` (H, W, 3) where the pixel ray meets z = 0,
        ``wi``/``wo`` (H, W, 3) unit directions to the light / camera, ``r_light_m`` (H, W)
        distance to the light, and ``on_sample`` (H, W) bool (hit inside the square sample,
        in front of the camera, and with the light above the surface).
        """
        origin, dirs = self.pixel_rays(camera_pos_m, camera_target_m, camera_to_world)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -origin[2] / dirs[..., 2]
        p = origin + t[..., None] * dirs
        to_light = np.asarray(light_pos_m, float) - p
        r_light = np.linalg.norm(to_light, axis=-1)
        wi = to_light / r_light[..., None]
        wo = -dirs
        hx, hy = self.sample_half_extent_m
        on = (
            np.isfinite(t)
            & (t > 0)
            & (np.abs(p[..., 0]) <= hx)
            & (np.abs(p[..., 1]) <= hy)
            & (wi[..., 2] > 0)
            & (wo[..., 2] > 0)
        )
        return {"point_m": p, "wi": wi, "wo": wo, "r_light_m": r_light, "on_sample": on}

    def truth_bsdf(self, wi, wo) -> np.ndarray:
        """Ground-truth f_r (N, 3) in sr⁻¹ from Mitsuba's own BSDF of the loaded material
        (simulator.bsdf_eval: ``wi`` to the light, ``wo`` to the camera; 0 below the horizon)."""
        return eval_fr(self._bsdf, wi, wo, self.variant)


@dataclass
class BoardTarget:
    """A calibration board rendered by Mitsuba on the sample plane.

    ``renderer`` renders it (its sample is the board texture as a diffuse bitmap);
    ``board_to_world(points)`` maps board-frame points (OpenCV board frame: x along columns, y
    along rows, z into the board; metres) to world coordinates (sample frame, +z out of it).
    """

    renderer: Renderer
    offset_m: tuple[float, float]
    extent_m: tuple[float, float]

    def board_to_world(self, points_board) -> np.ndarray:
        p = np.atleast_2d(np.asarray(points_board, float))
        ox, oy = self.offset_m
        # Seen from +z the board must not be mirrored: board y (down the printed image) runs
        # along world −y and board z (into the board) along world −z.
        return np.stack([p[:, 0] + ox, -p[:, 1] + oy, -p[:, 2]], axis=-1)


def board_renderer(
    scene: Scene,
    board,
    spp: int = 16,
    variant: str | None = None,
    black_reflectance: float = 0.05,
    white_reflectance: float = 0.85,
) -> BoardTarget:
    """A Renderer whose sample is ``board`` (ChArUco or chessboard, e.g.
    ``calibration.camera_model.BoardSpec``) printed on a Lambertian sheet centred on the origin.

    The texture comes from ``simulator.board.board_texture`` (one-square white quiet zone);
    its grey levels map linearly to reflectances ``black_reflectance`` … ``white_reflectance``.
    spp = 16 integrates each pixel over a 4×4 grid so square edges get their area coverage.
    Light it with the scene's lamp, or uniformly with ``stray_light`` (radiance = ρ·L_amb).
    """
    import mitsuba as mi

    from simulator.board import BLACK_DN, WHITE_DN, board_texture

    if variant is None:
        variant = ensure_variant()
    elif mi.variant() != variant:
        mi.set_variant(variant)
    texture, per_m, origin = board_texture(board)
    level = (texture - BLACK_DN) / (WHITE_DN - BLACK_DN)
    rho = black_reflectance + (white_reflectance - black_reflectance) * level
    h_t, w_t = rho.shape
    sx, sy = w_t / per_m, h_t / per_m
    # Mitsuba's rectangle has uv = (local + 1)/2 and its bitmap row index grows with v, i.e.
    # with world +y; the board's rows must run along world −y, hence the vertical flip.
    bitmap = mi.Bitmap(np.ascontiguousarray(np.repeat(rho[::-1, :, None], 3, axis=2)))
    bsdf = {
        "type": "diffuse",
        "reflectance": {"type": "bitmap", "bitmap": bitmap, "raw": True, "wrap_mode": "clamp"},
    }
    # Texel c (centre at integer c, covering [c − ½, c + ½]) sits at world x = (c + ½)/per_m −
    # sx/2; board X = (c − origin)/per_m. Rows likewise, mirrored.
    ox = (origin + 0.5) / per_m - sx / 2.0
    oy = sy / 2.0 - (origin + 0.5) / per_m
    r = Renderer(scene, spp=spp, variant=variant, sample_bsdf=bsdf, sample_extent_m=(sx, sy))
    return BoardTarget(renderer=r, offset_m=(ox, oy), extent_m=(sx, sy))


def reference_target_scene(
    scene: Scene,
    reflectance: float = 0.99,
    material: object | None = None,
    *,
    size_m: float | None = None,
) -> Scene:
    """The same rig with the sample replaced by a reference target: Lambertian of albedo
    ``reflectance`` (f_ref = ρ/π, e.g. Spectralon near normal incidence), or any scene
    ``material`` (a simulator.scene material model or its dict) — docs/design.md §7 warns that real
    Spectralon departs from Lambert at large angles, so a non-Lambertian target (evaluated as its
    "calibrated table" by ``Renderer.truth_bsdf``) exercises the calibrated-f_ref(θ) path."""
    from simulator.scene import DiffuseMaterial

    if material is None:
        rho = float(reflectance)
        material = DiffuseMaterial(reflectance=(rho, rho, rho))
    doc = {**scene.model_dump(), "material": _as_dict(material)}
    if size_m is not None:
        doc["sample"] = {**doc["sample"], "size_m": float(size_m)}
    return scene.model_validate(doc)


def _as_dict(material) -> dict:
    return material.model_dump() if hasattr(material, "model_dump") else dict(material)

"""Backend wiring: the front door is the only place that knows the simulator exists.

A rig config that names simulated devices (`dxlsim://`, `lightsim://`, camera backend "sim",
clock "sim") gets a simulated world built here, which registers those names; the acquisition
code then opens them exactly as it would open real devices.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from acquisition.config import RigConfig

__all__ = [
    "needs_simulator",
    "prepare_backends",
    "load_scene",
    "scene_model",
    "scene_truth",
    "scene_fit_model",
    "material_type",
    "truth_bsdf",
    "effects_description",
    "planned_spp",
    "effect_names",
    "blend_scene",
    "preview_png",
    "instrument_budget",
    "sobol_normal",
]


def needs_simulator(rig: RigConfig) -> bool:
    return (
        rig.bus.url.startswith("dxlsim://")
        or rig.light.url.startswith("lightsim://")
        or rig.camera.backend == "sim"
        or rig.clock == "sim"
    )


def prepare_backends(rig: RigConfig, scene: Any | None = None) -> Any | None:
    """Build the simulated world when the rig asks for one; return it (or None)."""
    if not needs_simulator(rig):
        return None
    from simulator.scene import Scene
    from simulator.world import SimWorld

    if scene is None:
        if rig.scene is None:
            from gonio.errors import UserError

            raise UserError("the rig uses simulated devices but names no scene (key `scene`)")
        scene = load_scene(Path(rig.scene))
    elif isinstance(scene, dict):
        scene = Scene.model_validate(scene)
    return SimWorld(rig, scene)


# -- the rest of the front door's view of the simulator ----------------------------------------
# Everything else in gonio that needs the emulated world (the demo's scene, the studies, a
# simulated run's truth in the report, the preview render) asks for it here, so this module
# stays the one door between gonio and simulator (an import-linter contract keeps it so).


def load_scene(path: Path | str) -> Any:
    """A scene file (the emulated world), checked (simulator.scene)."""
    from simulator.scene import load_scene as _load

    return _load(path)


def scene_model(data: dict) -> Any:
    """A scene from its frozen dict (run.toml [scene])."""
    from simulator.scene import Scene

    return Scene.model_validate(data)


def scene_truth(scene: Any) -> dict[str, float]:
    """The model parameters the scene's material *is* (simulator.truth), per channel."""
    from simulator.truth import reference_parameters

    return reference_parameters(scene)


def scene_fit_model(scene: Any) -> dict | None:
    """The registered model and options that *are* the scene's material, or None.

    {"model", "options", "describe"} for the materials a model here represents exactly:
    diffuse → lambert; roughconductor, or blend(diffuse, roughconductor) → torrance-sparrow
    with the conductor's distribution, Mitsuba's shadowing (Beckmann: the rational Smith G1;
    GGX: the exact separable Smith G1, which Mitsuba uses there), and F ≡ 1 for the perfect
    conductor "none" or the exact conductor Fresnel (η, k) otherwise; a wrapped model
    ("model") → that model with its options. Anything else (plastics, dielectrics, measured
    tensors, a smooth mirror) has no exact model: None.
    """
    from simulator.scene import (
        BlendMaterial,
        DiffuseMaterial,
        ModelMaterial,
        RoughConductorMaterial,
    )

    mat = scene.material
    if isinstance(mat, DiffuseMaterial):
        return {"model": "lambert", "options": {}, "describe": "diffuse"}
    if isinstance(mat, ModelMaterial):
        return {"model": mat.model, "options": dict(mat.options), "describe": f"model {mat.model}"}
    lobe = mat
    what = "roughconductor"
    if (
        isinstance(mat, BlendMaterial)
        and isinstance(mat.first, DiffuseMaterial)
        and isinstance(mat.second, RoughConductorMaterial)
    ):
        lobe, what = mat.second, "blend(diffuse, roughconductor)"
    if not isinstance(lobe, RoughConductorMaterial):
        return None
    perfect = lobe.eta is None and (lobe.conductor or "none") == "none"
    options = {
        "distribution": lobe.distribution,
        "shadowing": "smith-rational" if lobe.distribution == "beckmann" else "smith",
        "fresnel": "none" if perfect else "conductor",
    }
    return {"model": "torrance-sparrow", "options": options, "describe": f"{what}, {options}"}


def material_type(scene: Any) -> str:
    """The scene material's type name (blends as blend(first, second))."""
    mat = scene.material
    if getattr(mat, "type", "") == "blend":
        return f"blend({mat.first.type}, {mat.second.type})"
    return str(getattr(mat, "type", type(mat).__name__))


def truth_bsdf(scene: Any) -> Any:
    """f_r(ω_i, ω_o) → (N, 3) of the scene's material, Mitsuba's own BSDF (Renderer.truth_bsdf)."""
    from simulator.render import Renderer

    return Renderer(scene).truth_bsdf


def effects_description(scene: Any) -> str:
    """The simulation stages the scene needs and their cost (simulator.planner)."""
    from simulator.planner import plan_effects

    return plan_effects(scene).describe()


def effect_names(scene: Any) -> list[str]:
    """The simulation stages the scene runs (render effects, then sensor stages), by name."""
    from simulator.planner import plan_effects

    plan = plan_effects(scene)
    return [*plan.render_effects, *plan.sensor_stages]


def planned_spp(scene: Any) -> int:
    from simulator.planner import planned_spp as _spp

    return _spp(scene)


def blend_scene(base: Any, spec: dict, **update: Any) -> Any:
    """`base` with its material replaced by blendbsdf(diffuse ρ, roughconductor α, F ≡ 1) of
    weight w (`spec`: reflectance, alpha, weight) — Lambert + a Beckmann lobe exactly — and the
    other fields of `update` (seed, name, render...; `area_light_radius_m` swaps in a
    Lambertian disk lamp of the same intensity)."""
    from simulator.scene import BlendMaterial, DiffuseMaterial, LightSpec, RoughConductorMaterial

    mat = BlendMaterial(
        weight=spec["weight"],
        first=DiffuseMaterial(reflectance=spec["reflectance"]),
        second=RoughConductorMaterial(alpha=spec["alpha"], conductor="none"),
    )
    radius = update.pop("area_light_radius_m", None)
    if radius is not None and base.light.type != "area":
        update["light"] = LightSpec(
            type="area",
            shape="disk",
            radius_m=radius,
            intensity_W_sr=base.light.intensity_W_sr,
            drift_per_hour=base.light.drift_per_hour,
        )
    return base.model_copy(update={"material": mat, **update})


def preview_png(fit: Any, **kwargs: Any) -> bytes:
    """PNG of a sphere in the fitted material (simulator.preview)."""
    from simulator.preview import preview_png as _png

    return _png(fit, **kwargs)


def instrument_budget(**sizes: Any) -> Any:
    """A typical lab rig's shared-error budget (simulator.instrument_draws.InstrumentBudget):
    the rig file stating it, and worlds drawn from it."""
    from simulator.instrument_draws import InstrumentBudget

    return InstrumentBudget(**sizes)


def sobol_normal(n: int, dims: int, seed: int) -> Any:
    from simulator.instrument_draws import sobol_normal as _sobol

    return _sobol(n, dims, seed)

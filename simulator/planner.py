"""Effect planner: derive the minimal simulation a scene calls for (issue 4, item 5).

Rules (docs/simulator.md has the full table):

- variant: ``llvm_ad_rgb`` when the subprocess probe passes, else ``scalar_rgb``. RGB because no
  material here needs spectra (spectral would only be chosen for a spectral material).
- integrator: ``direct`` unless the scene has geometry that can *interreflect*: a holder whose
  walls reflect (reflectance > 0). A black holder only shadows, which shadow rays of the direct
  integrator already handle. With a reflecting holder: ``path`` with
  max_depth = 2 + n, n = the fewest extra bounces whose energy (q = ρ_holder,max · ½)ⁿ falls
  below the target noise (q: the holder albedo times ½, the largest cosine-weighted fraction of
  a sample point's hemisphere a wall can fill — a point at the wall's foot). Capped at 16.
- spp: 1 when every term is deterministic — a point or spot lamp (delta lights) under direct
  lighting, and stray light on a purely Lambertian sample (BSDF sampling returns exactly ρ·L_amb
  per sample, see simulator.render). Otherwise spp = ⌈(σ₁/ε)²⌉ rounded up to a square, where ε
  is ``render.target_rel_noise`` and σ₁ the estimated relative noise of one sample:
    area lamp        σ₁ = (a/d) · s   a = lamp radius, d = ``render.nominal_light_distance_m``,
                                      s = lobe sharpness (1 diffuse, 1/α glossy, 10 unknown)
    reflecting rim   σ₁ = ρ_h · F     F = h²/(h² + w²): cosine-weighted fraction of the sample
                                      centre's hemisphere filled by a rim of height h at w
    stray light      σ₁ = π L_amb d² / I  (ambient share of the signal; non-Lambertian only)
  The largest σ₁ wins; ``render.spp`` overrides; ``render.max_spp`` caps.
- sensor stages: exactly those ``Sensor.enabled_stages`` runs for the scene's sensor spec.

Costs are per capture, in ms: measured per-effect constants for a 64×64 capture from
``benchmarks/bench_effects.py`` (2-core dev machine, Nov 2026) — a fixed extra plus an extra per
additional sample per pixel — scaled by pixel count (and, for scalar_rgb, by its per-pixel
slowdown). Estimates, not guarantees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from simulator.materials import iter_materials, needs_wavefront
from simulator.scene import (
    BlendMaterial,
    DiffuseMaterial,
    MeasuredMaterial,
    ModelMaterial,
    Scene,
)
from simulator.sensor import enabled_stages

__all__ = [
    "SimPlan",
    "plan_effects",
    "planned_spp",
    "render_effects",
    "lobe_sharpness",
    "RENDER_NS_PER_PIXEL",
    "STAGE_NS_PER_PIXEL",
    "EFFECT_MS_64",
    "SPP_NS_PER_PIXEL",
]

# Measured with benchmarks/bench_render.py-style loops on the 2-core dev machine (Nov 2026):
# render ≈ overhead + per-pixel cost (32² … 256² fits); sensor stages per pixel and channel.
# Note: for small frames scalar_rgb is as fast as llvm_ad_rgb here (kernel launch overhead).
# llvm overhead re-measured by benchmarks/bench_effects.py (baseline 0.72 ms per 64×64 render).
RENDER_OVERHEAD_MS = {"llvm_ad_rgb": 0.45, "scalar_rgb": 0.2}
RENDER_NS_PER_PIXEL = {"llvm_ad_rgb": 70.0, "scalar_rgb": 230.0}
STAGE_NS_PER_PIXEL = {
    "irradiance": 4.0,
    "vignetting": 2.0,
    "photons": 4.0,
    "bayer": 8.0,
    "prnu": 2.0,
    "dark_current": 1.0,
    "dsnu": 2.0,
    "shot_noise": 26.0,
    "full_well": 3.0,
    "nonlinearity": 3.0,  # two multiplies and an add, like full_well (not yet benchmarked)
    "read_noise": 10.0,
    "adc": 6.0,
}
# Render-side effects, llvm_ad_rgb, 64×64, one scene alive: (extra ms at 1 spp over the point-lamp
# baseline, extra ms per additional sample per pixel), from `python benchmarks/bench_effects.py`
# (minimum over 60 poses; the table is in docs/simulator.md). Negative slopes measured
# within noise are stored as 0.
EFFECT_MS_64 = {
    "light_spot": (0.20, 0.006),
    "beam_profile": (0.20, 0.006),  # a projector's texture lookup: as a spot's falloff
    "sample_bow": (0.20, 0.006),  # a normal-map lookup per shading point: likewise
    "light_area": (0.68, 0.179),
    "holder": (0.35, 0.0),
    "stray_light": (0.54, 0.0),
    "path_integrator": (0.94, 0.0),
    "measured_material": (0.57, 0.039),
    "model_material": (0.41, 0.0),
}
# The baseline's cost per additional sample per pixel (same benchmark: 0.138 ms / 4096 px).
SPP_NS_PER_PIXEL = {"llvm_ad_rgb": 34.0, "scalar_rgb": 230.0}
MAX_DEPTH_CAP = 16


def lobe_sharpness(material) -> float:
    """How much a lobe amplifies a lamp's size into noise: 1 diffuse, 1/α glossy (α the
    roughness), 10 for a measured or smooth (delta) material whose lobe width is unknown here."""
    if isinstance(material, DiffuseMaterial):
        return 1.0
    if isinstance(material, BlendMaterial):
        return max(lobe_sharpness(material.first), lobe_sharpness(material.second))
    if isinstance(material, ModelMaterial):
        m = material.parameters.get("m")
        if m is None:
            return 1.0 if material.model == "lambert" else 10.0
        m_min = min(m) if isinstance(m, tuple) else m
        return max(1.0, 1.0 / m_min)
    alpha = getattr(material, "alpha", None)
    if alpha is not None:
        return max(1.0, 1.0 / alpha)
    if isinstance(material, MeasuredMaterial):
        return 10.0
    return 10.0


def _lambertian(material) -> bool:
    if isinstance(material, DiffuseMaterial):
        return True
    if isinstance(material, ModelMaterial):
        return material.model == "lambert"
    return False


def _square_at_least(x: float) -> int:
    n = max(1, math.ceil(math.sqrt(max(x, 1.0)) - 1e-12))
    return n * n


def render_effects(scene: Scene) -> list[str]:
    """Render-side effects the scene enables (names used in costs and Renderer.effect_counts)."""
    out = [f"light_{scene.light.type}"] if scene.light.type != "point" else []
    if scene.light.beam_falloff:
        out.append("beam_profile")
    if scene.geometry.sample_bow_m:
        out.append("sample_bow")
    if scene.holder is not None:
        out.append("holder")
    if scene.stray_light is not None:
        out.append("stray_light")
    if _interreflects(scene):
        out.append("path_integrator")
    if needs_wavefront(scene.material):
        out.append("model_material")
    if any(isinstance(m, MeasuredMaterial) for m in iter_materials(scene.material)):
        out.append("measured_material")
    return out


def _interreflects(scene: Scene) -> bool:
    return scene.holder is not None and max(scene.holder.reflectance) > 0


def _path_depth(scene: Scene) -> int:
    """2 + n extra bounces with (ρ_h·½)ⁿ ≤ target noise (module docstring)."""
    q = max(scene.holder.reflectance) * 0.5
    eps = scene.render.target_rel_noise
    n = 1 if q <= eps else math.ceil(math.log(eps) / math.log(q))
    return min(2 + max(n, 1), MAX_DEPTH_CAP)


def _noise_terms(scene: Scene) -> dict[str, float]:
    """Estimated relative noise σ₁ of one sample per stochastic effect (module docstring)."""
    terms: dict[str, float] = {}
    d = scene.render.nominal_light_distance_m
    if scene.light.type == "area":
        terms["light_area"] = scene.light.radius_m / d * lobe_sharpness(scene.material)
    if _interreflects(scene):
        h = scene.holder
        w = scene.sample.size_m / 2.0 + h.gap_m
        terms["path_integrator"] = (
            max(h.reflectance) * h.rim_height_m**2 / (h.rim_height_m**2 + w**2)
        )
    if scene.stray_light is not None and not (_lambertian(scene.material) and scene.holder is None):
        share = math.pi * max(scene.stray_light.radiance_W_m2_sr) * d**2
        share /= max(min(scene.light.intensity_W_sr), 1e-30)
        terms["stray_light"] = min(1.0, share)
    return terms


def planned_spp(scene: Scene) -> int:
    """Samples per pixel for ``scene`` (module docstring); always a perfect square."""
    if scene.render.spp is not None:
        return _square_at_least(scene.render.spp)
    terms = _noise_terms(scene)
    if not terms:
        return 1
    sigma = max(terms.values())
    spp = _square_at_least((sigma / scene.render.target_rel_noise) ** 2)
    cap = int(math.isqrt(scene.render.max_spp)) ** 2
    return max(1, min(spp, cap))


@dataclass
class SimPlan:
    """The effects one capture of a scene will simulate, with an estimated cost (ms)."""

    variant: str
    integrator: str
    max_depth: int
    spp: int
    sensor_stages: list[str]
    cost_estimate_ms: dict[str, float] = field(default_factory=dict)
    render_effects: list[str] = field(default_factory=list)
    bsdf_samples: int = 0
    noise_terms: dict[str, float] = field(default_factory=dict)

    @property
    def total_ms(self) -> float:
        return float(sum(self.cost_estimate_ms.values()))

    def describe(self) -> str:
        """Plain-text table of the plan and the estimated cost of each executed effect."""
        lines = [
            f"variant     {self.variant}",
            f"integrator  {self.integrator} (max_depth {self.max_depth}), spp {self.spp}",
            f"render      {', '.join(self.render_effects) or 'point lamp only'}",
        ]
        if self.noise_terms:
            terms = ", ".join(f"{k} σ₁≈{v:.3g}" for k, v in self.noise_terms.items())
            lines.append(f"noise       {terms}")
        lines += [
            "",
            f"{'effect':<16}{'est. ms/capture':>16}",
            f"{'-' * 16}{'-' * 16}",
        ]
        for name, ms in self.cost_estimate_ms.items():
            lines.append(f"{name:<16}{ms:>16.3f}")
        lines.append(f"{'-' * 16}{'-' * 16}")
        lines.append(f"{'total':<16}{self.total_ms:>16.3f}")
        return "\n".join(lines)


def plan_effects(scene: Scene, variant: str | None = None) -> SimPlan:
    """Minimal simulation plan for ``scene``. ``variant`` skips the probe when given."""
    if variant is None:
        from simulator.variant import choose_variant

        variant = choose_variant()
    w, h = scene.camera.resolution
    npx = w * h
    spp = planned_spp(scene)
    effects = render_effects(scene)
    path = "path_integrator" in effects
    stages = enabled_stages(scene.sensor)
    key = variant if variant in RENDER_NS_PER_PIXEL else "scalar_rgb"
    base_ms = RENDER_OVERHEAD_MS[key] + RENDER_NS_PER_PIXEL[key] * npx * 1e-6
    cost = {"render": base_ms}
    # Constants are for llvm; scalar pays its per-pixel ratio on top.
    ratio = RENDER_NS_PER_PIXEL[key] / RENDER_NS_PER_PIXEL["llvm_ad_rgb"]
    # Additive model: interactions (e.g. an area lamp sampled at every path vertex) are not
    # modelled; docs/simulator.md compares the estimate with whole-scene measurements.
    depth = _path_depth(scene) if path else 1
    for eff in effects:
        fixed_ms, per_spp_ms = EFFECT_MS_64[eff]
        cost[eff] = (fixed_ms + per_spp_ms * (spp - 1)) * npx / 4096 * ratio
    if spp > 1:
        cost["spp"] = SPP_NS_PER_PIXEL[key] * npx * (spp - 1) * 1e-6
    # Stages after "bayer" work on one plane instead of three.
    planes = 3
    for st in stages:
        cost[st] = STAGE_NS_PER_PIXEL[st] * npx * planes * 1e-6
        if st == "bayer":
            planes = 1
    return SimPlan(
        variant=variant,
        integrator="path" if path else "direct",
        max_depth=depth,
        spp=spp,
        sensor_stages=stages,
        cost_estimate_ms=cost,
        render_effects=effects,
        # BSDF sampling is only useful for lamps with area or for the environment.
        bsdf_samples=1 if (scene.light.type == "area" or scene.stray_light is not None) else 0,
        noise_terms=_noise_terms(scene),
    )

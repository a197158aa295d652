"""Effect planner: derive the minimal simulation a scene calls for (issue 4, item 5).

Rules (first version — scenes are a point light over one flat, one-sided sample):
- variant: ``llvm_ad_rgb`` when the subprocess probe passes, else ``scalar_rgb``; RGB because no
  current material needs spectra (spectral would only be chosen for spectral materials).
- integrator: ``direct`` — a single flat one-sided sample cannot see itself, so there is no
  interreflection; ``path`` (with the depth the geometry needs) is reserved for holder geometry.
- spp: 1 — a point light under direct lighting is deterministic, and the stratified sampler
  without jitter puts the single sample at the pixel centre (exact per-pixel geometry).
- sensor stages: exactly those ``Sensor.enabled_stages`` runs for the scene's sensor spec.

Cost estimates are per capture, in ms, from per-pixel constants measured by
``benchmarks/bench_render.py`` on a 2-core CI-class machine (estimates, not guarantees).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from simulator.scene import Scene
from simulator.sensor import enabled_stages

__all__ = ["SimPlan", "plan_effects", "RENDER_NS_PER_PIXEL", "STAGE_NS_PER_PIXEL"]

# Measured with benchmarks/bench_render.py-style loops on the 2-core dev machine (Nov 2026):
# render ≈ overhead + per-pixel cost (32² … 256² fits); sensor stages per pixel and channel.
# Note: for small frames scalar_rgb is as fast as llvm_ad_rgb here (kernel launch overhead).
RENDER_OVERHEAD_MS = {"llvm_ad_rgb": 1.5, "scalar_rgb": 0.2}
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
    "read_noise": 10.0,
    "adc": 6.0,
}


@dataclass
class SimPlan:
    """The effects one capture of a scene will simulate, with an estimated cost (ms)."""

    variant: str
    integrator: str
    max_depth: int
    spp: int
    sensor_stages: list[str]
    cost_estimate_ms: dict[str, float] = field(default_factory=dict)

    @property
    def total_ms(self) -> float:
        return float(sum(self.cost_estimate_ms.values()))

    def describe(self) -> str:
        """Plain-text table of the plan and the estimated cost of each executed effect."""
        lines = [
            f"variant     {self.variant}",
            f"integrator  {self.integrator} (max_depth {self.max_depth}), spp {self.spp}",
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
    spp = 1  # point light + direct lighting: deterministic (see module docstring)
    stages = enabled_stages(scene.sensor)
    key = variant if variant in RENDER_NS_PER_PIXEL else "scalar_rgb"
    cost = {
        "render": RENDER_OVERHEAD_MS[key] + RENDER_NS_PER_PIXEL[key] * npx * spp * 1e-6,
    }
    # Stages after "bayer" work on one plane instead of three.
    planes = 3
    for st in stages:
        if st == "bayer":
            planes_here = 3
        else:
            planes_here = planes
        cost[st] = STAGE_NS_PER_PIXEL[st] * npx * planes_here * 1e-6
        if st == "bayer":
            planes = 1
    return SimPlan(
        variant=variant,
        integrator="direct",
        max_depth=1,
        spp=spp,
        sensor_stages=stages,
        cost_estimate_ms=cost,
    )

"""The demo's material — a diffuse + Beckmann blend — and the torrance-sparrow options that
represent it exactly (F ≡ 1, Walter's rational Smith G₁, as Mitsuba)."""

from __future__ import annotations

from simulator.scene import BlendMaterial, DiffuseMaterial, RoughConductorMaterial

__all__ = ["MATERIAL", "OPTIONS"]

MATERIAL = BlendMaterial(
    weight=0.25,
    first=DiffuseMaterial(reflectance=(0.6, 0.45, 0.3)),
    second=RoughConductorMaterial(alpha=0.2, conductor="none"),
)
OPTIONS = {"fresnel": "none", "shadowing": "smith-rational", "distribution": "beckmann"}

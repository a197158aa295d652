"""Reference parameter values implied by a scene's material, for comparing fits with the truth.

Only materials that a model here represents exactly get reference values:
`blend(diffuse ρ, roughconductor α)` = (1 − w)ρ/π + w·(microfacet lobe with m = α), so
kd = (1 − w)ρ per channel, ks = w, m = α. These come from the scene config, never from a fit.
"""

from __future__ import annotations

from simulator.scene import (
    BlendMaterial,
    DiffuseMaterial,
    RoughConductorMaterial,
    Scene,
)

__all__ = ["reference_parameters"]


def reference_parameters(scene: Scene) -> dict[str, float]:
    mat = scene.material
    out: dict[str, float] = {}
    if isinstance(mat, DiffuseMaterial):
        for ch, rho in zip("RGB", mat.reflectance, strict=True):
            out[f"kd_{ch}"] = rho
        return out
    if isinstance(mat, RoughConductorMaterial):
        out["m"] = mat.alpha
        for ch in "RGB":
            out[f"kd_{ch}"] = 0.0
        return out
    if (
        isinstance(mat, BlendMaterial)
        and isinstance(mat.first, DiffuseMaterial)
        and isinstance(mat.second, RoughConductorMaterial)
    ):
        w = mat.weight
        for ch, rho, spec in zip(
            "RGB", mat.first.reflectance, mat.second.specular_reflectance, strict=True
        ):
            out[f"kd_{ch}"] = (1.0 - w) * rho
            out[f"ks_{ch}"] = w * spec
        out["m"] = mat.second.alpha
        return out
    return out

"""Reference parameter values implied by a scene's material, for comparing fits with the truth,
and Mitsuba's own BRDF of a material at given directions (the independent ground truth).

Only materials that a model here represents exactly get reference values:
`blend(diffuse ρ, roughconductor α)` = (1 − w)ρ/π + w·(microfacet lobe with m = α), so
kd = (1 − w)ρ per channel, ks = w, m = α. These come from the scene config, never from a fit.

The Fresnel truth of a conductor *preset* ("Au", "Cu", …) is not in the scene config: Mitsuba
turns its tabulated spectral (η, k) into one RGB value per channel when the BSDF is loaded in an
RGB variant. :func:`mitsuba_conductor_ior` reads those values back from the loaded BSDF
(``mi.traverse``: ``eta.value``, ``k.value``), so a ``fresnel=conductor`` model can be compared
with the same (η, k) Mitsuba uses. (Mitsuba 3.9.1, scalar_rgb: Au η = (0.1430, 0.3753, 1.4421),
k = (3.983, 2.3856, 1.6034); Cu η = (0.2010, 0.9238, 1.1022), k = (3.9133, 2.4531, 2.1421) —
the values of docs/design.md §6 to ≤ 0.3 %.)
"""

from __future__ import annotations

import numpy as np

from simulator.bsdf_eval import eval_fr
from simulator.materials import material_dict, model_bsdfs_alive, needs_wavefront
from simulator.scene import (
    BlendMaterial,
    DiffuseMaterial,
    RoughConductorMaterial,
    Scene,
)
from simulator.variant import use_variant

__all__ = [
    "reference_parameters",
    "material_reference_parameters",
    "mitsuba_conductor_ior",
    "mitsuba_brdf",
    "direct_samples",
]


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


def mitsuba_conductor_ior(
    material: RoughConductorMaterial, variant: str | None = None
) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
    """(η, k) per RGB channel that Mitsuba's loaded conductor BSDF uses; None for the perfect
    mirror ``conductor = "none"`` (F ≡ 1). Explicit ``eta``/``k`` are returned as given."""
    if material.eta is not None and material.k is not None:
        return tuple(material.eta), tuple(material.k)
    if (material.conductor or "none") == "none":
        return None
    import mitsuba as mi

    use_variant(variant)
    params = mi.traverse(mi.load_dict(material_dict(material)))

    def rgb(key: str) -> tuple[float, float, float]:
        v = np.ravel(np.asarray(params[key], dtype=np.float64))
        v = np.broadcast_to(v, (3,)) if v.size == 1 else v[:3]
        return tuple(float(x) for x in v)

    return rgb("eta.value"), rgb("k.value")


def material_reference_parameters(material, variant: str | None = None) -> dict[str, float]:
    """Reference values of ``torrance-sparrow`` (+ Lambert) parameters for a material that the
    model represents exactly, per channel name (``kd_R`` …, ``ks_R`` …, ``m``, and for a
    conductor ``eta_R`` …, ``k_R`` … from :func:`mitsuba_conductor_ior`).

    diffuse ρ → kd = ρ; roughconductor → kd = 0, ks = specular_reflectance, m = α;
    blend(diffuse, roughconductor; w) → kd = (1 − w)ρ, ks = w·specular_reflectance, m = α
    (Mitsuba's ``blendbsdf`` is (1 − w)·first + w·second). Other materials give {}.
    """
    out: dict[str, float] = {}
    conductor = None
    if isinstance(material, DiffuseMaterial):
        return {f"kd_{c}": float(r) for c, r in zip("RGB", material.reflectance, strict=True)}
    if isinstance(material, RoughConductorMaterial):
        conductor = material
        for c, s in zip("RGB", material.specular_reflectance, strict=True):
            out[f"kd_{c}"] = 0.0
            out[f"ks_{c}"] = float(s)
    elif (
        isinstance(material, BlendMaterial)
        and isinstance(material.first, DiffuseMaterial)
        and isinstance(material.second, RoughConductorMaterial)
    ):
        conductor = material.second
        w = float(material.weight)
        for c, rho, s in zip(
            "RGB", material.first.reflectance, conductor.specular_reflectance, strict=True
        ):
            out[f"kd_{c}"] = (1.0 - w) * float(rho)
            out[f"ks_{c}"] = w * float(s)
    else:
        return {}
    out["m"] = float(conductor.alpha)
    ior = mitsuba_conductor_ior(conductor, variant)
    if ior is not None:
        for c, eta, k in zip("RGB", *ior, strict=True):
            out[f"eta_{c}"] = eta
            out[f"k_{c}"] = k
    return out


def mitsuba_brdf(material, wi, wo, variant: str | None = None) -> np.ndarray:
    """f_r(ω_i, ω_o) (N, 3) in sr⁻¹ from Mitsuba's own BSDF of a scene material.

    ``wi`` (N, 3) points to the light, ``wo`` (N, 3) to the camera, sample frame. Mitsuba's
    ``bsdf.eval(ctx, si, w)`` returns f_r(si.wi, w)·cos θ_w; the direct integrator calls it
    with si.wi towards the camera and w towards the light, so we do the same and divide by
    cos θ_i (docs/design.md §3). Mitsuba runs in float32: pass directions that are exactly float32
    values if the comparison must not see their rounding. Below the horizon f_r = 0.
    """
    import mitsuba as mi

    variant = use_variant(variant)
    bsdf = mi.load_dict(material_dict(material))
    # A Python-model BSDF needs concrete arrays (wavefront mode), see simulator.materials.
    wavefront = needs_wavefront(material) or model_bsdfs_alive()
    return eval_fr(bsdf, wi, wo, variant, wavefront=wavefront)


def direct_samples(
    material,
    wi,
    wo,
    *,
    rel_sigma: float = 0.01,
    floor_sr: float = 1e-3,
    rng: np.random.Generator | int = 0,
    channels: str = "RGB",
    variant: str | None = None,
):
    """A noisy sample table of Mitsuba's own BRDF of ``material`` at the pairs (wi, wo), without
    the rig: f = f_true + N(0, σ²) with σ = rel_sigma·f_true + floor_sr per sample and channel.

    The directions are first rounded to float32 (Mitsuba's precision) and the table's angles
    are those of the rounded vectors, so data and model see the same geometry. Returns
    ``(table, f_true (N, 3))``.
    """
    from brdfdata.directions import normalize, vector_to_spherical
    from brdfdata.samples import SampleTable

    rng = np.random.default_rng(rng)
    wi = np.asarray(wi, dtype=np.float32).astype(np.float64)
    wo = np.asarray(wo, dtype=np.float32).astype(np.float64)
    f_true = mitsuba_brdf(material, wi, wo, variant)
    # Angles of the unit vectors (the float32 rounding leaves |w| = 1 ± 6e-8).
    ti, pi = vector_to_spherical(normalize(wi))
    to, po = vector_to_spherical(normalize(wo))
    cols = [("RGB".index(c), c) for c in channels]
    n = wi.shape[0]
    f_t = np.concatenate([f_true[:, i] for i, _ in cols])
    sigma = rel_sigma * f_t + floor_sr
    table = SampleTable(
        theta_i=np.tile(ti, len(cols)),
        phi_i=np.tile(pi, len(cols)),
        theta_o=np.tile(to, len(cols)),
        phi_o=np.tile(po, len(cols)),
        channel=np.repeat(np.array([c for _, c in cols]), n),
        f=f_t + sigma * rng.standard_normal(f_t.size),
        sigma=sigma,
        flags=np.zeros(f_t.size, dtype=np.int32),
    )
    return table, f_true

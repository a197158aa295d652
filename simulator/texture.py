"""The textured sample (`simulator.scene.TexturedMaterial`): its per-texel truth maps and the
Mitsuba description that renders them.

Truth: per texel kd_R, kd_G, kd_B, ks, m (float64 copies of the float32 values Mitsuba holds, so
the truth is exactly what is rendered). Mitsuba: ``blendbsdf`` with bitmap textures (nearest
lookup, raw values, clamped): weight = ks, diffuse ρ = kd/(1 − ks), roughconductor α = m with
F ≡ 1 (``conductor = "none"``), so f = (1 − ks)·ρ/π + ks·lobe = kd/π + ks·lobe (simulator.truth).

Texel layout (matches calibration's per-texel index, calibration.texels): the rectangle has
uv = (local + 1)/2 and the bitmap row index grows with v (world +y, simulator.render), so bitmap
row iy, column ix is the texel at x ∈ [−s/2 + ix·t, …), y ∈ [−s/2 + iy·t, …); index iy·N + ix.
"""

from __future__ import annotations

import json

import numpy as np

from simulator.bsdf_eval import eval_fr
from simulator.scene import TexturedMaterial
from simulator.variant import use_variant

__all__ = [
    "TRUTH_NAMES",
    "texel_truth",
    "textured_dict",
    "texel_uv",
    "textured_brdf",
    "texel_direct_samples",
]

TRUTH_NAMES = ("kd_R", "kd_G", "kd_B", "ks", "m")


def texel_truth(material: TexturedMaterial) -> dict[str, np.ndarray]:
    """Per-texel truth, each (N·N,) float64 indexed iy·N + ix (see module docstring)."""
    n = material.texels
    rng = np.random.default_rng(material.seed)
    lo, hi = np.asarray(material.kd_range[0]), np.asarray(material.kd_range[1])
    kd = lo + (hi - lo) * rng.random((n * n, 3))
    ks = rng.uniform(*material.ks_range, size=n * n)
    # Roughness log-uniform: equal weight per decade, as roughness is a scale parameter.
    log_m = rng.uniform(np.log(material.m_range[0]), np.log(material.m_range[1]), size=n * n)
    out = {"kd_R": kd[:, 0], "kd_G": kd[:, 1], "kd_B": kd[:, 2], "ks": ks, "m": np.exp(log_m)}
    # Mitsuba's bitmaps are float32: the truth is the rounded value it renders.
    return {k: v.astype(np.float32).astype(np.float64) for k, v in out.items()}


def _bitmap(mi, values: np.ndarray, n: int) -> dict:
    """A raw nearest-lookup bitmap texture from per-texel values (N·N,) or (N·N, 3)."""
    arr = np.asarray(values, dtype=np.float32).reshape(n, n, -1)
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(arr)),
        "raw": True,  # data values, not sRGB colours
        "filter_type": "nearest",  # piecewise constant per texel: the truth is one value each
        "wrap_mode": "clamp",
    }


def textured_dict(material: TexturedMaterial) -> dict:
    """Mitsuba ``load_dict`` description of the textured sample (needs a variant set)."""
    import mitsuba as mi

    t = texel_truth(material)
    n = material.texels
    kd = np.stack([t["kd_R"], t["kd_G"], t["kd_B"]], axis=-1)
    rho = kd / (1.0 - t["ks"][:, None])
    return {
        "type": "blendbsdf",
        "weight": _bitmap(mi, t["ks"], n),
        "bsdf_0_first": {"type": "diffuse", "reflectance": _bitmap(mi, rho, n)},
        "bsdf_1_second": {
            "type": "roughconductor",
            "distribution": "beckmann",
            "alpha": _bitmap(mi, t["m"], n),
            "material": "none",
        },
    }


def texel_uv(material: TexturedMaterial, texel: np.ndarray) -> np.ndarray:
    """(u, v) (K, 2) of the centres of texels ``texel`` (indices iy·N + ix)."""
    n = material.texels
    texel = np.asarray(texel, dtype=np.int64)
    return np.stack([(texel % n + 0.5) / n, (texel // n + 0.5) / n], axis=-1)


def textured_brdf(material: TexturedMaterial, wi, wo, texel, variant: str | None = None):
    """f_r (K, 3) in sr⁻¹ from Mitsuba's own textured BSDF at texel centres ``texel`` (K,),
    ``wi`` to the light and ``wo`` to the camera (K, 3) each, sample frame."""
    import mitsuba as mi

    variant = use_variant(variant)
    bsdf = mi.load_dict(textured_dict(material))
    return eval_fr(bsdf, wi, wo, variant, uv=texel_uv(material, texel))


def texel_direct_samples(
    material: TexturedMaterial,
    wi,
    wo,
    texel,
    *,
    counts_per_sr: float = 1e4,
    rng: np.random.Generator | int = 0,
    variant: str | None = None,
):
    """A per-texel sample table of Mitsuba's own textured BSDF without the rig: rows (K,) per
    channel R, G, B at directions ``wi``/``wo`` (K, 3) in texels ``texel`` (K,), with
    photon-like noise — a sample of f is a count c = f·counts_per_sr (Poisson), so
    σ = √(f/counts_per_sr) (1 % at f = 1 sr⁻¹ with the default) and f̂ = c/counts_per_sr.

    Directions are rounded to float32 first (Mitsuba's precision) and the table's angles are
    those of the rounded vectors. Returns ``(table, f_true (K, 3))``.
    """
    from brdfdata.directions import normalize, vector_to_spherical
    from brdfdata.samples import SampleTable

    rng = np.random.default_rng(rng)
    wi = normalize(np.asarray(wi, dtype=np.float32).astype(np.float64))
    wo = normalize(np.asarray(wo, dtype=np.float32).astype(np.float64))
    texel = np.asarray(texel, dtype=np.int64)
    f_true = textured_brdf(material, wi, wo, texel, variant)
    ti, pi = vector_to_spherical(wi)
    to, po = vector_to_spherical(wo)
    f_t = np.concatenate([f_true[:, c] for c in range(3)])
    f_hat = rng.poisson(f_t * counts_per_sr) / counts_per_sr
    # σ from the true rate (the expected count), as a calibrated noise model gives it; a floor
    # of one count keeps σ > 0 where f = 0.
    sigma = np.sqrt(np.maximum(f_t * counts_per_sr, 1.0)) / counts_per_sr
    k = wi.shape[0]
    table = SampleTable(
        theta_i=np.tile(ti, 3),
        phi_i=np.tile(pi, 3),
        theta_o=np.tile(to, 3),
        phi_o=np.tile(po, 3),
        channel=np.repeat(np.array(["R", "G", "B"]), k),
        f=f_hat,
        sigma=sigma,
        flags=np.zeros(3 * k, dtype=np.int32),
        extra={"texel": np.tile(texel, 3).astype(np.int32)},
        metadata={
            "gonio.texels": json.dumps(
                {"texel_mm": None, "n_x": material.texels, "n_y": material.texels}
            )
        },
    )
    return table, f_true

"""torrance-sparrow (Smith, conductor; Beckmann and GGX) against Mitsuba 3's roughconductor.

Mitsuba is an independent implementation of the same physics: π-normalised Beckmann D with
α = m, separable Smith G with Walter's rational G₁, exact conductor Fresnel (docs/design.md §7). Its
``bsdf.eval`` returns f·cos θ_o for si.wi = ω_i and the argument wo = ω_o (both pointing away
from the surface, local frame = sample frame), so we compare eval/cos θ_o with f.

Mitsuba's pip variants are single precision: the directions are rounded to float32 first and
the *same* float32 values (as float64) go into our model, so only Mitsuba's internal float32
arithmetic separates the two. Its relative error is a few ulps of float32 (6e-8) times the
condition number of exp(−tan²θ_h/m²), i.e. tan²θ_h/m² ≤ ~46 where Mitsuba cuts D off
(D cos θ_h < 1e-20): ≲ 1e-5 worst case, ~1e-7 typical — hence median ≤ 1e-5, max ≤ 1e-3.
"""

from __future__ import annotations

import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from brdfdata.directions import reflect, spherical_to_vector, uniform_hemisphere
from fitting import models

ETA, K = 0.2004, 3.9129  # copper, red channel (docs/design.md §6)

_PROBE = """
import mitsuba as mi, drjit as dr
mi.set_variant('llvm_ad_rgb')
b = mi.load_dict({'type': 'roughconductor', 'distribution': 'beckmann', 'alpha': 0.2})
si = dr.zeros(mi.SurfaceInteraction3f, 4)
si.wi = mi.Vector3f(0, 0, 1)
si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
v = b.eval(mi.BSDFContext(), si, mi.Vector3f(0, 0, 1))
dr.eval(v)
print(float(v[0][0]) > 0)
"""


@pytest.fixture(scope="module")
def variant():
    # LLVM 15/16 can abort the whole process (docs/design.md §7): probe in a subprocess first.
    try:
        res = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, timeout=120)
        ok = res.returncode == 0 and res.stdout.strip().endswith(b"True")
    except subprocess.TimeoutExpired:
        ok = False
    name = "llvm_ad_rgb" if ok else "scalar_rgb"
    mi.set_variant(name)
    return name


def mitsuba_f(variant, distribution, m, wi, wo):
    """Mitsuba roughconductor f = eval/cos θ_o for float32 direction arrays (N, 3)."""
    mi.set_variant(variant)
    bsdf = mi.load_dict(
        {"type": "roughconductor", "distribution": distribution, "alpha": m, "eta": ETA, "k": K}
    )
    ctx = mi.BSDFContext()
    if variant.startswith("llvm"):
        si = dr.zeros(mi.SurfaceInteraction3f, wi.shape[0])
        si.wi = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        val = np.array(bsdf.eval(ctx, si, mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2])))[0]
    else:
        val = np.empty(wi.shape[0])
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        for j in range(wi.shape[0]):
            si.wi = mi.Vector3f(*map(float, wi[j]))
            val[j] = bsdf.eval(ctx, si, mi.Vector3f(*map(float, wo[j])))[0]
    return val.astype(np.float64) / wo[:, 2].astype(np.float64)


def direction_pairs(m, n=10_000, seed=0):
    """float32-rounded pairs: 40 % inside the specular lobe (h drawn from Beckmann), 20 % with
    a grazing ω_i (within 1° of 90°) and ω_o in its lobe, 20 % with a grazing ω_o, 20 %
    uniform over the hemisphere."""
    rng = np.random.default_rng(seed)
    wi = uniform_hemisphere(n, rng)
    wo = uniform_hemisphere(n, rng)
    lobe, graze_i, graze_o = (
        slice(0, 6 * n // 10),
        slice(4 * n // 10, 6 * n // 10),
        slice(6 * n // 10, 8 * n // 10),
    )

    def grazing(count):
        theta = np.radians(90 - rng.uniform(0, 1, count))
        return spherical_to_vector(theta, rng.uniform(0, 2 * np.pi, count))

    wi[graze_i] = grazing(n // 5)
    wo[graze_o] = grazing(n // 5)
    # tan θ_h = m sqrt(−ln u) samples the Beckmann slope distribution; ω_o = mirror of ω_i
    count = 6 * n // 10
    tan_h = m * np.sqrt(-np.log(rng.uniform(1e-12, 1, count)))
    h = spherical_to_vector(np.arctan(tan_h), rng.uniform(0, 2 * np.pi, count))
    wo[lobe] = reflect(wi[lobe], h)
    wi32, wo32 = wi.astype(np.float32), wo.astype(np.float32)
    keep = (wi32[:, 2] > 0) & (wo32[:, 2] > 0)
    return wi32[keep], wo32[keep]


# Mitsuba's Smith G₁ is Walter's rational fit for Beckmann and the exact G₁ for GGX, which
# our "smith-rational" reproduces (for GGX "smith" is the same function).
@pytest.mark.parametrize("m", [0.05, 0.2, 0.6])
@pytest.mark.parametrize(
    ("distribution", "shadowing"),
    [("beckmann", "smith-rational"), ("ggx", "smith-rational"), ("ggx", "smith")],
)
def test_roughconductor(variant, distribution, shadowing, m):
    wi32, wo32 = direction_pairs(m)
    ref = mitsuba_f(variant, distribution, m, wi32, wo32)
    model = models.get(
        "torrance-sparrow", distribution=distribution, shadowing=shadowing, fresnel="conductor"
    )
    ours = model.evaluate(
        {"kd": 0.0, "ks": 1.0, "m": m, "eta": ETA, "k": K},
        wi32.astype(np.float64),
        wo32.astype(np.float64),
    )
    positive = ref > 0
    assert positive.sum() > 0.4 * ref.size  # the comparison covers the lobe and more
    # Where Mitsuba returns 0 it has cut D off at D cos θ_h < 1e-20 (or underflowed in
    # float32): ours must be negligible there.
    cos_o = wo32[~positive, 2].astype(np.float64)
    assert np.all(ours[~positive] * cos_o < 1e-15)
    rel = np.abs(ours[positive] - ref[positive]) / ref[positive]
    assert np.median(rel) <= 1e-5
    assert np.max(rel) <= 1e-3
    # grazing pairs specifically (either direction within 1° of the horizon)
    graze = positive & ((wi32[:, 2] < np.sin(np.radians(1))) | (wo32[:, 2] < np.sin(np.radians(1))))
    assert graze.sum() > 1000
    rel_g = np.abs(ours[graze] - ref[graze]) / ref[graze]
    assert np.max(rel_g) <= 1e-3


# --- anisotropic: torrance-sparrow-anisotropic against Mitsuba's anisotropic roughconductor ----


def mitsuba_f_anisotropic(variant, distribution, alpha_u, alpha_v, wi, wo):
    """Mitsuba roughconductor with alpha_u (tangent = local +x) and alpha_v, f = eval/cos θ_o."""
    mi.set_variant(variant)
    bsdf = mi.load_dict(
        {
            "type": "roughconductor",
            "distribution": distribution,
            "alpha_u": alpha_u,
            "alpha_v": alpha_v,
            "eta": ETA,
            "k": K,
        }
    )
    ctx = mi.BSDFContext()
    if variant.startswith("llvm"):
        si = dr.zeros(mi.SurfaceInteraction3f, wi.shape[0])
        si.wi = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        val = np.array(bsdf.eval(ctx, si, mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2])))[0]
    else:
        val = np.empty(wi.shape[0])
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        for j in range(wi.shape[0]):
            si.wi = mi.Vector3f(*map(float, wi[j]))
            val[j] = bsdf.eval(ctx, si, mi.Vector3f(*map(float, wo[j])))[0]
    return val.astype(np.float64) / wo[:, 2].astype(np.float64)


def anisotropic_pairs(ax, ay, phi0, n=24_000, seed=1):
    """Pairs in the *tangent* frame (float32) and the same pairs in the sample frame (float64,
    rotated by +φ₀ exactly from the float32 values): 60 % inside the anisotropic lobe (slopes
    drawn from the anisotropic Beckmann), 20 % with ω_i and 20 % with ω_o within 1° of the
    horizon, the rest uniform — the lobe share overlaps the grazing ones as in direction_pairs."""
    rng = np.random.default_rng(seed)
    wi = uniform_hemisphere(n, rng)
    wo = uniform_hemisphere(n, rng)
    k = 6 * n // 10
    slope = np.stack([ax * rng.standard_normal(k), ay * rng.standard_normal(k)], 1) / np.sqrt(2)
    h = np.concatenate([-slope, np.ones((k, 1))], 1)
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    g = n // 5
    grazing = spherical_to_vector(
        np.radians(90 - rng.uniform(0, 1, 2 * g)), rng.uniform(0, 2 * np.pi, 2 * g)
    )
    wi[4 * n // 10 : 4 * n // 10 + g] = grazing[:g]
    wo[k : k + g] = grazing[g:]
    wo[:k] = reflect(wi[:k], h)
    li, lo = wi.astype(np.float32), wo.astype(np.float32)
    keep = (li[:, 2] > 0) & (lo[:, 2] > 0)
    li, lo = li[keep], lo[keep]
    c, s = np.cos(phi0), np.sin(phi0)

    def to_sample(v):  # tangent frame → sample frame: rotate by +φ₀ about the normal
        v = v.astype(np.float64)
        return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], 1)

    return li, lo, to_sample(li), to_sample(lo)


# Acceptance (issue 19): median ≤ 1e-5, max ≤ 1e-3 relative over ≥ 1e4 pairs incl. grazing.
# Same argument as above: Mitsuba's float32 arithmetic (condition number of exp(−q) up to the
# 1e-20 cut-off) bounds the difference; our rotation back to the sample frame is float64 and
# adds ~1e-16 to the directions.
@pytest.mark.parametrize("phi0", [0.3, -1.2])
@pytest.mark.parametrize("alphas", [(0.05, 0.3), (0.2, 0.6)])
@pytest.mark.parametrize(
    ("distribution", "shadowing"), [("beckmann", "smith-rational"), ("ggx", "smith")]
)
def test_anisotropic_roughconductor(variant, distribution, shadowing, alphas, phi0):
    ax, ay = alphas
    li, lo, wi, wo = anisotropic_pairs(ax, ay, phi0)
    assert li.shape[0] >= 10_000
    ref = mitsuba_f_anisotropic(variant, distribution, ax, ay, li, lo)
    model = models.get(
        "torrance-sparrow-anisotropic",
        distribution=distribution,
        shadowing=shadowing,
        fresnel="conductor",
    )
    p = {"kd": 0.0, "ks": 1.0, "alpha_x": ax, "alpha_y": ay, "phi0": phi0, "eta": ETA, "k": K}
    ours = model.evaluate(p, wi, wo)
    positive = ref > 0
    assert positive.sum() >= 10_000
    assert np.all(ours[~positive] * wo[~positive, 2] < 1e-15)  # Mitsuba's D cut-off
    rel = np.abs(ours[positive] - ref[positive]) / ref[positive]
    assert np.median(rel) <= 1e-5
    assert np.max(rel) <= 1e-3
    graze = positive & ((li[:, 2] < np.sin(np.radians(1))) | (lo[:, 2] < np.sin(np.radians(1))))
    assert graze.sum() > 1000
    assert np.max(np.abs(ours[graze] - ref[graze]) / ref[graze]) <= 1e-3

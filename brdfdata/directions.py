"""Directions and angle conventions in the sample frame (docs/design.md §3).

+z is the sample normal, +x the reference direction on the holder, φ counted from +x toward +y.
Both ω_i (toward the light) and ω_o (toward the camera) point *away* from the surface.
Angles are radians everywhere inside the code.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "grid_direction_pairs",
    "spherical_to_vector",
    "vector_to_spherical",
    "normalize",
    "reflect",
    "uniform_hemisphere",
    "isotropic_gonio_directions",
    "SPECULAR_OFFSETS_DEG",
]


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis (zero vectors stay zero rather than becoming NaN)."""
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def spherical_to_vector(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(θ, φ) in radians → unit vectors of shape (..., 3) in the sample frame."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    s = np.sin(theta)
    return np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(theta)], axis=-1)


def vector_to_spherical(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (..., 3) → (θ, φ) in radians, θ ∈ [0, π], φ ∈ [0, 2π).

    θ uses atan2 of the tangential and normal parts, which stays accurate near the pole and
    the horizon (arccos loses half the digits near θ = 0). φ is 0 where it is undefined (θ = 0).
    """
    v = np.asarray(v, dtype=np.float64)
    rho = np.hypot(v[..., 0], v[..., 1])
    theta = np.arctan2(rho, v[..., 2])
    phi = np.mod(np.arctan2(v[..., 1], v[..., 0]), 2.0 * np.pi)
    phi = np.where(rho > 0, phi, 0.0)
    return theta, phi


def reflect(v: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Mirror v about the unit axis n: r = 2(v·n)n − v (both (..., 3); v and r point away)."""
    v = np.asarray(v, dtype=np.float64)
    n = np.asarray(n, dtype=np.float64)
    return 2.0 * np.sum(v * n, axis=-1, keepdims=True) * n - v


def uniform_hemisphere(count: int, rng: np.random.Generator | int | None) -> np.ndarray:
    """``count`` unit vectors uniformly distributed over the upper hemisphere (z ≥ 0).

    cos θ uniform in [0, 1) and φ uniform in [0, 2π) gives a uniform density 1/(2π) per sr.
    """
    rng = np.random.default_rng(rng)
    cos_t = rng.uniform(0.0, 1.0, count)
    phi = rng.uniform(0.0, 2.0 * np.pi, count)
    sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


#: In-plane offsets θ_o − θ_i (deg) of the specular scan in :func:`isotropic_gonio_directions`:
#: 0.5° steps near the mirror (a Beckmann lobe with m = 0.03 falls to 1/e at |δ| ≈ 2m ≈ 3.4°
#: in θ_o, since θ_h ≈ δ/2 in the plane, so ≥ 6 samples per side lie inside it), then widening
#: steps that follow lobes up to m ≈ 0.6 (1/e at ≈ 70°).
SPECULAR_OFFSETS_DEG = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 9.0, 13.0, 18.0, 25.0, 35.0, 50.0)


def grid_direction_pairs(theta_i_deg, theta_o_deg, phi_o_deg) -> tuple[np.ndarray, np.ndarray]:
    """Every (ω_i, ω_o) of a full grid: θ_i (deg, light at φ = 0) × θ_o × φ_o (deg), each
    (N, 3) with N the product of the three lengths, θ_i slowest."""
    ti, to, po = np.meshgrid(
        np.radians(theta_i_deg), np.radians(theta_o_deg), np.radians(phi_o_deg), indexing="ij"
    )
    ti, to, po = ti.ravel(), to.ravel(), po.ravel()
    return spherical_to_vector(ti, np.zeros_like(ti)), spherical_to_vector(to, po)


def isotropic_gonio_directions(
    theta_i_deg=(10.0, 25.0, 40.0, 55.0, 70.0),
    specular_offsets_deg=SPECULAR_OFFSETS_DEG,
    azimuth_offsets_deg=(0.5, 1.0, 2.0, 4.0, 8.0, 16.0),
    coarse_theta_o_deg=(0.0, 15.0, 30.0, 45.0, 60.0, 75.0),
    coarse_phi_o_deg=(0.0, 45.0, 90.0, 135.0),
    max_theta_deg: float = 85.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Direction pairs (ω_i, ω_o), each (N, 3), of an isotropic gonioreflectometer plan.

    The light sits at φ_i = 0 and each θ_i; per θ_i the camera visits (a) the incidence plane
    (φ_o = π) at θ_o = θ_i ± δ for δ in ``specular_offsets_deg`` (negative θ_o continues the
    plane through the normal to φ_o = 0), (b) out of the plane at θ_o = θ_i, φ_o = π ± Δφ for
    Δφ in ``azimuth_offsets_deg``, and (c) a coarse hemisphere grid θ_o × φ_o for the diffuse
    part. Directions with θ_o > ``max_theta_deg`` are dropped (a real arm cannot reach the
    horizon); duplicates are removed.
    """
    rows = []
    for ti in theta_i_deg:
        for d in sorted({s * x for x in specular_offsets_deg for s in (1.0, -1.0)}):
            to = ti + d
            rows.append((ti, abs(to), 180.0 if to >= 0 else 0.0))
        for dp in azimuth_offsets_deg:
            rows.extend([(ti, ti, 180.0 + dp), (ti, ti, 180.0 - dp)])
        for to in coarse_theta_o_deg:
            for po in coarse_phi_o_deg:
                rows.append((ti, to, po if to > 0 else 0.0))
    a = np.unique(np.round(np.array(rows, dtype=np.float64), 9), axis=0)
    a = a[a[:, 1] <= max_theta_deg]
    t = np.radians(a)
    wi = spherical_to_vector(t[:, 0], np.zeros(len(t)))
    wo = spherical_to_vector(t[:, 1], t[:, 2])
    return wi, wo

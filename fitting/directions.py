"""Directions and angle conventions in the sample frame (DESIGN §3).

+z is the sample normal, +x the reference direction on the holder, φ counted from +x toward +y.
Both ω_i (toward the light) and ω_o (toward the camera) point *away* from the surface.
Angles are radians everywhere inside the code.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "spherical_to_vector",
    "vector_to_spherical",
    "normalize",
    "reflect",
    "uniform_hemisphere",
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

"""Rusinkiewicz half/difference angles (θ_h, θ_d, φ_d) for isotropic BRDFs (docs/design.md §3).

S. Rusinkiewicz, "A new change of variables for efficient BRDF representation", EGWR 1998, §3:
h = (ω_i + ω_o)/|ω_i + ω_o| with spherical angles (θ_h, φ_h); the difference vector is ω_i
expressed in the frame where h is the pole, d = R_y(−θ_h) R_z(−φ_h) ω_i, with angles (θ_d, φ_d).
For an isotropic BRDF φ_h does not matter. ω_o is the mirror of d about the half vector:
in the half frame ω_o = (−d_x, −d_y, d_z).

Stability: all angles come from atan2 of vector components (see brdfdata.directions), so θ = 0
(φ undefined, taken as 0) and the poles are handled without arccos's loss of digits.
"""

from __future__ import annotations

import numpy as np

from brdfdata.directions import normalize, spherical_to_vector, vector_to_spherical

__all__ = ["to_half_diff", "from_half_diff", "half_vector"]


def half_vector(wi, wo) -> np.ndarray:
    """Unit half vector h = (ω_i + ω_o)/|ω_i + ω_o| (zero where ω_i = −ω_o)."""
    return normalize(np.asarray(wi, dtype=np.float64) + np.asarray(wo, dtype=np.float64))


def _rot_z(v, angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], -1)


def _rot_y(v, angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] + s * v[..., 2], v[..., 1], -s * v[..., 0] + c * v[..., 2]], -1)


def to_half_diff(wi, wo) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ω_i, ω_o) unit vectors (..., 3) → (θ_h, θ_d, φ_d) in radians (Rusinkiewicz 1998, §3).

    θ_h ∈ [0, π], θ_d ∈ [0, π/2] for directions above the horizon, φ_d ∈ [0, 2π).
    """
    wi = np.asarray(wi, dtype=np.float64)
    h = half_vector(wi, wo)
    theta_h, phi_h = vector_to_spherical(h)
    d = _rot_y(_rot_z(wi, -phi_h), -theta_h)
    theta_d, phi_d = vector_to_spherical(d)
    return theta_h, theta_d, phi_d


def from_half_diff(theta_h, theta_d, phi_d, phi_h=0.0) -> tuple[np.ndarray, np.ndarray]:
    """(θ_h, θ_d, φ_d[, φ_h]) in radians → (ω_i, ω_o) unit vectors of shape (..., 3)."""
    theta_h, theta_d, phi_d, phi_h = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (theta_h, theta_d, phi_d, phi_h))
    )
    d = spherical_to_vector(theta_d, phi_d)
    d_mirror = d * np.array([-1.0, -1.0, 1.0])
    wi = _rot_z(_rot_y(d, theta_h), phi_h)
    wo = _rot_z(_rot_y(d_mirror, theta_h), phi_h)
    return wi, wo

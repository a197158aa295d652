"""Fresnel reflectance of a smooth interface (docs/design.md §5), unpolarised, vectorised.

All functions take the cosine of the angle of incidence measured from the (micro)surface normal
and broadcast over every argument. Results are dimensionless reflectances in [0, 1].

References
----------
Born & Wolf, *Principles of Optics*, 7th ed., §1.5.2 (dielectric) and §14.2 (absorbing media);
Schlick, "An inexpensive BRDF model for physically-based rendering", CGF 13(3), 1994, eq. 24.
"""

from __future__ import annotations

import numpy as np

__all__ = ["dielectric", "dielectric_sp", "conductor", "conductor_sp", "schlick"]


def dielectric_sp(cos_theta, ior) -> tuple[np.ndarray, np.ndarray]:
    """s- and p-polarised reflectances (R_s, R_p) of a dielectric interface.

    Born & Wolf eqs. 1.5(21a,b) written without the refraction angle:
    with c = cos θ_i and u = η cos θ_t = sqrt(η² − sin²θ_i),
        R_s = ((c − u)/(c + u))²,    R_p = ((η² c − u)/(η² c + u))².
    η = n_t/n_i is the *relative* index (η < 1 for light leaving a denser medium). When
    η² < sin²θ_i the wave is totally internally reflected and both reflectances are 1.
    At grazing incidence (c = 0) both are 1 (their limit for η ≠ 1); η = 1 gives 0 elsewhere.
    """
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0)
    eta = np.asarray(ior, dtype=np.float64)
    eta2 = eta * eta
    # (η² − 1) + c² rather than η² − (1 − c²): exact for η = 1 and accurate at grazing
    u2 = (eta2 - 1.0) + c * c
    tir = u2 <= 0.0
    u = np.sqrt(np.where(tir, 0.0, u2))
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = ((c - u) / (c + u)) ** 2
        rp = ((eta2 * c - u) / (eta2 * c + u)) ** 2
    # c + u == 0 only at c = 0 with η = 1 (no interface, grazing): take the grazing limit 1.
    degenerate = tir | ~np.isfinite(rs) | ~np.isfinite(rp)
    return np.where(degenerate, 1.0, rs), np.where(degenerate, 1.0, rp)


def dielectric(cos_theta, ior) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a dielectric, F = (R_s + R_p)/2 (Born & Wolf §1.5).

    ``ior`` is the relative index η (any η > 0; η < 1 and total internal reflection → 1).
    """
    rs, rp = dielectric_sp(cos_theta, ior)
    return 0.5 * (rs + rp)


def conductor_sp(cos_theta, eta, k) -> tuple[np.ndarray, np.ndarray]:
    """s- and p-polarised reflectances of an absorbing medium with complex index η̃ = η + i k.

    Born & Wolf §14.2 in the refraction-angle-free form: with u = sqrt(η̃² − sin²θ_i)
    (principal branch, Im u ≥ 0 for k ≥ 0),
        R_s = |(c − u)/(c + u)|²,    R_p = |(η̃² c − u)/(η̃² c + u)|².
    With k = 0 this reduces exactly to :func:`dielectric_sp` (including TIR).
    """
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0)
    n = np.asarray(eta, dtype=np.float64) + 1j * np.asarray(k, dtype=np.float64)
    n2 = n * n
    u = np.sqrt((n2 - 1.0) + c * c + 0j)
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = np.abs((c - u) / (c + u)) ** 2
        rp = np.abs((n2 * c - u) / (n2 * c + u)) ** 2
    # 0/0 only at c = 0 with η̃ = 1: grazing limit 1 (as for the dielectric).
    rs = np.where(np.isfinite(rs), rs, 1.0)
    rp = np.where(np.isfinite(rp), rp, 1.0)
    return np.minimum(rs, 1.0), np.minimum(rp, 1.0)


def conductor(cos_theta, eta, k) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a conductor with complex IOR η + i k (Born & Wolf §14.2).

    At normal incidence F₀ = ((η − 1)² + k²)/((η + 1)² + k²).
    """
    rs, rp = conductor_sp(cos_theta, eta, k)
    return 0.5 * (rs + rp)


def schlick(cos_theta, f0) -> np.ndarray:
    """Schlick's approximation F = F₀ + (1 − F₀)(1 − cos θ)⁵ (Schlick 1994, eq. 24).

    An *option* only: at η = 1.5 it gives 0.0700 at 60° where the exact value is 0.0892.
    """
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0)
    f0 = np.asarray(f0, dtype=np.float64)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5

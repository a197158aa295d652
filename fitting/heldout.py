"""Scoring a fit where it was not measured: a dense held-out grid of direction pairs and the
errors of a fitted model against the truth on it (how the real-materials study ranks models).

Metrics (`heldout_errors`):

- Ngan et al.'s cosine-weighted L2 ("Experimental Analysis of BRDF Models", EGSR 2005;
  docs/design.md §6): plain L2 on f·cos θ_i weighted by sin θ_i sin θ_o, as a mean over the grid (an
  RMS per unit solid angle on a regular (θ_i, θ_o, Δφ) grid), in sr⁻¹:
      E_Ngan = √( Σ_j w_j ((f̂_j − f_j) cos θ_i,j)² / Σ_j w_j ),   w_j = sin θ_i,j sin θ_o,j;
- the relative RMS of f·cos θ_i, the same sum normalised by the truth's own norm (so materials
  of very different brightness compare):
      E_rel = √( Σ_j w_j ((f̂_j − f_j) cos θ_i,j)² / Σ_j w_j (f_j cos θ_i,j)² ).

`lambert_floor` is the least E_rel any Lambertian reaches on the grid: a model that does not
beat it has learnt nothing beyond a constant albedo.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["HeldoutGrid", "heldout_grid", "heldout_errors", "lambert_floor"]


@dataclass(frozen=True)
class HeldoutGrid:
    """Direction pairs (N, 3) with φ_i = 0, φ_o = Δφ, their angles (rad) and cell weights."""

    wi: np.ndarray
    wo: np.ndarray
    theta_i: np.ndarray
    theta_o: np.ndarray
    delta_phi: np.ndarray
    weight: np.ndarray


def heldout_grid(
    theta_i_deg: Sequence[float] = (15.0, 25.0, 35.0, 45.0, 55.0, 65.0),
    theta_o_step_deg: float = 1.0,
    theta_o_max_deg: float = 80.0,
    delta_phi_step_deg: float = 2.5,
) -> HeldoutGrid:
    """A dense grid of (ω_i, ω_o) pairs that no plan measures: incidence angles halfway between
    the plans' (10°, 20°, … 70°; a pose's pixels span only ±3° in θ_i), θ_o and Δφ on cell
    midpoints over [0, θ_o,max] × [0°, 180°] (isotropic materials: f depends on |Δφ|). θ_o,max
    is the plans' largest θ_o: the grid tests interpolation between measured directions, not
    extrapolation to grazing angles no pose saw.

    ``weight`` = sin θ_i sin θ_o (Ngan et al.'s weighting); on a regular grid Σ w ≈ the solid-
    angle integral up to the constant cell size. 1° × 2.5° cells resolve a lobe of width ~2°
    (nickel's m = 0.042) to a few samples.
    """
    from brdfdata.directions import spherical_to_vector

    ti = np.radians(np.asarray(theta_i_deg, dtype=np.float64))
    n_o = int(round(theta_o_max_deg / theta_o_step_deg))
    to = np.radians((np.arange(n_o) + 0.5) * theta_o_step_deg)
    n_p = int(round(180.0 / delta_phi_step_deg))
    dp = np.radians((np.arange(n_p) + 0.5) * delta_phi_step_deg)
    TI, TO, DP = (a.ravel() for a in np.meshgrid(ti, to, dp, indexing="ij"))
    wi = spherical_to_vector(TI, np.zeros_like(TI))
    wo = spherical_to_vector(TO, DP)
    return HeldoutGrid(wi, wo, TI, TO, DP, np.sin(TI) * np.sin(TO))


def heldout_errors(
    f_fit: np.ndarray, f_true: np.ndarray, theta_i: np.ndarray, weight: np.ndarray
) -> dict[str, float]:
    """Ngan's cosine-weighted L2 (sr⁻¹) and the relative RMS of f·cos θ_i (module doc).

    ``f_fit``, ``f_true``: (N,) or (N, C) for C channels (pooled); ``theta_i``, ``weight``: (N,).
    """
    f_fit = np.asarray(f_fit, dtype=np.float64)
    f_true = np.asarray(f_true, dtype=np.float64)
    if f_fit.ndim == 1:
        f_fit, f_true = f_fit[:, None], f_true[:, None]
    c = np.cos(np.asarray(theta_i, dtype=np.float64))[:, None]
    w = np.broadcast_to(np.asarray(weight, dtype=np.float64)[:, None], f_fit.shape)
    d2 = np.sum(w * ((f_fit - f_true) * c) ** 2)
    t2 = np.sum(w * (f_true * c) ** 2)
    return {
        "ngan_l2": float(math.sqrt(d2 / np.sum(w))),
        "rel_rms": float(math.sqrt(d2 / t2)) if t2 > 0 else float("nan"),
    }


def lambert_floor(f_true: np.ndarray, theta_i: np.ndarray, weight: np.ndarray) -> float:
    """The least held-out relative error any Lambertian can reach on the grid (per channel
    the kd minimising Σ w (kd/π − f)² cos² θ_i, i.e. kd/π = Σ w f cos² θ_i / Σ w cos² θ_i)."""
    f_true = np.asarray(f_true, dtype=np.float64)
    if f_true.ndim == 1:
        f_true = f_true[:, None]
    wc = (np.asarray(weight) * np.cos(np.asarray(theta_i)) ** 2)[:, None]
    level = np.sum(wc * f_true, axis=0) / np.sum(wc, axis=0)
    return heldout_errors(np.broadcast_to(level, f_true.shape), f_true, theta_i, weight)["rel_rms"]

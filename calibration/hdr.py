"""HDR merge of linear exposure brackets with noise-optimal weights.

Hasinoff, Durand & Freeman (2010), "Noise-optimal capture for high dynamic range photography";
Granados et al. (2010), "Optimal HDR reconstruction with linear digital cameras". For bracket i
with exposure t_i and signal s_i (electrons), the flux estimate is

    Φ̂ = Σ w_i s_i/t_i / Σ w_i,   w_i = t_i² / (g Φ̂ t_i + σ_read²),   Var(Φ̂) = 1 / Σ w_i,

with w_i = 0 where saturated. The weights depend on Φ̂, so we start from the longest unsaturated
exposure and iterate twice. Here signals are in electrons, so the gain g = 1. σ_read² may differ
per bracket (a dark frame's temporal variance grows with exposure through dark-current shot
noise): pass one value per bracket.
"""

from __future__ import annotations

import numpy as np

__all__ = ["merge_brackets"]


def merge_brackets(
    electrons: list[np.ndarray],
    exposures_s: list[float],
    saturated: list[np.ndarray],
    read_noise_e: float | list[float] | np.ndarray,
    iterations: int = 2,
    flux_for_weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge brackets → (flux e/s, variance (e/s)², all_saturated mask).

    ``read_noise_e``: signal-independent noise σ (electrons), a scalar or one per bracket.
    ``flux_for_weights``: an estimate of the flux that does not depend on this pixel's own
    noise (e.g. a local mean over neighbours). When given, the weights and the variance use it.
    Why: weights and a variance computed from the pixel's own noisy value are correlated with
    its noise — an upward fluctuation claims a larger variance and gets less weight — which
    biases any weighted fit by O(1/N_electrons). Invisible per pixel, that bias is several
    posterior σ once ~10⁴ samples of ~10⁴ e⁻ each are fitted together.
    """
    t = np.asarray(exposures_s, dtype=np.float64)
    s = np.stack([np.asarray(e, dtype=np.float64) for e in electrons])
    sat = np.stack([np.asarray(m, dtype=bool) for m in saturated])
    ok = ~sat
    shape = (-1,) + (1,) * (s.ndim - 1)
    tt = t.reshape(shape)
    # Initial estimate: the longest unsaturated exposure (best SNR under shot noise).
    order = np.argsort(t)[::-1]
    phi = np.full(s.shape[1:], np.nan)
    for i in order:
        fill = np.isnan(phi) & ok[i]
        phi[fill] = s[i][fill] / t[i]
    all_sat = np.isnan(phi)
    phi = np.where(all_sat, s[np.argmin(t)] / t.min(), phi)
    var_read = np.maximum(
        np.broadcast_to(np.asarray(read_noise_e, dtype=np.float64) ** 2, t.shape), 1e-12
    ).reshape(shape)
    for _ in range(iterations):
        w = np.where(ok, tt**2 / (np.maximum(phi, 0.0) * tt + var_read), 0.0)
        wsum = w.sum(axis=0)
        est = np.divide((w * s / tt).sum(axis=0), wsum, out=np.zeros_like(phi), where=wsum > 0)
        phi = np.where(all_sat, phi, est)
    if flux_for_weights is not None:
        ref = np.where(np.isfinite(flux_for_weights), flux_for_weights, phi)
        w = np.where(ok, tt**2 / (np.maximum(ref, 0.0) * tt + var_read), 0.0)
        wsum = w.sum(axis=0)
        est = np.divide((w * s / tt).sum(axis=0), wsum, out=np.zeros_like(phi), where=wsum > 0)
        phi = np.where(all_sat, phi, est)
    else:
        w = np.where(ok, tt**2 / (np.maximum(phi, 0.0) * tt + var_read), 0.0)
        wsum = w.sum(axis=0)
    var = np.divide(1.0, wsum, out=np.full_like(phi, np.inf), where=wsum > 0)
    return phi, var, all_sat

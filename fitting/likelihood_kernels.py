"""The MCMC's hot path: the Gaussian log-likelihood with a fractional discrepancy, fused.

Σ_j [ (f_j − f̂_wj)² / v_wj + ln v_wj ],  v_wj = σ_j² + (s_w f̃_wj)²  (fitting.likelihood).
One fused pass per walker instead of numpy's six (W, N) temporaries, where the ln v of every
(walker, sample) costs more than the model itself. NaN/inf propagate (the caller maps a
non-finite sum to −∞).
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from plumbing.numba_policy import dispatch, njit

__all__ = ["gauss_discrepancy_sum"]


@njit(cache=True)
def _gauss_disc_row(f, sig2, fm, s, ref):
    acc = 0.0
    for j in range(f.size):
        r = f[j] - fm[j]
        t = s * ref[j]
        v = sig2[j] + t * t
        acc += r * r / v + math.log(v)
    return acc


@njit(parallel=True, cache=True)
def _gauss_disc_par(f, sig2, fm, s, ref, out):
    shared = ref.shape[0] == 1
    for w in prange(fm.shape[0]):
        out[w] = _gauss_disc_row(f, sig2, fm[w], s[w], ref[0] if shared else ref[w])


@njit(cache=True)
def _gauss_disc_ser(f, sig2, fm, s, ref, out):
    shared = ref.shape[0] == 1
    for w in range(fm.shape[0]):
        out[w] = _gauss_disc_row(f, sig2, fm[w], s[w], ref[0] if shared else ref[w])


def gauss_discrepancy_sum(f, sig2, fm, s, ref):
    """Σ_j r²/v + ln v per walker (W,); ``fm`` (W, N), ``s`` (W,), ``ref`` (1, N) or (W, N)."""
    out = np.empty(fm.shape[0])
    dispatch("gauss_disc", _gauss_disc_par, _gauss_disc_ser, fm.size, f, sig2, fm, s, ref, out)
    return out

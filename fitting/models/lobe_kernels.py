"""Fused numba kernels of the Phong family's lobes and of Lambert's constant (the seed models
of :mod:`fitting.models.seed` besides torrance-sparrow).

Same layout as :mod:`fitting.models.microfacet_kernels`: a geometry pass once per direction
pair, then one pass over every (parameter set × pair); serial and parallel twins chosen by
:func:`plumbing.numba_policy.dispatch`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from fitting.models.kernel_math import (
    CHUNK,
    EXP_UNDERFLOW,
    INV_PI,
    NINF,
    PI,
    exp_neg_scalar,
    logaddexp,
)
from plumbing.numba_policy import dispatch, njit

__all__ = [
    "LOBE_PHONG",
    "LOBE_PHONG_NORMALIZED",
    "LOBE_BLINN_PHONG",
    "lobe_geometry",
    "lobe_parameter_table",
    "lobe",
    "constant_above",
]

LOBE_PHONG, LOBE_PHONG_NORMALIZED, LOBE_BLINN_PHONG = 0, 1, 2


@njit(cache=True)
def _lobe_row(wi, wo, kind, geo, j):
    ci = wi[j, 2]
    co = wo[j, 2]
    if not (ci > 0.0 and co > 0.0):
        geo[1, j] = NINF
        return
    geo[0, j] = 1.0
    if kind == LOBE_BLINN_PHONG:
        sx = wi[j, 0] + wo[j, 0]
        sy = wi[j, 1] + wo[j, 1]
        sz = ci + co
        base = sz / math.sqrt(sx * sx + sy * sy + sz * sz)
    else:
        dot = wi[j, 0] * wo[j, 0] + wi[j, 1] * wo[j, 1] + ci * co
        base = 2.0 * (ci * co) - dot
    base = min(base, 1.0)
    geo[1, j] = math.log(base) if base > 0.0 else NINF


@njit(parallel=True, cache=True)
def _lobe_geometry_par(wi, wo, kind):
    geo = np.zeros((2, wi.shape[0]))
    for j in prange(wi.shape[0]):
        _lobe_row(wi, wo, kind, geo, np.int64(j))
    return geo


@njit(cache=True)
def _lobe_geometry_ser(wi, wo, kind):
    geo = np.zeros((2, wi.shape[0]))
    for j in range(wi.shape[0]):
        _lobe_row(wi, wo, kind, geo, j)
    return geo


def lobe_geometry(wi, wo, kind, parallel=False):
    """Per-pair table (2, N): valid, log base, with base = l̂·r̂ = 2 cos θ_i cos θ_o − ω_i·ω_o
    (Phong; symmetric in ω_i, ω_o) or cos θ_h (Blinn-Phong), clamped to ≤ 1; log 0 = −inf."""
    if parallel:
        return _lobe_geometry_par(wi, wo, kind)
    return _lobe_geometry_ser(wi, wo, kind)


@njit(cache=True)
def _lobe_log_norm(n, kind):
    if kind == LOBE_PHONG:
        return 0.0
    if kind == LOBE_PHONG_NORMALIZED:
        return math.log((n + 2.0) / (2.0 * PI))
    # exact normal-incidence normalisation of Blinn-Phong (see fitting.models)
    return math.log((n + 2.0) * (n + 4.0) / (8.0 * PI * (math.pow(2.0, -0.5 * n) + n)))


@njit(cache=True)
def lobe_parameter_table(kd, ks, nexp, kind):
    """Rows (kd/π, log(kd/π), ks·N(n), log(ks·N(n)), n) per parameter set (1-D inputs)."""
    tab = np.empty((kd.shape[0], 5))
    for r in range(kd.shape[0]):
        lnorm = _lobe_log_norm(nexp[r], kind)
        tab[r, 0] = kd[r] * INV_PI
        tab[r, 1] = math.log(kd[r] * INV_PI) if kd[r] > 0.0 else NINF
        tab[r, 2] = ks[r] * math.exp(lnorm)
        tab[r, 3] = math.log(ks[r]) + lnorm if ks[r] > 0.0 else NINF
        tab[r, 4] = nexp[r]
    return tab


@njit(cache=True)
def _lobe_block(geo, pt, rs, cs, log_out, out, b, n_chunks):
    """One (set, chunk) of f = kd/π + ks N(n) base^n with base^n = exp(n log base) (exact for n
    up to 1e6, no overflow); parameter row r = w·rs + j·cs (per set: rs=1, cs=0)."""
    n = out.shape[1]
    w = b // n_chunks
    j0 = (b - w * n_chunks) * CHUNK
    j1 = min(j0 + CHUNK, n)
    if cs == 0 and not log_out:  # the common case, branch-free so that it vectorises
        kdpi = pt[w * rs, 0]
        ksn = pt[w * rs, 2]
        nexp = pt[w * rs, 4]
        # 1-D views from j0: contiguous loads and stores (see _stage_d)
        valid = geo[0, j0:j1]
        log_base = geo[1, j0:j1]
        row = out[w, j0:j1]
        for i in range(j1 - j0):
            x = -nexp * log_base[i]  # −n log base ≥ 0 (+inf where base = 0)
            e = exp_neg_scalar(min(x, 745.0))
            v = kdpi + ksn * (e if x < EXP_UNDERFLOW else 0.0)
            row[i] = v if valid[i] != 0.0 else 0.0
        return
    for j in range(j0, j1):
        r = w * rs + j * cs
        x = -pt[r, 4] * geo[1, j]
        e = exp_neg_scalar(min(x, 745.0))
        v = pt[r, 0] + pt[r, 2] * (e if x < EXP_UNDERFLOW else 0.0)
        if not log_out:
            out[w, j] = v if geo[0, j] != 0.0 else 0.0
        elif geo[0, j] == 0.0:
            out[w, j] = NINF
        elif v > 1e-250:
            out[w, j] = math.log(v)
        else:
            spec = pt[r, 3] - x if x < np.inf else NINF
            out[w, j] = logaddexp(pt[r, 1], spec)


@njit(parallel=True, cache=True)
def _lobe_par(geo, pt, rs, cs, log_out, out):
    n_chunks = (out.shape[1] + CHUNK - 1) // CHUNK
    for b in prange(out.shape[0] * n_chunks):
        _lobe_block(geo, pt, rs, cs, log_out, out, np.int64(b), n_chunks)


@njit(cache=True)
def _lobe_ser(geo, pt, rs, cs, log_out, out):
    n_chunks = (out.shape[1] + CHUNK - 1) // CHUNK
    for b in range(out.shape[0] * n_chunks):
        _lobe_block(geo, pt, rs, cs, log_out, out, b, n_chunks)


def lobe(geo, pt, per_sample, log_out, out):
    """f (or log f) of the Phong family for every (set, pair); ``pt`` from
    :func:`lobe_parameter_table` with W rows, or W·N rows (row w·N + j) if ``per_sample``."""
    rs, cs = (out.shape[1], 1) if per_sample else (1, 0)
    dispatch("lobe", _lobe_par, _lobe_ser, out.size, geo, pt, rs, cs, log_out, out)


# -- Lambert: a constant per set, 0 (−inf for log f) below the horizon -----------------------------
@njit(cache=True)
def _constant_row(value, cs, above, fill, out, w):
    n = out.shape[1]
    row = out[w]
    if cs == 0:  # one value per set: a select per store, vectorised
        v = value[w, 0]
        for j in range(n):
            row[j] = v if above[j] else fill
    else:
        vrow = value[w]
        for j in range(n):
            row[j] = vrow[j] if above[j] else fill


@njit(parallel=True, cache=True)
def _constant_par(value, cs, above, fill, out):
    for w in prange(out.shape[0]):
        _constant_row(value, cs, above, fill, out, np.int64(w))


@njit(cache=True)
def _constant_ser(value, cs, above, fill, out):
    for w in range(out.shape[0]):
        _constant_row(value, cs, above, fill, out, w)


def constant_above(value, above, log_out, out):
    """out[w, j] = value[w] (or value[w, j]; its log if ``log_out``) where ``above[j]``, else 0
    (−inf): Lambert's f = kd/π for every (set, pair) in one store each — a store-bound loop that
    numpy's divide-then-masked-assignment took two passes and a gather for. ``value`` is (W, 1)
    or (W, N) in out's precision (float64 or float32), already kd/π."""
    cs = 0 if value.shape[1] == 1 else 1
    if log_out:
        with np.errstate(divide="ignore"):
            value = np.log(value)  # once per value, not per (set, pair)
    fill = out.dtype.type(NINF if log_out else 0.0)  # a float64 fill would widen the select
    dispatch("constant", _constant_par, _constant_ser, out.size, value, cs, above, fill, out)

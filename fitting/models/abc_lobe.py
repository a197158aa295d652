"""The ABC lobe: a smooth-surface scattering lobe in the projected disk (issue 19).

    f(ω_i, ω_o) = kd/π + ks · F̂(ω_i·h) · (cos θ_i cos θ_o)^k · (1 + (2^(1/C) − 1)(d/w)^p)^(−C)

* d = ‖(ω_i + ω_o)_xy‖: the distance, in the projected (surface-plane) unit disk, of ω_o from
  the mirror direction of ω_i. Löw, Kronander, Ynnerman & Unger, "BRDF models for accurate and
  efficient rendering of glossy surfaces", ACM TOG 31(1):9, 2012, §4: the smooth-surface model
  S(f) = A / (1 + B f²)^C of the spatial frequency f ∝ ‖ω_r,p − ω_o,p‖, from the Rayleigh-Rice
  theory of scattering by a slightly rough surface (Church & Takacs).
* The lobe is written through its half-width w (the lobe is ks/2 at d = w):
  B = (2^(1/C) − 1)/w^p. Löw's B and C trade off along a ridge in the posterior; w and C do not.
  C sets the tail, which falls as d^(−pC). p is the option ``exponent``: 2 is Löw's form.
* F̂ = 1 + q (1 − ω_i·h)⁵: Schlick's Fresnel (CGF 13(3), 1994, eq. 24) divided by its
  normal-incidence value F₀ (q = 1/F₀ − 1). ks is then the lobe's height at normal incidence and
  q shapes only the rise towards grazing, so ks and F₀ are not degenerate as ks·F₀ would be.
* (cos θ_i cos θ_o)^k: the obliquity factor of the Rayleigh-Rice theory (k = 1) with a fitted
  exponent k ∈ [0, 2]; k = 0 is Löw's form.

Unlike a microfacet lobe, whose peak grows as 1/(cos θ_i cos θ_o) towards grazing, this lobe's
peak stays near ks and its width in θ_o grows as 1/cos θ_o: what the gold vinyl film of the
real-materials study does. On that study, ``exponent = 3`` was selected from a least-squares
fit of p to the gold film's own samples (docs/real-materials.md says so); p free in the MCMC did
not converge, which is why it is an option and not a parameter.

Properties: reciprocal (d, ω_i·h = ω_o·h and the cosine product are symmetric in ω_i, ω_o) and
isotropic; not energy conserving (nothing bounds ks; `gonio models --check` measures the
albedo).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numba import prange

from fitting.models import kernel_math as km
from fitting.models.base import Model, Parameter, above_horizon, flat_parameters
from plumbing.numba_policy import dispatch, njit  # its flags: numba's cache ignores them, see there

__all__ = ["AbcLobe", "abc_lobe", "EXPONENTS"]

#: Allowed values of the ``exponent`` option (p in d^p).
EXPONENTS = ("2", "3")

_KD = Parameter("kd", "1", 0.0, 1.0)
_KS = Parameter("ks", "sr^-1", 1e-4, 1e4, log=True)
_W = Parameter("w", "1", 1e-3, 2.0, log=True)  # half-width in the projected disk (d ≤ 2)
_C = Parameter("C", "1", 0.05, 20.0, log=True)
_Q = Parameter("q", "1", 1e-3, 1e3, log=True)  # 1/F₀ − 1: F₀ from 0.001 to 0.999
_KOBL = Parameter("k", "1", 0.0, 2.0)
_NINF = -np.inf
_NAMES = ("kd", "ks", "w", "C", "q", "k")


def abc_lobe(wi, wo, params: Mapping[str, object], p: float = 2.0) -> np.ndarray:
    """f of the module's equation, in numpy (the reference the kernel is checked against).
    ``wi``, ``wo``: (N, 3) unit vectors; ``params``: kd, ks, w, C, q, k, each a scalar or an
    array broadcastable to (N,) or (W, N)."""
    kd, ks, w, C, q, k = (np.asarray(params[n], dtype=np.float64) for n in _NAMES)
    wi, wo = np.asarray(wi, dtype=np.float64), np.asarray(wo, dtype=np.float64)
    above, d, cos_d = _pair_terms(wi, wo)
    b = np.expm1(np.log(2.0) / C)  # 2^(1/C) − 1
    lobe = np.exp(-C * np.log1p(b * (d / w) ** p))
    fres = 1.0 + q * (1.0 - cos_d) ** 5
    obl = np.clip(wi[:, 2] * wo[:, 2], 0.0, 1.0) ** k
    return np.where(above, kd / np.pi + ks * fres * obl * lobe, 0.0)


def _pair_terms(wi: np.ndarray, wo: np.ndarray):
    """(above the horizon, d = ‖(ω_i + ω_o)_xy‖, ω_i·h) per pair."""
    s = wi + wo
    norm = np.linalg.norm(s, axis=1)
    cos_d = np.clip(np.sum(wi * s, axis=1) / np.where(norm > 0, norm, 1.0), 0.0, 1.0)
    return above_horizon(wi, wo), np.hypot(s[:, 0], s[:, 1]), cos_d


def _geometry(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Per pair, once per direction set (not per parameter set): d, (1 − ω_i·h)⁵ and
    log(cos θ_i cos θ_o) (rows 0–2; 0 / 0 / −inf below the horizon, where f is 0 anyway)."""
    above, d, cos_d = _pair_terms(wi, wo)
    geo = np.empty((3, wi.shape[0]))
    geo[0] = d
    geo[1] = (1.0 - cos_d) ** 5
    with np.errstate(divide="ignore"):
        geo[2] = np.where(above, np.log(np.clip(wi[:, 2] * wo[:, 2], 0.0, 1.0)), _NINF)
    return geo


@njit(cache=True)
def _abc_block(geo, kd, ks, w, c, b2, q, k, rs, cs, p, log_out, out, blk, n_chunks):
    n = out.shape[1]
    row = blk // n_chunks
    j0 = (blk - row * n_chunks) * km.CHUNK
    for j in range(j0, min(j0 + km.CHUNK, n)):
        if geo[2, j] == _NINF:  # below the horizon
            out[row, j] = _NINF if log_out else 0.0
            continue
        r = row * rs + j * cs
        x = geo[0, j] / w[r]
        xp = x * x if p == 2.0 else x * x * x
        # lobe × obliquity in one exp: exp(−C log(1 + B'(d/w)^p) + k log(cos θ_i cos θ_o)).
        # log(1 + y), not log1p: scalar log1p cost 8 of 24 ns per value here, and for small y
        # its absolute error (≤ 1.1e-16) moves f by ≤ C·1.1e-16 relative (C ≤ 20).
        spec = math.exp(k[r] * geo[2, j] - c[r] * math.log(1.0 + b2[r] * xp))
        f = kd[r] / math.pi + ks[r] * (1.0 + q[r] * geo[1, j]) * spec
        if log_out:
            out[row, j] = math.log(f) if f > 0.0 else _NINF
        else:
            out[row, j] = f


@njit(parallel=True, cache=True)
def _abc_par(geo, kd, ks, w, c, b2, q, k, rs, cs, p, log_out, out):
    n_chunks = (out.shape[1] + km.CHUNK - 1) // km.CHUNK
    for blk in prange(out.shape[0] * n_chunks):
        _abc_block(geo, kd, ks, w, c, b2, q, k, rs, cs, p, log_out, out, np.int64(blk), n_chunks)


@njit(cache=True)
def _abc_ser(geo, kd, ks, w, c, b2, q, k, rs, cs, p, log_out, out):
    n_chunks = (out.shape[1] + km.CHUNK - 1) // km.CHUNK
    for blk in range(out.shape[0] * n_chunks):
        _abc_block(geo, kd, ks, w, c, b2, q, k, rs, cs, p, log_out, out, blk, n_chunks)


class AbcLobe(Model):
    """kd/π + the ABC lobe of the module docstring; option ``exponent`` 2 (Löw's) | 3."""

    def __init__(self, exponent: str = "2"):
        if exponent not in EXPONENTS:
            raise ValueError(f"abc: exponent={exponent!r}; choose one of {', '.join(EXPONENTS)}")
        flags = {"reciprocal": True, "energy_conserving": False, "isotropic": True}
        super().__init__("abc", (_KD, _KS, _W, _C, _Q, _KOBL), {"exponent": exponent}, flags)
        self._p = float(exponent)

    def _numpy(self, v, wi, wo, log):
        f = abc_lobe(wi, wo, v, self._p)
        if not log:
            return f
        with np.errstate(divide="ignore"):
            return np.log(f)

    def _numba(self, v, wi, wo, log, out):
        flat, per_sample = flat_parameters({n: v[n] for n in _NAMES}, out)
        rs, cs = (out.shape[1], 1) if per_sample else (1, 0)
        b2 = np.expm1(math.log(2.0) / flat["C"])  # 2^(1/C) − 1, once per parameter row
        cols = (flat["kd"], flat["ks"], flat["w"], flat["C"], b2, flat["q"], flat["k"])
        geo = _geometry(wi, wo)
        dispatch("abc", _abc_par, _abc_ser, out.size, geo, *cols, rs, cs, self._p, log, out)

"""Fused numba kernels of the microfacet models (torrance-sparrow; their stages are reused by
:mod:`fitting.models.anisotropic` and :mod:`fitting.models.multilobe`).

Layout: a first pass computes the per-sample geometry (cosines, tan²θ_h, ...) once for the N
direction pairs; a second, parallel pass over all W·N (parameter set × sample) pairs evaluates
f_r (or log f_r) in one loop body, so nothing of size W·N is materialised except the output.
The formulas are those of :mod:`fitting.models.microfacet` and :mod:`fitting.models.fresnel`
(the numpy reference path, which the tests compare against this one to 1e-12).

Parameter arrays are 2-D, shape (W, 1) (one value per set) or (W, N) (per set and sample);
``out`` is (W, N). Compiled with ``cache=True`` so only the first run on a machine pays the
compile time, and with :data:`plumbing.numba_policy.njit`: IEEE semantics, so the serial and
parallel twins agree bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from fitting.models.kernel_math import (
    CHUNK,
    ERFC_ZERO,
    EXP_UNDERFLOW,
    INV_PI,
    INV_SQRT_PI,
    NINF,
    PI,
    exp_clamp,
    exp_neg_any,
    exp_underflow,
    logaddexp,
)
from plumbing.numba_policy import dispatch, njit

__all__ = [
    "DIST_BECKMANN",
    "DIST_GGX",
    "SHADOW_VCAVITY",
    "SHADOW_SMITH",
    "SHADOW_SMITH_RATIONAL",
    "SHADOW_SMITH_CORRELATED",
    "FRESNEL_DIELECTRIC",
    "FRESNEL_CONDUCTOR",
    "FRESNEL_SCHLICK",
    "FRESNEL_NONE",
    "GEOMETRY_ROWS",
    "microfacet_geometry",
    "ts_parameter_table",
    "torrance_sparrow",
    "torrance_sparrow_per_sample",
    "smith_over_4cc",
    "fresnel_value",
    "walter_g1_fraction",
    "walter_constants",
    "stage_fresnel",
    "stage_fresnel_frac",
    "stage_distribution",
    "stage_shadowing",
    "stage_shadowing_frac",
    "divide_in_place",
]

DIST_BECKMANN, DIST_GGX = 0, 1
SHADOW_VCAVITY, SHADOW_SMITH, SHADOW_SMITH_RATIONAL, SHADOW_SMITH_CORRELATED = 0, 1, 2, 3
FRESNEL_DIELECTRIC, FRESNEL_CONDUCTOR, FRESNEL_SCHLICK, FRESNEL_NONE = 0, 1, 2, 3

# Columns of the microfacet geometry table (one row per direction pair).
_G_VALID, _G_CI, _G_CO, _G_SI, _G_SO, _G_T2, _G_VH, _G_CH, _G_GV = range(9)
_G_COLS = 9

# Columns of the per-set parameter table built by `ts_parameter_table`.
_P_KDPI, _P_LKDPI, _P_KS, _P_LKS, _P_M, _P_IM2, _P_DN, _P_LDN, _P_P1, _P_P2 = range(10)
_P_COLS = 10


@njit(cache=True)
def _geometry_row(wi, wo, geo, j):
    ci = wi[j, 2]
    co = wo[j, 2]
    if not (ci > 0.0 and co > 0.0):
        return
    sx = wi[j, 0] + wo[j, 0]
    sy = wi[j, 1] + wo[j, 1]
    sz = ci + co
    rho2 = sx * sx + sy * sy
    norm = math.sqrt(rho2 + sz * sz)
    t2 = rho2 / (sz * sz)
    # ω_i·h and ω_o·h are equal for unit vectors; averaging them keeps f exactly symmetric.
    vh = (
        0.5
        * ((wi[j, 0] * sx + wi[j, 1] * sy + ci * sz) + (wo[j, 0] * sx + wo[j, 1] * sy + co * sz))
        / norm
    )
    vh = min(max(vh, 0.0), 1.0)
    ch = sz / norm
    gv = min(0.25 / (ci * co), min(0.5 * ch / (vh * ci), 0.5 * ch / (vh * co)))
    geo[_G_VALID, j] = 1.0
    geo[_G_CI, j] = ci
    geo[_G_CO, j] = co
    geo[_G_SI, j] = math.sqrt(wi[j, 0] * wi[j, 0] + wi[j, 1] * wi[j, 1])
    geo[_G_SO, j] = math.sqrt(wo[j, 0] * wo[j, 0] + wo[j, 1] * wo[j, 1])
    geo[_G_T2, j] = t2
    geo[_G_VH, j] = vh
    geo[_G_CH, j] = ch
    geo[_G_GV, j] = gv


@njit(parallel=True, cache=True)
def _microfacet_geometry_par(wi, wo, geo):
    for j in prange(wi.shape[0]):
        _geometry_row(wi, wo, geo, np.int64(j))


@njit(cache=True)
def _microfacet_geometry_ser(wi, wo, geo):
    for j in range(wi.shape[0]):
        _geometry_row(wi, wo, geo, j)


def microfacet_geometry(wi, wo, parallel=False, dtype=np.float64):
    """Per-pair geometry table (9, N), column-major so that the stage loops read contiguously:
    valid, cos θ_i, cos θ_o, sin θ_i, sin θ_o, tan²θ_h, ω·h, cos θ_h and the V-cavity
    G/(4 cos θ_i cos θ_o).

    sin θ comes from the tangential components (accurate at the pole) and
    tan²θ_h = (s_x² + s_y²)/s_z² with s = ω_i + ω_o (no normalisation; exact at θ_h = 0).
    The V-cavity term does not depend on m, so it is computed here once per pair:
    G/(4 ci co) = min{1/(4 ci co), ch/(2 vh ci), ch/(2 vh co)}, finite as either cosine → 0.

    Computed in float64 from float64 directions and stored in ``dtype`` (np.float32 for the
    single-precision kernels: each value rounded once, no float64 table in between).
    """
    geo = np.zeros((_G_COLS, wi.shape[0]), dtype)
    (_microfacet_geometry_par if parallel else _microfacet_geometry_ser)(wi, wo, geo)
    if geo.dtype == np.float32:
        # tan²θ_h overflows float32 (to inf, then GGX's (1 + t²)/(1 + t²/m²) is inf/inf) when
        # both directions are within 1e-19 of the horizon; at 1e30 every D has its limit (GGX
        # r → m² to float32's precision, Beckmann 0), and t²/m² stays finite for m ≥ 1e-3.
        np.minimum(geo[_G_T2], np.float32(1e30), out=geo[_G_T2])
    return geo


@njit(cache=True)
def _c_lambda(c, s, m, dist):
    """cos θ · Λ(θ), exact Smith (finite at the horizon); see fitting.models.microfacet."""
    if dist == DIST_GGX:
        q = math.sqrt(c * c + m * m * s * s) + c  # (R − c)/2 = α²s²/(2(R + c))
        return 0.5 * m * m * s * s / q if q > 0.0 else 0.0
    if s == 0.0:
        return 0.0
    a = c / (m * s)
    if a > ERFC_ZERO:
        return 0.0  # a·Λ(a) < 1e-320: avoid libm's slow underflow paths
    return m * s * 0.5 * (math.exp(-a * a) * INV_SQRT_PI - a * math.erfc(a))


@njit(cache=True)
def _g1_over_cos(c, s, m, dist, rational):
    if rational and dist == DIST_BECKMANN:
        a = c / (m * s) if s > 0.0 else np.inf
        if a < 1.6:
            # G1/cos = (3.535 + 2.181 a)/(m sin θ (1 + 2.276 a + 2.577 a²))  (Walter 2007 eq. 27)
            return (3.535 + 2.181 * a) / (m * s * (1.0 + 2.276 * a + 2.577 * a * a))
        return 1.0 / c
    return 1.0 / (c + _c_lambda(c, s, m, dist))


@njit(cache=True)
def _smith_over_4cc(ci, co, si, so, m, dist, shadow):
    """Smith G₂/(4 cos θ_i cos θ_o) in a form with a finite limit as either cosine → 0."""
    if shadow == SHADOW_SMITH_CORRELATED:
        li = _c_lambda(ci, si, m, dist)
        lo = _c_lambda(co, so, m, dist)
        return 0.25 / (ci * co + (co * li + ci * lo))
    rational = shadow == SHADOW_SMITH_RATIONAL
    return 0.25 * (
        _g1_over_cos(ci, si, m, dist, rational) * _g1_over_cos(co, so, m, dist, rational)
    )


@njit(cache=True)
def _fresnel(c, fresnel, p1, p2):
    if fresnel == FRESNEL_NONE:
        return 1.0
    if fresnel == FRESNEL_SCHLICK:
        x = 1.0 - c
        x2 = x * x
        return p1 + (1.0 - p1) * (x2 * x2 * x)
    if fresnel == FRESNEL_DIELECTRIC:
        # R_s = (A/B)², R_p = (A'/B')² with one division: F = (A²B'² + A'²B²)/(2 B²B'²).
        eta2 = p1 * p1
        u2 = (eta2 - 1.0) + c * c  # exact for η = 1
        if u2 <= 0.0:
            return 1.0  # total internal reflection
        u = math.sqrt(u2)
        b = c + u
        bp = eta2 * c + u
        if b == 0.0:
            return 1.0  # c = 0 with η = 1: grazing limit, as fitting.models.fresnel
        a = (c - u) * bp
        ap = (eta2 * c - u) * b
        return 0.5 * (a * a + ap * ap) / (b * b * bp * bp)
    # Conductor η + ik in real arithmetic (K. D. Möller, *Optics*, 1988; the form Mitsuba uses),
    # algebraically equal to the complex form of fitting.models.fresnel.conductor; one division:
    # F = (r_s + r_p)/2 = (t1 − t2) t3 / ((t1 + t2)(t3 + t4)).
    c2 = c * c
    s2 = 1.0 - c2
    tmp = (p1 * p1 - p2 * p2 - 1.0) + c2
    a2pb2 = math.sqrt(tmp * tmp + 4.0 * p1 * p1 * p2 * p2)
    a = math.sqrt(max(0.5 * (a2pb2 + tmp), 0.0))
    t1 = a2pb2 + c2
    t2 = 2.0 * c * a
    t3 = a2pb2 * c2 + s2 * s2
    t4 = t2 * s2
    den = (t1 + t2) * (t3 + t4)
    if den == 0.0:
        return 1.0
    return min((t1 - t2) * t3 / den, 1.0)


@njit(cache=True)
def ts_parameter_table(kd, ks, m, p1, p2, dist):
    """Per-set derived parameters (W, 10): kd/π, log(kd/π), ks, log ks, m, 1/m², the D prefactor
    1/(π m²) and its log, p1, p2 — divisions and logs done once per set, not per sample.
    Inputs are 1-D arrays of length W. (``dist`` is accepted for symmetry; both D share the
    prefactor 1/(π m²).)"""
    w_count = kd.shape[0]
    tab = np.empty((w_count, _P_COLS))
    for w in range(w_count):
        mv = m[w]
        tab[w, _P_KDPI] = kd[w] * INV_PI
        tab[w, _P_LKDPI] = math.log(kd[w] * INV_PI) if kd[w] > 0.0 else NINF
        tab[w, _P_KS] = ks[w]
        tab[w, _P_LKS] = math.log(ks[w]) if ks[w] > 0.0 else NINF
        tab[w, _P_M] = mv
        tab[w, _P_IM2] = 1.0 / (mv * mv)
        tab[w, _P_DN] = 1.0 / (PI * mv * mv)
        tab[w, _P_LDN] = -math.log(PI * mv * mv)
        tab[w, _P_P1] = p1[w]
        tab[w, _P_P2] = p2[w]
    return tab


@njit(cache=True)
def _ts_one(geo, j, pt, w, dist, shadow, fresnel, log_out):
    """f (or log f) for pair j and parameter row w of the tables."""
    if geo[_G_VALID, j] == 0.0:
        return NINF if log_out else 0.0
    t2 = geo[_G_T2, j]
    im2 = pt[w, _P_IM2]
    mv = pt[w, _P_M]
    if shadow == SHADOW_VCAVITY:
        g = geo[_G_GV, j]
    else:
        g = _smith_over_4cc(
            geo[_G_CI, j], geo[_G_CO, j], geo[_G_SI, j], geo[_G_SO, j], mv, dist, shadow
        )
    fr = _fresnel(geo[_G_VH, j], fresnel, pt[w, _P_P1], pt[w, _P_P2])
    x = t2 * im2
    if dist == DIST_BECKMANN:
        # exp(−x) underflows to 0 beyond x ≈ 745; skip the call there (libm's underflow path is
        # ~10× slower) and the 0·∞ of cos⁻⁴θ_h = (1 + tan²θ_h)² with it.
        if x < EXP_UNDERFLOW:
            d = math.exp(-x) * (1.0 + t2) * (1.0 + t2) * pt[w, _P_DN]
        else:
            d = 0.0
    else:
        # D = m²((1 + t2)/(m² + t2))²/π = r²/(π m²) with r = (1 + t2)/(1 + t2/m²)
        r = (1.0 + t2) / (1.0 + x)
        d = r * r * pt[w, _P_DN]
    v = pt[w, _P_KDPI] + pt[w, _P_KS] * (d * g * fr)
    if not log_out:
        return v
    if v > 1e-250:
        return math.log(v)  # f has 16 good digits, so log f has them in absolute terms
    # f underflows (narrow lobe far from the peak, kd = 0): stay in log space.
    if pt[w, _P_KS] > 0.0 and fr > 0.0:
        if dist == DIST_BECKMANN:
            log_d = -x + 2.0 * math.log1p(t2) + pt[w, _P_LDN]
        else:
            log_d = 2.0 * math.log((1.0 + t2) / (1.0 + x)) + pt[w, _P_LDN]
        log_g = math.log(g)
        spec = pt[w, _P_LKS] + log_d + log_g + math.log(fr)
    else:
        spec = NINF
    return logaddexp(pt[w, _P_LKDPI], spec)


@njit(cache=True)
def _stage_d(geo, j0, dbuf, im2, dn, dist):
    """D for a chunk, branch-free so that it vectorises (the branch on dist is loop-invariant).
    In the buffers' precision (float64, or float32 for the single-precision path): every
    constant is made in it, since numba widens float32 ⊕ a Python float to float64."""
    # Rows as 1-D views from j0. Indexed by the loop's i ≥ 0 they load contiguously; with
    # geo[row, j0 + i] numba's negative-index wraparound (j0 + i < 0 → + N) kept LLVM from
    # proving the lanes consecutive, and it gathered every lane: 16 gathers per vector made the
    # float32 kernels 1.5–2× slower (the float64 ones ~5 %, being divide/sqrt-bound).
    g_t2 = geo[_G_T2, j0 : j0 + dbuf.size]
    num = dbuf.dtype.type
    one = num(1.0)
    if dist == DIST_BECKMANN:
        for i in range(dbuf.size):
            t2 = g_t2[i]
            x = t2 * im2
            e = exp_neg_any(min(x, exp_clamp(x)))
            # exp(−x) underflows to 0 beyond x ≈ 745.2: the select also avoids 0·∞ there.
            dbuf[i] = e * (one + t2) * (one + t2) * dn if x < exp_underflow(x) else num(0.0)
    else:
        for i in range(dbuf.size):
            t2 = g_t2[i]
            # GGX: D = m²((1 + t2)/(m² + t2))²/π = r²/(π m²) with r = (1 + t2)/(1 + t2/m²)
            r = (one + t2) / (one + t2 * im2)
            dbuf[i] = r * r * dn


@njit(cache=True)
def _stage_f_frac(geo, j0, fbuf, fden, p1, p2, fresnel):
    """F(ω·h) for a chunk as a fraction fbuf/fden (fden = 1 where F needs no division), so the
    caller can fold the division into one per value (divide and sqrt share one unit, the
    kernels' bottleneck); TIR and the degenerate cases by selects, not branches. Constants in
    the buffers' precision (see _stage_d)."""
    # rows as 1-D views from j0: contiguous loads (see _stage_d)
    g_vh = geo[_G_VH, j0 : j0 + fbuf.size]
    num = fbuf.dtype.type
    one, zero, half = num(1.0), num(0.0), num(0.5)
    if fresnel == FRESNEL_DIELECTRIC:
        eta2 = p1 * p1
        for i in range(fbuf.size):
            c = g_vh[i]
            u2 = (eta2 - one) + c * c  # exact for η = 1
            u = math.sqrt(max(u2, zero))
            b = c + u
            bp = eta2 * c + u
            a = (c - u) * bp
            ap = (eta2 * c - u) * b
            den = b * b * bp * bp
            ok = u2 > zero and den > zero
            fbuf[i] = half * (a * a + ap * ap) if ok else one
            fden[i] = den if ok else one
    elif fresnel == FRESNEL_CONDUCTOR:
        two = num(2.0)
        base = p1 * p1 - p2 * p2 - one
        four_e2k2 = num(4.0) * p1 * p1 * p2 * p2
        for i in range(fbuf.size):
            c = g_vh[i]
            c2 = c * c
            s2 = one - c2
            tmp = base + c2  # η² − k² − sin²θ
            a2pb2 = math.sqrt(tmp * tmp + four_e2k2)
            a = math.sqrt(max(half * (a2pb2 + tmp), zero))
            t1 = a2pb2 + c2
            t2 = two * c * a
            t3 = a2pb2 * c2 + s2 * s2
            t4 = t2 * s2
            den = (t1 + t2) * (t3 + t4)
            # min(num/den, 1) = min(num, den)/den for den > 0
            fbuf[i] = min((t1 - t2) * t3, den) if den > zero else one
            fden[i] = den if den > zero else one
    elif fresnel == FRESNEL_SCHLICK:
        for i in range(fbuf.size):
            x = one - g_vh[i]
            x2 = x * x
            fbuf[i] = p1 + (one - p1) * (x2 * x2 * x)
            fden[i] = one
    else:
        for i in range(fbuf.size):
            fbuf[i] = one
            fden[i] = one


@njit(cache=True)
def _stage_f(geo, j0, fbuf, p1, p2, fresnel):
    """F(ω·h) for a chunk (the value: for the modules that combine it with other lobes)."""
    fden = np.empty_like(fbuf)
    _stage_f_frac(geo, j0, fbuf, fden, p1, p2, fresnel)
    _divide_in_place(fbuf, fden)


@njit(cache=True)
def _divide_in_place(num, den):
    """num /= den element by element (a fraction stage's value, for callers that need it whole)."""
    for i in range(num.size):
        num[i] = num[i] / den[i]


@njit(cache=True)
def _stage_g_frac(geo, j0, gbuf, gden, m, dist, shadow):
    """G/(4 cos θ_i cos θ_o) for a chunk as a fraction gbuf/gden (gden = 1 where the form is
    computed whole). The cheap shadowing forms get branch-free loops with at most one division
    (so they vectorise), left to the caller; exact Beckmann Smith needs libm's erfc per pair.
    Constants in the buffers' precision (see _stage_d)."""
    # rows as 1-D views from j0: contiguous loads (see _stage_d)
    g_ci = geo[_G_CI, j0 : j0 + gbuf.size]
    g_co = geo[_G_CO, j0 : j0 + gbuf.size]
    g_gv = geo[_G_GV, j0 : j0 + gbuf.size]
    g_si = geo[_G_SI, j0 : j0 + gbuf.size]
    g_so = geo[_G_SO, j0 : j0 + gbuf.size]
    g_valid = geo[_G_VALID, j0 : j0 + gbuf.size]
    num = gbuf.dtype.type
    one, zero, half, quarter = num(1.0), num(0.0), num(0.5), num(0.25)
    size = gbuf.size
    for i in range(size):
        gden[i] = one
    if shadow == SHADOW_VCAVITY:
        for i in range(size):
            gbuf[i] = g_gv[i]
    elif dist == DIST_GGX and shadow != SHADOW_SMITH_CORRELATED:
        # G₁/cos = 2/(c + R), R = sqrt(c² + α² s²)  ⇒  G/(4 ci co) = 1/((ci + Ri)(co + Ro))
        m2 = m * m
        for i in range(size):
            ci = g_ci[i]
            co = g_co[i]
            si = g_si[i]
            so = g_so[i]
            ri = math.sqrt(ci * ci + m2 * si * si)
            ro = math.sqrt(co * co + m2 * so * so)
            den = (ci + ri) * (co + ro)
            gbuf[i] = one if den > zero else zero
            gden[i] = den if den > zero else one
    elif dist == DIST_GGX:
        # height-correlated: cos·Λ = (R − c)/2 = α² s²/(2(R + c)) (no cancellation)
        m2 = m * m
        for i in range(size):
            ci = g_ci[i]
            co = g_co[i]
            si = g_si[i]
            so = g_so[i]
            ri = math.sqrt(ci * ci + m2 * si * si)
            ro = math.sqrt(co * co + m2 * so * so)
            qi = ri + ci
            qo = ro + co
            li = half * m2 * si * si / qi if qi > zero else zero
            lo = half * m2 * so * so / qo if qo > zero else zero
            den = ci * co + (co * li + ci * lo)
            gbuf[i] = quarter if den > zero else zero
            gden[i] = den if den > zero else one
    elif shadow == SHADOW_SMITH_RATIONAL:
        # Walter's rational G₁ with u = m sin θ; the product of the two sides: one division.
        k = _walter_constants(num)
        for i in range(size):
            ni, di = _walter_g1_frac(g_ci[i], m * g_si[i], k)
            no, do = _walter_g1_frac(g_co[i], m * g_so[i], k)
            den = di * do
            gbuf[i] = quarter * (ni * no) if den > zero else zero
            gden[i] = den if den > zero else one
    else:
        for i in range(size):
            if g_valid[i] != zero:
                gbuf[i] = _smith_over_4cc(g_ci[i], g_co[i], g_si[i], g_so[i], m, dist, shadow)
            else:
                gbuf[i] = zero


@njit(cache=True)
def _walter_g1_frac(c, u, k):
    """Walter's rational Beckmann G₁/cos θ as a fraction (n, d), with c = cos θ, u = m sin θ
    (a = c/u): (3.535u + 2.181c)/(u² + 2.276cu + 2.577c²) for c < 1.6u, else 1/c (Walter et al.
    2007, eq. 27). ``k`` from _walter_constants, in the caller's precision; written so that the
    loops calling it stay branch-free (both forms computed, one selected)."""
    a1, a2, b1, b2, cut, one = k
    n = a1 * u + a2 * c
    d = u * u + b1 * c * u + b2 * c * c
    if not c < cut * u:
        n = one
        d = c
    return n, d


@njit(cache=True)
def _walter_constants(num):
    """Walter's rational-G₁ constants (and 1) as the number type ``num`` (float64 or float32)."""
    return num(3.535), num(2.181), num(2.276), num(2.577), num(1.6), num(1.0)


@njit(cache=True)
def _stage_g(geo, j0, gbuf, m, dist, shadow):
    """G/(4 cos θ_i cos θ_o) for a chunk (the value: for the modules that sum several lobes)."""
    gden = np.empty_like(gbuf)
    _stage_g_frac(geo, j0, gbuf, gden, m, dist, shadow)
    _divide_in_place(gbuf, gden)


@njit(cache=True)
def _ts_block(geo, pt, dist, shadow, fresnel, log_out, out, b, n_chunks):
    n = out.shape[1]
    w = b // n_chunks
    j0 = (b - w * n_chunks) * CHUNK
    size = min(CHUNK, n - j0)
    buf = np.empty((5, size), out.dtype)  # one allocation per work item, in out's precision
    dbuf = buf[0]
    gbuf = buf[1]
    fbuf = buf[2]
    gden = buf[3]
    fden = buf[4]
    _stage_d(geo, j0, dbuf, pt[w, _P_IM2], pt[w, _P_DN], dist)
    _stage_g_frac(geo, j0, gbuf, gden, pt[w, _P_M], dist, shadow)
    _stage_f_frac(geo, j0, fbuf, fden, pt[w, _P_P1], pt[w, _P_P2], fresnel)
    # G and F's divisions become one: d·(g/gden)·(f/fden) = d·g·f/(gden·fden). Both
    # denominators are products of O(1) sums (≥ cos θ or sin θ terms), far from over- or underflow.
    kdpi = pt[w, _P_KDPI]
    ks = pt[w, _P_KS]
    if not log_out:
        zero = out.dtype.type(0.0)
        valid = geo[_G_VALID, j0 : j0 + size]  # 1-D views: contiguous loads and stores
        row = out[w, j0 : j0 + size]
        for i in range(size):
            v = kdpi + ks * (dbuf[i] * gbuf[i] * fbuf[i]) / (gden[i] * fden[i])
            row[i] = v if valid[i] != zero else zero
    else:
        for i in range(size):
            j = j0 + i
            v = kdpi + ks * (dbuf[i] * gbuf[i] * fbuf[i]) / (gden[i] * fden[i])
            if geo[_G_VALID, j] == 0.0:
                out[w, j] = NINF
            elif v > 1e-250:
                out[w, j] = math.log(v)  # v has 16 good digits, log v has them absolutely
            else:  # f underflows (narrow lobe far from its peak): stay in log space
                out[w, j] = _ts_one(geo, j, pt, w, dist, shadow, fresnel, True)


@njit(parallel=True, cache=True)
def _ts_par(geo, pt, dist, shadow, fresnel, log_out, out):
    n_chunks = (out.shape[1] + CHUNK - 1) // CHUNK
    for b in prange(out.shape[0] * n_chunks):
        # prange's index is unsigned; as int64 the helper is the one the serial twin compiled
        # (every prange loop of the model kernels does this: one compile, not two)
        _ts_block(geo, pt, dist, shadow, fresnel, log_out, out, np.int64(b), n_chunks)


@njit(cache=True)
def _ts_ser(geo, pt, dist, shadow, fresnel, log_out, out):
    n_chunks = (out.shape[1] + CHUNK - 1) // CHUNK
    for b in range(out.shape[0] * n_chunks):
        _ts_block(geo, pt, dist, shadow, fresnel, log_out, out, b, n_chunks)


def torrance_sparrow(geo, pt, dist, shadow, fresnel, log_out, out):
    """f = kd/π + ks D G F/(4 cos θ_i cos θ_o) for every (set w, pair j); log f if ``log_out``.

    ``geo`` from :func:`microfacet_geometry`, ``pt`` from :func:`ts_parameter_table`, ``out``
    is (W, N). D is the π-normalised Beckmann or GGX, which makes the default (Beckmann,
    V-cavity) equal to the seed's D_seed G F/(π cos cos) identically (D_seed/π = D_norm/4).
    Work items are (set, chunk of samples); inside one, D, G and F are computed in separate
    simple loops (stages) that LLVM can vectorise, then combined.
    """
    dispatch("ts", _ts_par, _ts_ser, out.size, geo, pt, dist, shadow, fresnel, log_out, out)


@njit(parallel=True, cache=True)
def _ts_per_sample_par(geo, pt, dist, shadow, fresnel, log_out, out):
    w_count, n = out.shape
    for i in prange(w_count * n):
        w = i // n
        j = i - w * n
        out[w, j] = _ts_one(geo, j, pt, i, dist, shadow, fresnel, log_out)


@njit(cache=True)
def _ts_per_sample_ser(geo, pt, dist, shadow, fresnel, log_out, out):
    w_count, n = out.shape
    for i in range(w_count * n):
        w = i // n
        j = i - w * n
        out[w, j] = _ts_one(geo, j, pt, i, dist, shadow, fresnel, log_out)


def torrance_sparrow_per_sample(geo, pt, dist, shadow, fresnel, log_out, out):
    """As :func:`torrance_sparrow` but with a parameter table of W·N rows (row w·N + j), for
    parameters that vary per sample as well as per set (scalar loop, no staging)."""
    dispatch(
        "ts_per_sample",
        _ts_per_sample_par,
        _ts_per_sample_ser,
        out.size,
        geo,
        pt,
        dist,
        shadow,
        fresnel,
        log_out,
        out,
    )


# -- public handles of the scalar building blocks (numba functions, callable from other njit
# code): the other model modules reuse them rather than copying the formulas.
#: Smith G₂/(4 cos θ_i cos θ_o) from (cos θ, m·sin θ) pairs: pass m = 1 and the *projected*
#: u = sqrt((α_x x)² + (α_y y)²) of each direction for an anisotropic distribution (Heitz 2014
#: §5.3: Λ depends on the roughness projected on the direction's azimuth).
smith_over_4cc = _smith_over_4cc
fresnel_value = _fresnel
#: Walter's rational G₁/cos θ as a fraction (n, d) of (cos θ, u, walter_constants(num)).
walter_g1_fraction = _walter_g1_frac
walter_constants = _walter_constants
#: The Fresnel stage F(ω·h) for a chunk, reading ω·h from row 6 of a geometry table laid out as
#: :func:`microfacet_geometry` (rows 0–8).
stage_fresnel = _stage_f
#: The same as a fraction (value, denominator), for a caller that divides once per value.
stage_fresnel_frac = _stage_f_frac
#: The D and G/(4 cos θ_i cos θ_o) stages of torrance-sparrow for a chunk (same table layout).
stage_distribution = _stage_d
stage_shadowing = _stage_g
#: The shadowing stage as a fraction (value, denominator), as stage_fresnel_frac.
stage_shadowing_frac = _stage_g_frac
divide_in_place = _divide_in_place
#: Rows of the geometry table of :func:`microfacet_geometry`.
GEOMETRY_ROWS = _G_COLS

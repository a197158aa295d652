"""Fused numba kernels for the BRDF models (the fast path of :mod:`fitting.models`).

Layout: a first pass computes the per-sample geometry (cosines, tan²θ_h, ...) once for the N
direction pairs; a second, parallel pass over all W·N (parameter set × sample) pairs evaluates
f_r (or log f_r) in one loop body, so nothing of size W·N is materialised except the output.
The formulas are those of :mod:`fitting.microfacet` and :mod:`fitting.fresnel` (the numpy
reference path, which the tests compare against this one to 1e-12).

Parameter arrays are 2-D, shape (W, 1) (one value per set) or (W, N) (per set and sample);
``out`` is (W, N). Compiled with ``cache=True`` so only the first run on a machine pays the
compile time. Every kernel here and in the other model modules is compiled by this module's
:func:`njit`: IEEE semantics (no fast-math; see the note above ``njit``), so the serial and
parallel twins agree bit for bit.
"""

from __future__ import annotations

import functools
import math
import os
import time

import numba
import numpy as np
from llvmlite import ir as llvm_ir
from numba import prange, types
from numba.extending import intrinsic, overload

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
    "LOBE_PHONG",
    "LOBE_PHONG_NORMALIZED",
    "LOBE_BLINN_PHONG",
    "PARALLEL_MIN_WORK",
    "set_threading",
    "exp_neg",
    "microfacet_geometry",
    "ts_parameter_table",
    "torrance_sparrow",
    "torrance_sparrow_per_sample",
    "lobe_geometry",
    "lobe_parameter_table",
    "lobe",
    "gauss_discrepancy_sum",
    "dispatch",
    "prefers_threads",
    "logaddexp",
    "smith_over_4cc",
    "fresnel_value",
    "walter_g1_fraction",
    "walter_constants",
    "exp_neg_scalar",
    "stage_fresnel",
    "stage_fresnel_frac",
    "stage_distribution",
    "stage_shadowing",
    "CHUNK",
    "njit",
    "constant_above",
]


def _prefer_512_bit_vectors() -> None:
    """On an AVX-512 CPU let LLVM vectorise with 512-bit registers (8 float64 lanes, not 4).

    LLVM's tuning for Intel's AVX-512 cores says "prefer 256-bit" (older parts dropped their clock
    on 512-bit code); numba inherits it. On this project's machine type the wide vectors measured
    15–20 % faster for the seed torrance-sparrow, the conductor forms and phong, and within noise
    for GGX (docs/performance.md, "Kernels"). Done through numba's own NUMBA_CPU_FEATURES (the
    host's features plus "-prefer-256-bit"), before anything here is compiled; left alone when the
    user has chosen the features, and a no-op without AVX-512. numba keys its cache by the features,
    so a machine switching this on recompiles once."""
    if os.environ.get("NUMBA_CPU_FEATURES") or numba.config.CPU_FEATURES is not None:
        return
    import llvmlite.binding as llvm

    features = llvm.get_host_cpu_features()
    if not features.get("avx512f", False):
        return
    os.environ["NUMBA_CPU_FEATURES"] = features.flatten() + ",-prefer-256-bit"
    numba.core.config.reload_config()


_prefer_512_bit_vectors()

# No fast-math flag at all. "contract" (fused multiply-adds) measured 14–28 % faster, but LLVM
# fuses differently in the serial and the parallel twin of a kernel (each is compiled on its own),
# so their results differed in the last bit (a fresh-clone run of
# tests/test_models.py::test_large_problem_uses_parallel_kernels_identically) and the "auto"
# threading policy would make a seeded fit depend on the machine's load. Without it both twins
# round every operation as IEEE says, whatever the vector width, so they agree bit for bit.
# Flags that assume finite values (nnan, ninf) would also break the inf/NaN guards below.
# error_model="numpy": a float division by zero gives ±inf/NaN as IEEE says instead of numba's
# default Python-style check, whose raise path keeps LLVM from vectorising any loop that divides
# (the kernels guard their divisions themselves).
# nogil: a kernel releases the GIL while it runs, so a thread beside it (the calibration's frame
# decoder, calibration.reduce) keeps working: held, a 24 MP RAW's decode took 24× its time.
# numba's on-disk cache is keyed by a kernel's source, not by these options: after changing them,
# edit every module that imports this njit (or clear its __pycache__), or their old builds load
# with the new flags reported (a fresh checkout has no cache; tests/test_kernels_release_the_gil.py
# checks the flags only: a timing check would flake on a loaded machine).
njit = functools.partial(numba.njit, fastmath=False, error_model="numpy", nogil=True)

DIST_BECKMANN, DIST_GGX = 0, 1
SHADOW_VCAVITY, SHADOW_SMITH, SHADOW_SMITH_RATIONAL, SHADOW_SMITH_CORRELATED = 0, 1, 2, 3
FRESNEL_DIELECTRIC, FRESNEL_CONDUCTOR, FRESNEL_SCHLICK, FRESNEL_NONE = 0, 1, 2, 3
LOBE_PHONG, LOBE_PHONG_NORMALIZED, LOBE_BLINN_PHONG = 0, 1, 2

_PI = math.pi
_INV_PI = 1.0 / math.pi
_LOG_PI = math.log(math.pi)
_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)
_NINF = -np.inf
_EXP_UNDERFLOW = 745.2  # exp(−x) == 0.0 in float64 for x above this
_ERFC_ZERO = 27.3  # erfc(a) and exp(−a²) are 0.0 (or denormal and negligible) above this

# Columns of the microfacet geometry table (one row per direction pair).
_G_VALID, _G_CI, _G_CO, _G_SI, _G_SO, _G_T2, _G_VH, _G_CH, _G_GV = range(9)
_G_COLS = 9

# Columns of the per-set parameter table built by `ts_parameter_table`.
_P_KDPI, _P_LKDPI, _P_KS, _P_LKS, _P_M, _P_IM2, _P_DN, _P_LDN, _P_P1, _P_P2 = range(10)
_P_COLS = 10

# Below this many (set × sample) evaluations the serial kernels are always used.
PARALLEL_MIN_WORK = 65536

_POLICIES = ("auto", "parallel", "serial")
_policy = ["auto"]


def set_threading(policy: str) -> str:
    """Choose how the kernels use numba's threads; returns the previous policy.

    "parallel": the prange kernels whenever the work is ≥ PARALLEL_MIN_WORK; "serial": never;
    "auto" (default): time both twins as they are used and keep the faster one per kernel,
    re-trying the other every 64 calls. Why: with free cores the parallel kernels are ~2×
    faster, but when the cores are oversubscribed (other processes busy) every parallel
    launch waits for a scheduler time slice — measured 5–40× slower than serial. Results are
    bitwise identical either way (tested), only the speed differs.
    """
    if policy not in _POLICIES:
        raise ValueError(f"threading policy {policy!r}; choose one of {', '.join(_POLICIES)}")
    previous = _policy[0]
    _policy[0] = policy
    return previous


class _Chooser:
    """Per-kernel running timings (ns per unit of work) of the parallel and serial twins."""

    def __init__(self):
        self.ns = {True: [], False: []}
        self.calls = 0

    def pick(self) -> bool:
        self.calls += 1
        for par in (True, False):
            if len(self.ns[par]) < 2:
                return par
        best = min(self.ns, key=lambda p: min(self.ns[p]))
        return (not best) if self.calls % 64 == 0 else best

    def record(self, par: bool, seconds: float, work: int) -> None:
        hist = self.ns[par]
        hist.append(seconds * 1e9 / work)
        del hist[:-4]  # recent timings only: the machine's load changes


_choosers: dict[str, _Chooser] = {}


def _dispatch(name, par_fn, ser_fn, work, *args):
    """Run the parallel or the serial twin of a kernel according to the threading policy."""
    policy = _policy[0]
    if work < PARALLEL_MIN_WORK or numba.get_num_threads() < 2 or policy == "serial":
        return ser_fn(*args)
    if policy == "parallel":
        return par_fn(*args)
    chooser = _choosers.setdefault(name, _Chooser())
    par = chooser.pick()
    t0 = time.perf_counter()
    result = (par_fn if par else ser_fn)(*args)
    chooser.record(par, time.perf_counter() - t0, work)
    return result


def dispatch(name, par_fn, ser_fn, work, *args):
    """Public handle of the threading dispatcher, for the kernels of the other model modules
    (:mod:`fitting.anisotropic`, :mod:`fitting.oren_nayar`, :mod:`fitting.multilobe`)."""
    return _dispatch(name, par_fn, ser_fn, work, *args)


def prefers_threads(name: str, work: int) -> bool:
    """Whether a geometry pass should use threads (follows kernel ``name``'s timings)."""
    return _prefers_threads(name, work)


def _prefers_threads(name: str, work: int) -> bool:
    """Whether the geometry pass of a call should use threads (follows the kernel's choice)."""
    policy = _policy[0]
    if work < PARALLEL_MIN_WORK or numba.get_num_threads() < 2 or policy == "serial":
        return False
    if policy == "parallel":
        return True
    c = _choosers.get(name)
    if c is None or any(len(v) < 2 for v in c.ns.values()):
        return False
    return min(c.ns[True]) < min(c.ns[False])


# Samples per parallel work item: long enough to amortise the scheduling, short enough to
# balance two cores for W = 1.
_CHUNK = 1024
CHUNK = _CHUNK


# exp(−x) for x ∈ [0, 745.2): Cody-Waite reduction x = k ln2 − r, |r| ≤ ln2/2, a degree-13
# Taylor polynomial for e^r (truncation < 4e-18 relative) and 2^−k from a table. Written with
# plain arithmetic, floor and a table gather so that LLVM vectorises the loops that use it
# (libm's exp is an opaque call that keeps them scalar). Accuracy ≈ 2 ulp; tested against
# numpy's exp in tests/test_models.py.
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e00
_POW2_NEG = np.ldexp(1.0, -np.arange(1090)).astype(np.float64)  # 2^−k, 0 beyond k = 1074
_EXP_C = tuple(1.0 / math.factorial(i) for i in range(14))


@njit(cache=True)
def _exp_neg(x):
    k = math.floor(x * _INV_LN2 + 0.5)
    r = (k * _LN2_HI - x) + k * _LN2_LO
    p = _EXP_C[13]
    p = p * r + _EXP_C[12]
    p = p * r + _EXP_C[11]
    p = p * r + _EXP_C[10]
    p = p * r + _EXP_C[9]
    p = p * r + _EXP_C[8]
    p = p * r + _EXP_C[7]
    p = p * r + _EXP_C[6]
    p = p * r + _EXP_C[5]
    p = p * r + _EXP_C[4]
    p = p * r + _EXP_C[3]
    p = p * r + _EXP_C[2]
    p = p * r + _EXP_C[1]
    p = p * r + _EXP_C[0]
    return p * _POW2_NEG[int(k)]


# The float32 twin for the single-precision kernels (MCMC's likelihood, `Model.evaluate(...,
# precision="float32")`): the same reduction with Cody-Waite constants split for float32
# (ln2_hi has 15 significant bits, so k·ln2_hi is exact for k < 2⁹; k ≤ 124 here) and a
# degree-7 Taylor polynomial (truncation |r|⁸/8! ≤ 5e-9 relative for |r| ≤ ln2/2, below
# float32's 6e-8). 2^−k is made from its exponent bits, not gathered from a table: a 16-lane
# gather measured 7× slower than the whole rest of the function. Every constant is a
# np.float32: numba widens float32 ⊕ a Python float (or an int) to float64, which would make the
# loops float64 again.
# Denormals are avoided in the exp (the products after it can still meet one, rarely), not only
# for accuracy: an operation with a denormal operand or result takes a microcode assist on x86
# (~100 cycles for the whole vector), and a Beckmann lobe's tail made the float32 kernel 2.5×
# slower than the float64 one. So exp(−x) is taken as 0 from x = 86 (e^−86 = 4.4e-38, just
# above float32's smallest normal 1.2e-38; k ≤ 124 there, so p·2^−k stays normal): an absolute
# change below 4.4e-38, where the float64 kernel's cut is at 745.2 (its denormals start at 708).
_F32 = np.float32
_LN2_HI_32 = _F32(0.693145751953125)
_LN2_LO_32 = _F32(1.428606765330187045e-06)
_INV_LN2_32 = _F32(1.44269504088896338700)
_EXP_C_32 = tuple(_F32(1.0 / math.factorial(i)) for i in range(8))
_HALF_32 = _F32(0.5)
_EXP_CLAMP_32 = _F32(86.0)
_EXP_UNDERFLOW_32 = _F32(86.0)


@intrinsic
def _float32_from_bits(typingctx, bits):
    """The float32 whose IEEE bit pattern is the int32 ``bits`` (an LLVM bitcast)."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], llvm_ir.FloatType())

    return types.float32(types.int32), codegen


@njit(cache=True)
def _exp_neg32(x):
    # x ≥ 0, so truncation is the floor; k stays a float32 (math.floor gives an int, and an int
    # times a float32 is a float64 in numba).
    ki = np.int32(x * _INV_LN2_32 + _HALF_32)
    k = _F32(ki)
    r = (k * _LN2_HI_32 - x) + k * _LN2_LO_32
    p = _EXP_C_32[7]
    p = p * r + _EXP_C_32[6]
    p = p * r + _EXP_C_32[5]
    p = p * r + _EXP_C_32[4]
    p = p * r + _EXP_C_32[3]
    p = p * r + _EXP_C_32[2]
    p = p * r + _EXP_C_32[1]
    p = p * r + _EXP_C_32[0]
    return p * _float32_from_bits((np.int32(127) - ki) << np.int32(23))  # 2^−k, 0 ≤ k ≤ 126


def exp_neg_any(x):  # pragma: no cover - numba code only (the overload below)
    """exp(−x) in x's precision: the float64 or the float32 polynomial above."""
    raise NotImplementedError


def exp_clamp(x):  # pragma: no cover - numba code only
    """The largest argument the kernels pass to exp_neg_any in x's precision (745.0 or 86.0)."""
    raise NotImplementedError


def exp_underflow(x):  # pragma: no cover - numba code only
    """The x from which the kernels take exp(−x) as 0 in x's precision (745.2 or 86.0)."""
    raise NotImplementedError


_OVERLOAD_OPTIONS = {"nogil": True, "error_model": "numpy"}


@overload(exp_neg_any, jit_options=_OVERLOAD_OPTIONS)
def _exp_neg_any_impl(x):
    return (lambda x: _exp_neg32(x)) if x == types.float32 else (lambda x: _exp_neg(x))


@overload(exp_clamp, jit_options=_OVERLOAD_OPTIONS)
def _exp_clamp_impl(x):
    return (lambda x: _EXP_CLAMP_32) if x == types.float32 else (lambda x: 745.0)


@overload(exp_underflow, jit_options=_OVERLOAD_OPTIONS)
def _exp_underflow_impl(x):
    return (lambda x: _EXP_UNDERFLOW_32) if x == types.float32 else (lambda x: _EXP_UNDERFLOW)


@njit(cache=True)
def exp_neg(x):
    """exp(−x) for an array x ≥ 0 by the vectorisable kernel formula, in x's precision, as the
    kernels take it: 0 from x = 745.2 (float64) or 86 (float32; see _exp_neg32)."""
    out = np.empty_like(x)
    zero = out.dtype.type(0.0)
    for i in range(x.size):
        v = x.flat[i]
        e = exp_neg_any(min(v, exp_clamp(v)))
        out.flat[i] = e if v < exp_underflow(v) else zero
    return out


@njit(cache=True)
def _logaddexp(a, b):
    if a == _NINF:
        return b
    if b == _NINF:
        return a
    if a > b:
        return a + math.log1p(math.exp(b - a))
    return b + math.log1p(math.exp(a - b))


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
        _geometry_row(wi, wo, geo, j)


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
    """cos θ · Λ(θ), exact Smith (finite at the horizon); see fitting.microfacet._c_lambda."""
    if dist == DIST_GGX:
        q = math.sqrt(c * c + m * m * s * s) + c  # (R − c)/2 = α²s²/(2(R + c))
        return 0.5 * m * m * s * s / q if q > 0.0 else 0.0
    if s == 0.0:
        return 0.0
    a = c / (m * s)
    if a > _ERFC_ZERO:
        return 0.0  # a·Λ(a) < 1e-320: avoid libm's slow underflow paths
    return m * s * 0.5 * (math.exp(-a * a) * _INV_SQRT_PI - a * math.erfc(a))


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
            return 1.0  # c = 0 with η = 1: grazing limit, as fitting.fresnel
        a = (c - u) * bp
        ap = (eta2 * c - u) * b
        return 0.5 * (a * a + ap * ap) / (b * b * bp * bp)
    # Conductor η + ik in real arithmetic (K. D. Möller, *Optics*, 1988; the form Mitsuba uses),
    # algebraically equal to the complex form of fitting.fresnel.conductor; one division:
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
        tab[w, _P_KDPI] = kd[w] * _INV_PI
        tab[w, _P_LKDPI] = math.log(kd[w] * _INV_PI) if kd[w] > 0.0 else _NINF
        tab[w, _P_KS] = ks[w]
        tab[w, _P_LKS] = math.log(ks[w]) if ks[w] > 0.0 else _NINF
        tab[w, _P_M] = mv
        tab[w, _P_IM2] = 1.0 / (mv * mv)
        tab[w, _P_DN] = 1.0 / (_PI * mv * mv)
        tab[w, _P_LDN] = -math.log(_PI * mv * mv)
        tab[w, _P_P1] = p1[w]
        tab[w, _P_P2] = p2[w]
    return tab


@njit(cache=True)
def _ts_one(geo, j, pt, w, dist, shadow, fresnel, log_out):
    """f (or log f) for pair j and parameter row w of the tables."""
    if geo[_G_VALID, j] == 0.0:
        return _NINF if log_out else 0.0
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
        if x < _EXP_UNDERFLOW:
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
        spec = _NINF
    return _logaddexp(pt[w, _P_LKDPI], spec)


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
    j0 = (b - w * n_chunks) * _CHUNK
    size = min(_CHUNK, n - j0)
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
                out[w, j] = _NINF
            elif v > 1e-250:
                out[w, j] = math.log(v)  # v has 16 good digits, log v has them absolutely
            else:  # f underflows (narrow lobe far from its peak): stay in log space
                out[w, j] = _ts_one(geo, j, pt, w, dist, shadow, fresnel, True)


@njit(parallel=True, cache=True)
def _ts_par(geo, pt, dist, shadow, fresnel, log_out, out):
    n_chunks = (out.shape[1] + _CHUNK - 1) // _CHUNK
    for b in prange(out.shape[0] * n_chunks):
        _ts_block(geo, pt, dist, shadow, fresnel, log_out, out, b, n_chunks)


@njit(cache=True)
def _ts_ser(geo, pt, dist, shadow, fresnel, log_out, out):
    n_chunks = (out.shape[1] + _CHUNK - 1) // _CHUNK
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
    _dispatch("ts", _ts_par, _ts_ser, out.size, geo, pt, dist, shadow, fresnel, log_out, out)


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
    _dispatch(
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


@njit(cache=True)
def _lobe_row(wi, wo, kind, geo, j):
    ci = wi[j, 2]
    co = wo[j, 2]
    if not (ci > 0.0 and co > 0.0):
        geo[1, j] = _NINF
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
    geo[1, j] = math.log(base) if base > 0.0 else _NINF


@njit(parallel=True, cache=True)
def _lobe_geometry_par(wi, wo, kind):
    geo = np.zeros((2, wi.shape[0]))
    for j in prange(wi.shape[0]):
        _lobe_row(wi, wo, kind, geo, j)
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
        return math.log((n + 2.0) / (2.0 * _PI))
    # exact normal-incidence normalisation of Blinn-Phong (see fitting.models)
    return math.log((n + 2.0) * (n + 4.0) / (8.0 * _PI * (math.pow(2.0, -0.5 * n) + n)))


@njit(cache=True)
def lobe_parameter_table(kd, ks, nexp, kind):
    """Rows (kd/π, log(kd/π), ks·N(n), log(ks·N(n)), n) per parameter set (1-D inputs)."""
    tab = np.empty((kd.shape[0], 5))
    for r in range(kd.shape[0]):
        lnorm = _lobe_log_norm(nexp[r], kind)
        tab[r, 0] = kd[r] * _INV_PI
        tab[r, 1] = math.log(kd[r] * _INV_PI) if kd[r] > 0.0 else _NINF
        tab[r, 2] = ks[r] * math.exp(lnorm)
        tab[r, 3] = math.log(ks[r]) + lnorm if ks[r] > 0.0 else _NINF
        tab[r, 4] = nexp[r]
    return tab


@njit(cache=True)
def _lobe_block(geo, pt, rs, cs, log_out, out, b, n_chunks):
    """One (set, chunk) of f = kd/π + ks N(n) base^n with base^n = exp(n log base) (exact for n
    up to 1e6, no overflow); parameter row r = w·rs + j·cs (per set: rs=1, cs=0)."""
    n = out.shape[1]
    w = b // n_chunks
    j0 = (b - w * n_chunks) * _CHUNK
    j1 = min(j0 + _CHUNK, n)
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
            e = _exp_neg(min(x, 745.0))
            v = kdpi + ksn * (e if x < _EXP_UNDERFLOW else 0.0)
            row[i] = v if valid[i] != 0.0 else 0.0
        return
    for j in range(j0, j1):
        r = w * rs + j * cs
        x = -pt[r, 4] * geo[1, j]
        e = _exp_neg(min(x, 745.0))
        v = pt[r, 0] + pt[r, 2] * (e if x < _EXP_UNDERFLOW else 0.0)
        if not log_out:
            out[w, j] = v if geo[0, j] != 0.0 else 0.0
        elif geo[0, j] == 0.0:
            out[w, j] = _NINF
        elif v > 1e-250:
            out[w, j] = math.log(v)
        else:
            spec = pt[r, 3] - x if x < np.inf else _NINF
            out[w, j] = _logaddexp(pt[r, 1], spec)


@njit(parallel=True, cache=True)
def _lobe_par(geo, pt, rs, cs, log_out, out):
    n_chunks = (out.shape[1] + _CHUNK - 1) // _CHUNK
    for b in prange(out.shape[0] * n_chunks):
        _lobe_block(geo, pt, rs, cs, log_out, out, b, n_chunks)


@njit(cache=True)
def _lobe_ser(geo, pt, rs, cs, log_out, out):
    n_chunks = (out.shape[1] + _CHUNK - 1) // _CHUNK
    for b in range(out.shape[0] * n_chunks):
        _lobe_block(geo, pt, rs, cs, log_out, out, b, n_chunks)


def lobe(geo, pt, per_sample, log_out, out):
    """f (or log f) of the Phong family for every (set, pair); ``pt`` from
    :func:`lobe_parameter_table` with W rows, or W·N rows (row w·N + j) if ``per_sample``."""
    rs, cs = (out.shape[1], 1) if per_sample else (1, 0)
    _dispatch("lobe", _lobe_par, _lobe_ser, out.size, geo, pt, rs, cs, log_out, out)


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
        _constant_row(value, cs, above, fill, out, w)


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
    fill = out.dtype.type(_NINF if log_out else 0.0)  # a float64 fill would widen the select
    _dispatch("constant", _constant_par, _constant_ser, out.size, value, cs, above, fill, out)


# -- Gaussian log-likelihood with a fractional discrepancy ----------------------------------------
# Σ_j [ (f_j − f̂_wj)² / v_wj + ln v_wj ],  v_wj = σ_j² + (s_w f̃_wj)²  (fitting.likelihood).
# One fused pass per walker instead of numpy's six (W, N) temporaries: the MCMC hot path, where
# the ln v of every (walker, sample) costs more than the model itself. NaN/inf propagate (the
# caller maps a non-finite sum to −∞).
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
    _dispatch("gauss_disc", _gauss_disc_par, _gauss_disc_ser, fm.size, f, sig2, fm, s, ref, out)
    return out


# -- public handles of the scalar building blocks (numba functions, callable from other njit
# code): the other model modules reuse them rather than copying the formulas.
logaddexp = _logaddexp
#: Smith G₂/(4 cos θ_i cos θ_o) from (cos θ, m·sin θ) pairs: pass m = 1 and the *projected*
#: u = sqrt((α_x x)² + (α_y y)²) of each direction for an anisotropic distribution (Heitz 2014
#: §5.3: Λ depends on the roughness projected on the direction's azimuth).
smith_over_4cc = _smith_over_4cc
fresnel_value = _fresnel
#: Walter's rational G₁/cos θ as a fraction (n, d) of (cos θ, u, walter_constants(num)).
walter_g1_fraction = _walter_g1_frac
walter_constants = _walter_constants
exp_neg_scalar = _exp_neg
#: The Fresnel stage F(ω·h) for a chunk, reading ω·h from row 6 of a geometry table laid out as
#: :func:`microfacet_geometry` (rows 0–8).
stage_fresnel = _stage_f
#: The same as a fraction (value, denominator), for a caller that divides once per value.
stage_fresnel_frac = _stage_f_frac
#: The D and G/(4 cos θ_i cos θ_o) stages of torrance-sparrow for a chunk (same table layout).
stage_distribution = _stage_d
stage_shadowing = _stage_g

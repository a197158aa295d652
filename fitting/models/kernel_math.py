"""Arithmetic shared by the model kernels: constants, exp(−x) written so that LLVM vectorises
it (float64 and float32), log-add-exp, and the work item size of the parallel loops.

Every function here is compiled with :data:`plumbing.numba_policy.njit` (IEEE semantics; see
there), so serial and parallel kernels that use them agree bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir as llvm_ir
from numba import types
from numba.extending import intrinsic, overload

from plumbing.numba_policy import njit

__all__ = [
    "PI",
    "INV_PI",
    "LOG_PI",
    "INV_SQRT_PI",
    "NINF",
    "EXP_UNDERFLOW",
    "ERFC_ZERO",
    "CHUNK",
    "exp_neg",
    "exp_neg_scalar",
    "exp_neg_any",
    "exp_clamp",
    "exp_underflow",
    "logaddexp",
]

PI = math.pi
INV_PI = 1.0 / math.pi
LOG_PI = math.log(math.pi)
INV_SQRT_PI = 1.0 / math.sqrt(math.pi)
NINF = -np.inf
EXP_UNDERFLOW = 745.2  # exp(−x) == 0.0 in float64 for x above this
ERFC_ZERO = 27.3  # erfc(a) and exp(−a²) are 0.0 (or denormal and negligible) above this

# Samples per parallel work item: long enough to amortise the scheduling, short enough to
# balance two cores for W = 1.
CHUNK = 1024


# exp(−x) for x ∈ [0, 745.2): Cody-Waite reduction x = k ln2 − r, |r| ≤ ln2/2, a degree-13
# Taylor polynomial for e^r (truncation < 4e-18 relative) and 2^−k from a table. Written with
# plain arithmetic, floor and a table gather so that LLVM vectorises the loops that use it
# (libm's exp is an opaque call that keeps them scalar). Accuracy ≈ 2 ulp; tested against
# numpy's exp in tests/fitting/models/test_models.py.
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e00
_POW2_NEG = np.ldexp(1.0, -np.arange(1090)).astype(np.float64)  # 2^−k, 0 beyond k = 1074
_EXP_C = tuple(1.0 / math.factorial(i) for i in range(14))


@njit(cache=True)
def exp_neg_scalar(x):
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
    return (lambda x: _exp_neg32(x)) if x == types.float32 else (lambda x: exp_neg_scalar(x))


@overload(exp_clamp, jit_options=_OVERLOAD_OPTIONS)
def _exp_clamp_impl(x):
    return (lambda x: _EXP_CLAMP_32) if x == types.float32 else (lambda x: 745.0)


@overload(exp_underflow, jit_options=_OVERLOAD_OPTIONS)
def _exp_underflow_impl(x):
    return (lambda x: _EXP_UNDERFLOW_32) if x == types.float32 else (lambda x: EXP_UNDERFLOW)


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
def logaddexp(a, b):
    if a == NINF:
        return b
    if b == NINF:
        return a
    if a > b:
        return a + math.log1p(math.exp(b - a))
    return b + math.log1p(math.exp(a - b))

"""Multi-lobe microfacet models: a sharp lobe plus a broad one, and heavy-tailed lobes.

two-lobe
    f = kd/π + F(ω·h) [ks D₁(m) G₁ + ks2 D₂(m₂) G₂] / (4 cos θ_i cos θ_o),  m₂ = m · m_ratio,
    e.g. a sharp clear coat over a broad sheen (the two-lobe fits of Ngan, Durand & Matusik,
    EGSR 2005, §5). Each D is the π-normalised Beckmann, GGX or Student-t distribution
    (options ``distribution`` for the sharp lobe and ``distribution2`` for the broad one), each G
    the Smith term of its own distribution (or the V-cavity), F is shared (one interface).
heavy-tail (variant: one lobe, ``lobes = "1"``, Student-t D)
    f = kd/π + ks D G F/(4 cos θ_i cos θ_o) with the Student-t ("STD") distribution of slopes,
    D = 1/(π m² cos⁴θ_h (1 + tan²θ_h/((γ−1) m²))^γ)  (Ribardière, Bringier, Meneveaux,
    Simonot, "STD: Student's t-distribution of slopes for microfacet based BSDFs", CGF 36(2),
    2017, eq. 6): γ = 2 is GGX, γ → ∞ Beckmann, and the tail falls as tan^(−2γ)θ_h. Its Smith
    Λ is computed exactly (:func:`fitting.models.microfacet.smith_lambda_student_t`; the paper fits
    a rational approximation).

Identifiability (why the parameterisation is what it is):
* ordered lobes: the broad lobe's roughness is m·m_ratio with m_ratio ≥ 2, so the two lobes
  cannot swap labels (no label-switching modes in the posterior);
* the prior keeps them apart: m_ratio's box starts at 2 (a lobe ≥ 2× rougher), so a single
  lobe cannot be split into two nearly equal ones;
* :func:`check_lobes` reads a fit's posterior and reports when the second lobe is not
  distinguishable (its weight consistent with zero, its ratio piled at the bound, or the two
  weights traded against each other).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numba import prange
from scipy.special import gammaln

from fitting.models import fresnel as _fresnel
from fitting.models import kernel_math as km
from fitting.models import microfacet as _mf
from fitting.models import microfacet_kernels as mk
from fitting.models.base import (
    FRESNEL_CODES,
    FRESNEL_PARAMETERS,
    KD,
    Model,
    Parameter,
    above_horizon,
    combine,
    flat_parameters,
    parallel_geometry,
)
from plumbing.numba_policy import dispatch, njit  # its flags: numba's cache ignores them, see there

__all__ = [
    "DISTRIBUTIONS",
    "SHADOWING",
    "M_RATIO",
    "GAMMA",
    "TwoLobe",
    "LobeCheck",
    "check_lobes",
    "betainc",
]

DISTRIBUTIONS = {"beckmann": mk.DIST_BECKMANN, "ggx": mk.DIST_GGX, "student-t": 2}
SHADOWING = {
    "smith": mk.SHADOW_SMITH,
    "smith-correlated": mk.SHADOW_SMITH_CORRELATED,
    "v-cavity": mk.SHADOW_VCAVITY,
}
_DIST_STD = 2
#: Broad-lobe roughness over the sharp one's; the lower bound 2 orders the lobes and keeps
#: them apart (module docstring).
M_RATIO = Parameter("m_ratio", "1", 2.0, 1000.0, log=True)
#: Student-t tail exponent (γ > 3/2 for a finite mean slope and Λ; 2 = GGX).
GAMMA = Parameter("gamma", "1", 1.6, 30.0)
_KS = Parameter("ks", "1", 1e-6, 10.0, log=True)
_KS2 = Parameter("ks2", "1", 1e-6, 10.0, log=True)
_M = Parameter("m", "1", 1e-3, 2.0, log=True)
_NINF = -np.inf
_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)

# Parameter table columns.
_T_KDPI, _T_LKDPI, _T_KS, _T_KS2, _T_M1, _T_M2, _T_G, _T_LK, _T_P1, _T_P2 = range(10)
_T_COLS = 10


# -- Student-t Smith in numba ---------------------------------------------------------------------


@njit(cache=True)
def _betacf(a, b, x):
    """Continued fraction of the incomplete beta function (modified Lentz; Press et al.,
    Numerical Recipes, 3rd ed., §6.4)."""
    tiny = 1e-300
    qab = a + b
    qap = a + 1.0
    qam = a - 1.0
    c = 1.0
    d = 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 400):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        de = d * c
        h *= de
        if abs(de - 1.0) < 1e-16:
            break
    return h


@njit(cache=True)
def betainc(a, b, x, xc):
    """Regularised incomplete beta I_x(a, b) for x ∈ [0, 1]; ``xc`` = 1 − x given separately
    (accurately) so that x → 1 keeps its digits."""
    if x <= 0.0:
        return 0.0
    if xc <= 0.0:
        return 1.0
    lbt = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log(xc)
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(lbt) * _betacf(a, b, x) / a
    return 1.0 - math.exp(lbt) * _betacf(b, a, xc) / b


@njit(cache=True)
def _c_lambda_std(c, u, gamma, log_k):
    """cos θ · Λ of the Student-t distribution with u = m sin θ (finite as c → 0; see
    fitting.models.microfacet.smith_lambda_student_t): u K ν (1 + μ²/ν)^(3/2−γ)/(2γ−3) − ½ c I."""
    if u <= 0.0:
        return 0.0
    nu = gamma - 1.0
    mu2 = (c / u) * (c / u)
    first = u * math.exp(log_k + (1.5 - gamma) * math.log1p(mu2 / nu)) * nu / (2.0 * gamma - 3.0)
    second = 0.5 * c * betainc(nu, 0.5, nu / (nu + mu2), mu2 / (nu + mu2))
    return max(first - second, 0.0)


@njit(cache=True)
def _c_lambda(c, s, m, dist, gamma, log_k):
    if dist == _DIST_STD:
        return _c_lambda_std(c, m * s, gamma, log_k)
    if dist == mk.DIST_GGX:
        q = math.sqrt(c * c + m * m * s * s) + c
        return 0.5 * m * m * s * s / q if q > 0.0 else 0.0
    if s == 0.0:
        return 0.0
    a = c / (m * s)
    if a > 27.3:
        return 0.0
    return m * s * 0.5 * (math.exp(-a * a) * _INV_SQRT_PI - a * math.erfc(a))


@njit(cache=True)
def _d(t2, m, dist, gamma):
    im2 = 1.0 / (m * m)
    x = t2 * im2
    dn = im2 / math.pi
    if dist == mk.DIST_BECKMANN:
        return math.exp(-x) * (1.0 + t2) * (1.0 + t2) * dn if x < 745.2 else 0.0
    if dist == mk.DIST_GGX:
        r = (1.0 + t2) / (1.0 + x)
        return r * r * dn
    return (1.0 + t2) * (1.0 + t2) * dn * math.exp(-gamma * math.log1p(x / (gamma - 1.0)))


@njit(cache=True)
def _g(geo, j, m, dist, shadow, gamma, log_k):
    if shadow == mk.SHADOW_VCAVITY:
        return geo[8, j]
    ci = geo[1, j]
    co = geo[2, j]
    li = _c_lambda(ci, geo[3, j], m, dist, gamma, log_k)
    lo = _c_lambda(co, geo[4, j], m, dist, gamma, log_k)
    if shadow == mk.SHADOW_SMITH_CORRELATED:
        return 0.25 / (ci * co + (co * li + ci * lo))
    return 0.25 / ((ci + li) * (co + lo))


@njit(cache=True)
def _two_lobe_one(geo, j, pt, r, d1, d2, lobes, shadow, fresnel, log_out):
    if geo[0, j] == 0.0:
        return _NINF if log_out else 0.0
    t2 = geo[5, j]
    gamma = pt[r, _T_G]
    log_k = pt[r, _T_LK]
    fr = mk.fresnel_value(geo[6, j], fresnel, pt[r, _T_P1], pt[r, _T_P2])
    m1 = pt[r, _T_M1]
    spec = pt[r, _T_KS] * _d(t2, m1, d1, gamma) * _g(geo, j, m1, d1, shadow, gamma, log_k)
    if lobes == 2:
        m2 = pt[r, _T_M2]
        spec += pt[r, _T_KS2] * _d(t2, m2, d2, gamma) * _g(geo, j, m2, d2, shadow, gamma, log_k)
    v = pt[r, _T_KDPI] + fr * spec
    if not log_out:
        return v
    if v > 0.0:
        return math.log(v)
    return pt[r, _T_LKDPI]  # −inf when kd = 0 and both lobes underflow


@njit(cache=True)
def _block_staged(geo, pt, d1, d2, lobes, shadow, fresnel, log_out, out, b, n_chunks):
    """Per-set parameters and Beckmann/GGX lobes: torrance-sparrow's vectorised stages."""
    n = out.shape[1]
    w = b // n_chunks
    j0 = (b - w * n_chunks) * km.CHUNK
    size = min(km.CHUNK, n - j0)
    buf = np.empty((3, size))
    dbuf, gbuf, fbuf = buf[0], buf[1], buf[2]
    acc = np.zeros(size)
    for lobe in range(lobes):
        m = pt[w, _T_M1] if lobe == 0 else pt[w, _T_M2]
        dist = d1 if lobe == 0 else d2
        weight = pt[w, _T_KS] if lobe == 0 else pt[w, _T_KS2]
        mk.stage_distribution(geo, j0, dbuf, 1.0 / (m * m), 1.0 / (math.pi * m * m), dist)
        mk.stage_shadowing(geo, j0, gbuf, m, dist, shadow)
        for i in range(size):
            acc[i] += weight * dbuf[i] * gbuf[i]
    mk.stage_fresnel(geo, j0, fbuf, pt[w, _T_P1], pt[w, _T_P2], fresnel)
    kdpi = pt[w, _T_KDPI]
    for i in range(size):
        j = j0 + i
        v = kdpi + fbuf[i] * acc[i]
        if geo[0, j] == 0.0:
            out[w, j] = _NINF if log_out else 0.0
        elif not log_out:
            out[w, j] = v
        else:
            out[w, j] = math.log(v) if v > 0.0 else pt[w, _T_LKDPI]


@njit(cache=True)
def _block(geo, pt, rs, cs, d1, d2, lobes, shadow, fresnel, log_out, out, b, n_chunks):
    if cs == 0 and d1 != _DIST_STD and (lobes == 1 or d2 != _DIST_STD):
        _block_staged(geo, pt, d1, d2, lobes, shadow, fresnel, log_out, out, b, n_chunks)
        return
    n = out.shape[1]
    w = b // n_chunks
    j0 = (b - w * n_chunks) * km.CHUNK
    for j in range(j0, min(j0 + km.CHUNK, n)):
        out[w, j] = _two_lobe_one(
            geo, j, pt, w * rs + j * cs, d1, d2, lobes, shadow, fresnel, log_out
        )


@njit(parallel=True, cache=True)
def _par(geo, pt, rs, cs, d1, d2, lobes, shadow, fresnel, log_out, out):
    n_chunks = (out.shape[1] + km.CHUNK - 1) // km.CHUNK
    for b in prange(out.shape[0] * n_chunks):
        _block(geo, pt, rs, cs, d1, d2, lobes, shadow, fresnel, log_out, out, np.int64(b), n_chunks)


@njit(cache=True)
def _ser(geo, pt, rs, cs, d1, d2, lobes, shadow, fresnel, log_out, out):
    n_chunks = (out.shape[1] + km.CHUNK - 1) // km.CHUNK
    for b in range(out.shape[0] * n_chunks):
        _block(geo, pt, rs, cs, d1, d2, lobes, shadow, fresnel, log_out, out, b, n_chunks)


def _parameter_table(flat: Mapping[str, np.ndarray]) -> np.ndarray:
    kd, gamma = flat["kd"], flat["gamma"]
    t = np.empty((kd.shape[0], _T_COLS))
    with np.errstate(divide="ignore"):
        t[:, _T_KDPI] = kd / np.pi
        t[:, _T_LKDPI] = np.log(kd / np.pi)
    t[:, _T_KS] = flat["ks"]
    t[:, _T_KS2] = flat["ks2"]
    t[:, _T_M1] = flat["m"]
    t[:, _T_M2] = flat["m"] * flat["m_ratio"]
    t[:, _T_G] = gamma
    nu = np.maximum(gamma - 1.0, 1e-12)
    t[:, _T_LK] = 0.5 * np.log(nu / np.pi) + gammaln(gamma - 0.5) - gammaln(gamma)
    t[:, _T_P1] = flat["p1"]
    t[:, _T_P2] = flat["p2"]
    return t


def _choice(option: str, value: str, table) -> str:
    if value not in table:
        raise ValueError(f"two-lobe: {option}={value!r}; choose one of {', '.join(table)}")
    return value


class TwoLobe(Model):
    """kd/π + F [ks D₁ G₁ + ks2 D₂ G₂]/(4 cos θ_i cos θ_o) (or one lobe); module docstring."""

    def __init__(
        self,
        distribution: str = "ggx",
        distribution2: str = "ggx",
        shadowing: str = "smith",
        fresnel: str = "dielectric",
        lobes: str = "2",
    ):
        options = {
            "distribution": _choice("distribution", distribution, DISTRIBUTIONS),
            "distribution2": _choice("distribution2", distribution2, DISTRIBUTIONS),
            "shadowing": _choice("shadowing", shadowing, SHADOWING),
            "fresnel": _choice("fresnel", fresnel, FRESNEL_CODES),
            "lobes": _choice("lobes", lobes, ("1", "2")),
        }
        two = lobes == "2"
        uses_t = distribution == "student-t" or (two and distribution2 == "student-t")
        params = (
            KD,
            _KS,
            _M,
            *((_KS2, M_RATIO) if two else ()),
            *((GAMMA,) if uses_t else ()),
            *FRESNEL_PARAMETERS[fresnel],
        )
        # As for torrance-sparrow: normalised D, G ≤ 1, F ≤ 1, so weights ks (+ ks2) ≤ 1 conserve
        # energy (the prior box, like torrance-sparrow's, lets the weights exceed that).
        flags = {"reciprocal": True, "energy_conserving": True, "isotropic": True}
        super().__init__("two-lobe", params, options, flags)
        self._codes = (
            DISTRIBUTIONS[distribution],
            DISTRIBUTIONS[distribution2],
            2 if two else 1,
            SHADOWING[shadowing],
            FRESNEL_CODES[fresnel],
        )
        self._two = two
        self._uses_t = uses_t

    def _fresnel_params(self, v):
        zero = np.zeros(())
        return {
            "dielectric": lambda: (v["ior"], zero),
            "conductor": lambda: (v["eta"], v["k"]),
            "schlick": lambda: (v["f0"], zero),
            "none": lambda: (zero, zero),
        }[self.options["fresnel"]]()

    def _cols(self, v):
        p1, p2 = self._fresnel_params(v)
        one = np.ones(())
        return {
            "kd": v["kd"],
            "ks": v["ks"],
            "m": v["m"],
            "ks2": v["ks2"] if self._two else np.zeros(()),
            "m_ratio": v["m_ratio"] if self._two else one * 2.0,
            "gamma": v["gamma"] if self._uses_t else one * 2.0,
            "p1": p1,
            "p2": p2,
        }

    def _numba(self, v, wi, wo, log, out):
        geo = mk.microfacet_geometry(wi, wo, parallel_geometry(out, "two_lobe"))
        flat, per_sample = flat_parameters(self._cols(v), out)
        pt = _parameter_table(flat)
        rs, cs = (out.shape[1], 1) if per_sample else (1, 0)
        dispatch("two_lobe", _par, _ser, out.size, geo, pt, rs, cs, *self._codes, log, out)

    def _lobe_numpy(self, t2, ci, si, co, so, ch, vh, m, dist, gamma):
        name = {v: k for k, v in DISTRIBUTIONS.items()}[dist]
        d = {
            "beckmann": lambda: _mf.beckmann(t2, m),
            "ggx": lambda: _mf.ggx(t2, m),
            "student-t": lambda: _mf.student_t(t2, m, gamma),
        }[name]()
        shadow = self.options["shadowing"]
        if shadow == "v-cavity":
            g = _mf.v_cavity(ch, ci, co, vh) / (4.0 * ci * co)
        else:
            kind = "correlated" if shadow == "smith-correlated" else "separable"
            g = 0.25 * _mf.g2_over_cos_cos(ci, si, co, so, m, name, kind, gamma)
        return d * g

    def _numpy(self, v, wi, wo, log):
        cols = self._cols(v)
        above = above_horizon(wi, wo)
        up = np.array([0.0, 0.0, 1.0])
        wi_s = np.where(above[:, None], wi, up)
        wo_s = np.where(above[:, None], wo, up)
        s = wi_s + wo_s
        norm = np.linalg.norm(s, axis=1)
        t2 = _mf.tan2_theta(s)
        ch = s[:, 2] / norm
        vh = np.clip(0.5 * (np.sum(wi_s * s, axis=1) + np.sum(wo_s * s, axis=1)) / norm, 0, 1)
        ci, co = wi_s[:, 2], wo_s[:, 2]
        si, so = np.hypot(wi_s[:, 0], wi_s[:, 1]), np.hypot(wo_s[:, 0], wo_s[:, 1])
        geo = (t2, ci, si, co, so, ch, vh)
        d1, d2 = self._codes[:2]
        spec = cols["ks"] * self._lobe_numpy(*geo, cols["m"], d1, cols["gamma"])
        if self._two:
            m2 = cols["m"] * cols["m_ratio"]
            spec = spec + cols["ks2"] * self._lobe_numpy(*geo, m2, d2, cols["gamma"])
        p1, p2 = cols["p1"], cols["p2"]
        fres = {
            "dielectric": lambda: _fresnel.dielectric(vh, p1),
            "conductor": lambda: _fresnel.conductor(vh, p1, p2),
            "schlick": lambda: _fresnel.schlick(vh, p1),
            "none": lambda: np.ones_like(vh),
        }[self.options["fresnel"]]()
        f = np.where(above, combine(v["kd"], fres * spec, False), 0.0)
        if not log:
            return f
        with np.errstate(divide="ignore"):
            return np.log(f)


# -- the posterior check --------------------------------------------------------------------------


@dataclass(frozen=True)
class LobeCheck:
    """Whether a two-lobe fit resolved two lobes; ``reasons`` say why not (one line each)."""

    distinguishable: bool
    reasons: tuple[str, ...]


def _quantiles(p: Mapping[str, float]) -> tuple[float, float, float]:
    return float(p["p2.5"]), float(p["median"]), float(p["p97.5"])


def check_lobes(
    parameters: Mapping[str, Mapping[str, float]],
    *,
    ratio_lower: float = M_RATIO.lower,
    weight_span: float = 100.0,
    draws: Mapping[str, np.ndarray] | None = None,
    max_weight_correlation: float = 0.95,
) -> LobeCheck:
    """Posterior check of a two-lobe fit: are the two lobes distinguishable?

    ``parameters`` is the fit JSON's "parameters" table (NAME → {"median", "p2.5", "p97.5"…};
    per-channel weights are ks_R, ks2_R, …). Not distinguishable when any of:

    * m_ratio's 95 % interval reaches within 10 % of its lower bound ``ratio_lower`` — the data
      do not tell the broad lobe's width from the sharp one's (the ordering constraint, not
      the data, is then holding the lobes apart);
    * a lobe weight's 95 % interval spans more than ``weight_span`` (×100 by default) — that
      lobe's weight is consistent with (nearly) zero in that channel;
    * with ``draws`` (natural-unit posterior draws by name), ln ks and ln ks2 of a channel are
      correlated beyond −``max_weight_correlation``: one lobe's weight is traded for the
      other's, i.e. the data see their sum only.
    """
    reasons = []
    if "m_ratio" in parameters:
        lo, _, _ = _quantiles(parameters["m_ratio"])
        if lo <= ratio_lower * 1.1:
            reasons.append(
                f"m_ratio's 95 % interval reaches its lower bound {ratio_lower:g} "
                f"(p2.5 = {lo:.3g}): the broad lobe's width is not resolved"
            )
    for name in sorted(parameters):
        base = name.split("_")[0]
        if base not in ("ks", "ks2"):
            continue
        lo, med, hi = _quantiles(parameters[name])
        if lo <= 0 or hi / lo > weight_span:
            reasons.append(
                f"{name}'s 95 % interval [{lo:.3g}, {hi:.3g}] spans more than ×{weight_span:g}: "
                "that lobe's weight is consistent with zero"
            )
    if draws is not None:
        for name in sorted(draws):
            if not name.startswith("ks2"):
                continue
            partner = "ks" + name[3:]
            if partner not in draws:
                continue
            a, b = np.log(draws[partner]), np.log(draws[name])
            if np.std(a) > 0 and np.std(b) > 0:
                r = float(np.corrcoef(a, b)[0, 1])
                if r < -max_weight_correlation:
                    reasons.append(
                        f"ln {partner} and ln {name} are correlated ({r:.2f}): the data "
                        "constrain only the lobes' sum"
                    )
    return LobeCheck(not reasons, tuple(reasons))

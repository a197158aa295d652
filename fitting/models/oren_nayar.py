"""Rough diffuse reflection with retro-reflection: Oren & Nayar (1994).

M. Oren and S. K. Nayar, "Generalization of Lambert's reflectance model", SIGGRAPH 1994,
pp. 239–246. The surface is a collection of long symmetric V-cavities with Lambertian facets
of albedo ρ; facet slopes θ_a follow a Gaussian of standard deviation σ (radians) over the
solid angle of facet normals, azimuths φ_a are uniform. Masking, shadowing and the foreshortening
of tilted facets make the surface brighter toward the light (retro-reflection) and flatter than
Lambert's law; σ = 0 is Lambert exactly.

With α = max(θ_i, θ_o), β = min(θ_i, θ_o), c = cos(φ_o − φ_i) and f_r = L/(E₀ cos θ_i):

full (eqs. 26–29; the default)
    f = ρ/π [C₁ + c C₂ tan β + (1 − |c|) C₃ tan((α + β)/2)]
        + 0.17 ρ²/π · σ²/(σ² + 0.13) · [1 − c (2β/π)²]        (two-bounce interreflection)
    C₁ = 1 − 0.5 σ²/(σ² + 0.33);  C₂ = 0.45 σ²/(σ² + 0.09) · (sin α  if c ≥ 0,
    else sin α − (2β/π)³);  C₃ = 0.125 σ²/(σ² + 0.09) · (4αβ/π²)²
qualitative (eq. 30)
    f = ρ/π [A + B max(0, c) sin α tan β],  A = C₁,  B = 0.45 σ²/(σ² + 0.09)
v-cavity
    the single-bounce V-cavity integral the full model approximates, by quadrature:
    f = ρ/(π cos θ_i) ∫∫ p(θ_a) ⟨ω_i,a⟩⁺⟨ω_o,a⟩⁺ / (⟨a,n⟩ cos θ_o) · GAF(a) dφ_a dθ_a with
    p ∝ exp(−θ_a²/(2σ²)) sin θ_a on θ_a ∈ [0, π/2] (normalised there) and the V-cavity
    GAF = min{1, 2⟨n,a⟩ cos θ_i/⟨ω_i,a⟩, 2⟨n,a⟩ cos θ_o/⟨ω_o,a⟩} (Torrance & Sparrow's; eq. 9),
    plus the same interreflection term. Slow (a 2-D quadrature per direction pair, cached per
    direction set); the reference the approximations are measured against.

The full form's forward term c C₂ tan β is negative for c < 0 and grows without bound at
grazing: for rough surfaces (σ ≳ 0.5) the published bracket goes negative there (e.g.
θ_i → 90°, θ_o = 80°, Δφ = 180°), so it is clamped at 0 (a direct radiance cannot be
negative; the V-cavity integral there is small and positive).

The ``interreflection`` option switches the two-bounce term (default: on for full and
v-cavity, off for the qualitative model, which has none). Parameters: kd = ρ (facet albedo,
0…1) and sigma = σ (rad, 0…1; σ → 0 gives Lambert). Reciprocal (every term is symmetric in
ω_i, ω_o) and isotropic; f grows like tan β as both directions approach the horizon (the
V-cavity model does too), which is finite for every direction above it.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
from numba import prange

from fitting.models import kernel_math as km
from fitting.models.base import Model, Parameter, above_horizon, flat_parameters, parallel_geometry
from plumbing.numba_policy import dispatch, njit  # its flags: numba's cache ignores them, see there

__all__ = [
    "FORMS",
    "SIGMA",
    "OrenNayar",
    "oren_nayar_full",
    "oren_nayar_qualitative",
    "interreflection",
    "v_cavity_direct",
    "v_cavity_nodes",
]

FORMS = {"full": 0, "qualitative": 1, "v-cavity": 2}
SIGMA = Parameter("sigma", "rad", 0.0, 1.0)
_RHO = Parameter("kd", "1", 0.0, 1.0)
_NINF = -np.inf
_TWO_OVER_PI = 2.0 / math.pi


# -- the published formulas (numpy reference) ----------------------------------------------------


def _angles(wi, wo):
    """θ_i, θ_o, cos(φ_o − φ_i) (0 where an azimuth is undefined) for unit pairs (N, 3)."""
    si, so = np.hypot(wi[:, 0], wi[:, 1]), np.hypot(wo[:, 0], wo[:, 1])
    ti, to = np.arctan2(si, wi[:, 2]), np.arctan2(so, wo[:, 2])
    den = si * so
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(den > 0, (wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1]) / den, 0.0)
    return ti, to, np.clip(c, -1.0, 1.0)


def oren_nayar_full(theta_i, theta_o, cos_dphi, sigma) -> np.ndarray:
    """The direct term of the full model, f₁·π/ρ = C₁ + c C₂ tan β + (1 − |c|) C₃ tan((α+β)/2)
    (Oren & Nayar 1994, eqs. 26–29; dimensionless; θ in rad, below π/2)."""
    a, b = np.maximum(theta_i, theta_o), np.minimum(theta_i, theta_o)
    s2 = np.asarray(sigma, dtype=np.float64) ** 2
    c = np.asarray(cos_dphi, dtype=np.float64)
    c1 = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b2 = 0.45 * s2 / (s2 + 0.09)
    c2 = np.where(c >= 0.0, b2 * np.sin(a), b2 * (np.sin(a) - (_TWO_OVER_PI * b) ** 3))
    c3 = 0.125 * s2 / (s2 + 0.09) * (4.0 * a * b / np.pi**2) ** 2
    return c1 + c * c2 * np.tan(b) + (1.0 - np.abs(c)) * c3 * np.tan(0.5 * (a + b))


def oren_nayar_qualitative(theta_i, theta_o, cos_dphi, sigma) -> np.ndarray:
    """f·π/ρ = A + B max(0, c) sin α tan β (Oren & Nayar 1994, eq. 30)."""
    a, b = np.maximum(theta_i, theta_o), np.minimum(theta_i, theta_o)
    s2 = np.asarray(sigma, dtype=np.float64) ** 2
    big_a = 1.0 - 0.5 * s2 / (s2 + 0.33)
    big_b = 0.45 * s2 / (s2 + 0.09)
    return big_a + big_b * np.maximum(cos_dphi, 0.0) * np.sin(a) * np.tan(b)


def interreflection(theta_i, theta_o, cos_dphi, sigma) -> np.ndarray:
    """Two-bounce term f₂·π/ρ² = 0.17 σ²/(σ² + 0.13) [1 − c (2β/π)²] (Oren & Nayar 1994)."""
    b = np.minimum(theta_i, theta_o)
    s2 = np.asarray(sigma, dtype=np.float64) ** 2
    return 0.17 * s2 / (s2 + 0.13) * (1.0 - cos_dphi * (_TWO_OVER_PI * b) ** 2)


# -- the V-cavity integral by quadrature --------------------------------------------------------


def v_cavity_nodes(n_phi: int = 192, gauss: int = 8, theta_min: float = 1e-5):
    """Quadrature of the facet-normal integral: θ_a nodes and weights on [0, π/2] (Gauss-Legendre
    panels shrinking geometrically toward 0, down to ``theta_min`` of the range, so that a
    Gaussian with σ ≥ 1e-4 is resolved) and ``n_phi`` midpoint azimuths."""
    frac = np.concatenate(
        [[0.0], np.geomspace(theta_min, 1.0, 1 + int(np.ceil(np.log2(1 / theta_min))))]
    )
    x, w = np.polynomial.legendre.leggauss(gauss)
    a, b = frac[:-1, None] * np.pi / 2, frac[1:, None] * np.pi / 2
    theta = (0.5 * (b - a) * x + 0.5 * (b + a)).ravel()
    w_theta = (0.5 * (b - a) * w).ravel()
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    return theta, w_theta, phi


@njit(cache=True)
def _k_row(wi, wo, st, ct, cp, sp, kt, j):
    """K_j(θ_a) = (1/(π cos θ_i)) ∫ ⟨ω_i,a⟩⁺⟨ω_o,a⟩⁺ GAF/(⟨a,n⟩ cos θ_o) dφ_a for pair j; the
    sines and cosines of the nodes are precomputed (``st, ct`` of θ_a, ``cp, sp`` of φ_a)."""
    six, siy, ci = wi[j, 0], wi[j, 1], wi[j, 2]
    sox, soy, co = wo[j, 0], wo[j, 1], wo[j, 2]
    if not (ci > 0.0 and co > 0.0):
        return
    scale = 2.0 / (cp.size * ci * co)  # dφ/(π cos θ_i cos θ_o) with dφ = 2π/n_φ
    for k in range(st.size):
        # ⟨ω,a⟩ = sin θ_a (ω_x cos φ_a + ω_y sin φ_a) + cos θ_a ω_z
        sti = st[k]
        cti = ct[k]
        ci_t = ci * cti
        co_t = co * cti
        acc = 0.0
        for p in range(cp.size):
            sa = sti * (six * cp[p] + siy * sp[p]) + ci_t
            va = sti * (sox * cp[p] + soy * sp[p]) + co_t
            if sa > 0.0 and va > 0.0:
                # lit-and-visible fraction min{1, 2⟨n,a⟩ cos θ_i/⟨ω_i,a⟩, 2⟨n,a⟩ cos θ_o/⟨ω_o,a⟩}
                # times ⟨ω_i,a⟩⟨ω_o,a⟩, written without a division per term
                acc += min(sa * va, 2.0 * min(ci_t * va, co_t * sa)) / cti
        kt[k, j] = acc * scale


@njit(parallel=True, cache=True)
def _k_table_par(wi, wo, st, ct, cp, sp):
    kt = np.zeros((st.size, wi.shape[0]))
    for j in prange(wi.shape[0]):
        _k_row(wi, wo, st, ct, cp, sp, kt, np.int64(j))
    return kt


@njit(cache=True)
def _k_table_ser(wi, wo, st, ct, cp, sp):
    kt = np.zeros((st.size, wi.shape[0]))
    for j in range(wi.shape[0]):
        _k_row(wi, wo, st, ct, cp, sp, kt, j)
    return kt


_NODES = v_cavity_nodes()
_CACHE: dict[bytes, np.ndarray] = {}


def _k_table(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """K (n_θ, N) for a direction set, cached by content (a fit evaluates the same pairs every
    step; the table costs ~40 µs per pair, the weighted sum over it ~0.2 µs)."""
    key = hashlib.blake2b(wi.tobytes() + wo.tobytes(), digest_size=16).digest()
    if key not in _CACHE:
        theta, _, phi = _NODES
        trig = (np.sin(theta), np.cos(theta), np.cos(phi), np.sin(phi))
        par = wi.shape[0] >= 64
        _CACHE[key] = (_k_table_par if par else _k_table_ser)(wi, wo, *trig)
        while len(_CACHE) > 8:
            _CACHE.pop(next(iter(_CACHE)))
    return _CACHE[key]


def _theta_weights(sigma: np.ndarray) -> np.ndarray:
    """Normalised weights (rows, n_θ) of p(θ_a) ∝ exp(−θ_a²/(2σ²)) sin θ_a per σ (2π included);
    σ below the finest node puts all weight on the flat facet (θ_a → 0, Lambert)."""
    theta, w_theta, _ = _NODES
    sigma = np.asarray(sigma, dtype=np.float64).reshape(-1)
    with np.errstate(divide="ignore", invalid="ignore", under="ignore"):
        logw = -(theta[None, :] ** 2) / (2.0 * sigma[:, None] ** 2)
        w = np.exp(logw - logw.max(axis=1, keepdims=True)) * np.sin(theta) * w_theta
        w /= 2.0 * np.pi * w.sum(axis=1, keepdims=True)
    flat = ~np.all(np.isfinite(w), axis=1) | (sigma < 1e-9)
    w[flat] = 0.0
    w[flat, 0] = 1.0 / (2.0 * np.pi)
    return w


def v_cavity_direct(wi, wo, sigma) -> np.ndarray:
    """Single-bounce V-cavity f·π/ρ for unit pairs (N, 3) and σ (scalar or (W, 1)) → (N,) or
    (W, N); 0 below the horizon. The quadrature converges to ~1e-4 relative (kinks of GAF)."""
    wi = np.ascontiguousarray(wi, dtype=np.float64)
    wo = np.ascontiguousarray(wo, dtype=np.float64)
    w = _theta_weights(sigma)
    out = np.pi * (w @ _k_table(wi, wo))
    return out[0] if np.ndim(sigma) == 0 else out


# -- the numba kernel for the closed forms ------------------------------------------------------


# Geometry rows (per pair): valid, cos Δφ, sin α, tan β, tan((α+β)/2), 2β/π, (4αβ/π²)².
_O_ROWS = 7


@njit(cache=True)
def _on_row(wi, wo, geo, j):
    ci = wi[j, 2]
    co = wo[j, 2]
    if not (ci > 0.0 and co > 0.0):
        return
    si = math.sqrt(wi[j, 0] * wi[j, 0] + wi[j, 1] * wi[j, 1])
    so = math.sqrt(wo[j, 0] * wo[j, 0] + wo[j, 1] * wo[j, 1])
    den = si * so
    cdp = (wi[j, 0] * wo[j, 0] + wi[j, 1] * wo[j, 1]) / den if den > 0.0 else 0.0
    a = max(math.atan2(si, ci), math.atan2(so, co))
    b = min(math.atan2(si, ci), math.atan2(so, co))
    geo[0, j] = 1.0
    geo[1, j] = min(max(cdp, -1.0), 1.0)
    geo[2, j] = math.sin(a)
    geo[3, j] = math.tan(b)
    geo[4, j] = math.tan(0.5 * (a + b))
    geo[5, j] = _TWO_OVER_PI * b
    y = 4.0 * a * b / (math.pi * math.pi)
    geo[6, j] = y * y


@njit(parallel=True, cache=True)
def _on_geometry_par(wi, wo):
    geo = np.zeros((_O_ROWS, wi.shape[0]))
    for j in prange(wi.shape[0]):
        _on_row(wi, wo, geo, np.int64(j))
    return geo


@njit(cache=True)
def _on_geometry_ser(wi, wo):
    geo = np.zeros((_O_ROWS, wi.shape[0]))
    for j in range(wi.shape[0]):
        _on_row(wi, wo, geo, j)
    return geo


@njit(cache=True)
def _on_value(geo, j, rho, sigma, form, inter):
    """f for pair j: the closed form's bracket (clamped at 0, see OrenNayar) + interreflection."""
    s2 = sigma * sigma
    c1 = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b2 = 0.45 * s2 / (s2 + 0.09)
    cdp = geo[1, j]
    x = geo[5, j]
    if form == 1:
        v = c1 + b2 * max(cdp, 0.0) * geo[2, j] * geo[3, j]
    else:
        c2 = b2 * geo[2, j] if cdp >= 0.0 else b2 * (geo[2, j] - x * x * x)
        c3 = 0.125 * s2 / (s2 + 0.09) * geo[6, j]
        v = c1 + cdp * c2 * geo[3, j] + (1.0 - abs(cdp)) * c3 * geo[4, j]
    f = rho / math.pi * max(v, 0.0)
    if inter:
        f += 0.17 * rho * rho / math.pi * s2 / (s2 + 0.13) * (1.0 - cdp * x * x)
    return f


@njit(cache=True)
def _on_block(geo, rho, sig, rs, cs, form, inter, log_out, out, b, n_chunks):
    n = out.shape[1]
    w = b // n_chunks
    j0 = (b - w * n_chunks) * km.CHUNK
    for j in range(j0, min(j0 + km.CHUNK, n)):
        r = w * rs + j * cs
        if geo[0, j] == 0.0:
            out[w, j] = _NINF if log_out else 0.0
            continue
        f = _on_value(geo, j, rho[r], sig[r], form, inter)
        if log_out:
            out[w, j] = math.log(f) if f > 0.0 else _NINF
        else:
            out[w, j] = f


@njit(parallel=True, cache=True)
def _on_par(geo, rho, sig, rs, cs, form, inter, log_out, out):
    n_chunks = (out.shape[1] + km.CHUNK - 1) // km.CHUNK
    for b in prange(out.shape[0] * n_chunks):
        _on_block(geo, rho, sig, rs, cs, form, inter, log_out, out, np.int64(b), n_chunks)


@njit(cache=True)
def _on_ser(geo, rho, sig, rs, cs, form, inter, log_out, out):
    n_chunks = (out.shape[1] + km.CHUNK - 1) // km.CHUNK
    for b in range(out.shape[0] * n_chunks):
        _on_block(geo, rho, sig, rs, cs, form, inter, log_out, out, b, n_chunks)


class OrenNayar(Model):
    """Oren & Nayar 1994 rough diffuse model; ``form`` full | qualitative | v-cavity."""

    def __init__(self, form: str = "full", interreflection: str = "auto"):
        if form not in FORMS:
            raise ValueError(f"oren-nayar: form={form!r}; choose one of {', '.join(FORMS)}")
        if interreflection not in ("auto", "yes", "no"):
            raise ValueError(
                f"oren-nayar: interreflection={interreflection!r}; choose one of auto, yes, no"
            )
        if interreflection == "yes" and form == "qualitative":
            raise ValueError(
                "oren-nayar: the qualitative model (eq. 30) has no interreflection term; use "
                "interreflection=no or form=full"
            )
        inter = interreflection == "yes" or (interreflection == "auto" and form != "qualitative")
        flags = {
            "reciprocal": True,
            # Not derived to conserve energy: the closed forms are fits, and the measured albedo
            # of the full model exceeds 1 at grazing (gonio models --check).
            "energy_conserving": False,
            "isotropic": True,
        }
        super().__init__(
            "oren-nayar",
            (_RHO, SIGMA),
            {"form": form, "interreflection": "yes" if inter else "no"},
            flags,
        )
        self._form = FORMS[form]
        self._inter = inter

    def _direct_numpy(self, wi, wo, sigma):
        ti, to, c = _angles(wi, wo)
        if self._form == 0:
            return oren_nayar_full(ti, to, c, sigma)
        if self._form == 1:
            return oren_nayar_qualitative(ti, to, c, sigma)
        if np.ndim(sigma) == 1 or (np.ndim(sigma) == 2 and np.shape(sigma)[1] != 1):
            raise ValueError("oren-nayar form=v-cavity: sigma must not vary per sample")
        return v_cavity_direct(wi, wo, sigma)

    def _numpy(self, v, wi, wo, log):
        above = above_horizon(wi, wo)
        up = np.array([0.0, 0.0, 1.0])
        wi_s = np.where(above[:, None], wi, up)
        wo_s = np.where(above[:, None], wo, up)
        rho, sigma = v["kd"], v["sigma"]
        f = rho / np.pi * np.maximum(self._direct_numpy(wi_s, wo_s, sigma), 0.0)
        if self._inter:
            ti, to, c = _angles(wi_s, wo_s)
            f = f + rho * rho / np.pi * interreflection(ti, to, c, sigma)
        f = np.where(above, f, 0.0)
        if not log:
            return f
        with np.errstate(divide="ignore"):
            return np.log(f)

    def _numba(self, v, wi, wo, log, out):
        if self._form == 2:
            # The quadrature path: a cached table per direction set, then one weighted sum.
            res = self._numpy({"kd": v["kd"], "sigma": v["sigma"]}, wi, wo, log)
            out[...] = np.broadcast_to(res, out.shape)
            return
        flat, per_sample = flat_parameters({"kd": v["kd"], "sigma": v["sigma"]}, out)
        rs, cs = (out.shape[1], 1) if per_sample else (1, 0)
        par_geo = parallel_geometry(out, "oren_nayar")
        geo = (_on_geometry_par if par_geo else _on_geometry_ser)(wi, wo)
        dispatch(
            "oren_nayar",
            _on_par,
            _on_ser,
            out.size,
            geo,
            flat["kd"],
            flat["sigma"],
            rs,
            cs,
            self._form,
            self._inter,
            log,
            out,
        )

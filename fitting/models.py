"""BRDF models: the seed lecture's Lambert, Phong and Torrance-Sparrow, then beyond (DESIGN §5).

Registry: ``get(name, **options) -> Model`` and ``names()`` dispatch to :mod:`fitting.registry`,
where every model (these and those of :mod:`fitting.anisotropic`, :mod:`fitting.oren_nayar`,
:mod:`fitting.multilobe`) is registered once with its options, aliases and reference. Every
model returns f_r in sr⁻¹
(never f_r·cos θ_o), zero below the horizon (cos θ_i ≤ 0 or cos θ_o ≤ 0), for direction pairs
``wi``, ``wo`` of shape (N, 3) (unit vectors in the sample frame, both pointing away from the
surface). Parameters are passed by name; scalars give shape (N,), arrays of shape (W, 1) give
(W, N) — W parameter sets such as MCMC walkers — and anything else that broadcasts against
(N,) or (W, N) is accepted too.

Models
------
lambert            f = kd/π.
phong              f = kd/π + ks (l̂·r̂)^n, r̂ the mirror of ω_o, base clamped at 0 (seed form;
                   ks in sr⁻¹). Reciprocal (l̂·r̂ = 2cosθ_i cosθ_o − ω_i·ω_o), not energy
                   conserving.
phong-normalized   f = kd/π + ks (n+2)/(2π) cos^n α (Lafortune & Willems 1994, "modified Phong").
blinn-phong        f = kd/π + ks N(n) cos^n θ_h with the exact normal-incidence normalisation
                   N(n) = (n+2)(n+4) / (8π (2^(−n/2) + n)) (Giesen 2009), so ks = 1 reflects
                   all light at normal incidence.
torrance-sparrow   f = kd/π + ks D G F / (4 cos θ_i cos θ_o) with the π-normalised D.
                   The default options (beckmann, v-cavity, dielectric) are *the seed's exact
                   formula* f = kd/π + ks D_seed G F/(π cos θ_i cos θ_o), because
                   D_seed = exp(−tan²β/m²)/(4 m² cos⁴β) satisfies D_seed/π ≡ D_norm/4 with
                   D_norm = exp(−tan²β/m²)/(π m² cos⁴β) (DESIGN §5; tested to 1e-12).
                   So one form serves every option:
                   distribution = "beckmann" | "ggx"                (m is Beckmann m / GGX α)
                   shadowing    = "v-cavity" | "smith" | "smith-rational" | "smith-correlated"
                                  (smith: separable exact-Λ Smith; smith-rational: separable with
                                  Walter's rational Beckmann G₁, as Mitsuba; for GGX the rational
                                  option is the exact GGX G₁, as in Mitsuba; smith-correlated:
                                  height-correlated Smith G₂ = 1/(1+Λ_i+Λ_o))
                   fresnel      = "dielectric" (ior) | "conductor" (eta, k) | "schlick" (f0) |
                                  "none" (F ≡ 1, a perfect conductor like Mitsuba's material
                                  "none")

Two backends: ``backend="numba"`` (default; fused kernels in :mod:`fitting.kernels`) and
``backend="numpy"`` (the reference written with :mod:`fitting.microfacet` and
:mod:`fitting.fresnel`, used to test the kernels).

Two precisions of the numba backend: float64 (default: least squares, whose finite-difference
steps of 1.5e-8 relative are below float32's resolution) and, for the models that have the
kernels (``Model.float32``: lambert, torrance-sparrow and its anisotropic twin),
``precision="float32"``:
the same stages in single precision, about twice as fast (twice the vector lanes, cheaper
divides and square roots). Where the formulas are well conditioned the values are within
(64 + 3x) float32 ulps of float64 (x: Beckmann's exponent; tests/test_float32_kernels.py); a
conductor's Fresnel term for a noble metal and a narrow anisotropic lobe lose more. The MCMC's
likelihood uses float32 only where it measures that rounding negligible beside the noise
(:mod:`fitting.likelihood`). Per-sample parameters and ``log_evaluate`` stay float64.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from fitting import fresnel as _fresnel
from fitting import kernels as _k
from fitting import microfacet as _mf

__all__ = [
    "PRECISIONS",
    "Parameter",
    "Model",
    "Lambert",
    "PhongFamily",
    "TorranceSparrow",
    "get",
    "names",
]


PRECISIONS = ("float64", "float32")


@dataclass(frozen=True)
class Parameter:
    """One model parameter: name, unit ("1" dimensionless, "sr^-1"), prior bounds, and whether
    it is a scale parameter best sampled in log space. ``default`` (or None) is used by
    ``evaluate`` when the parameter is not passed."""

    name: str
    unit: str
    lower: float
    upper: float
    log: bool = False
    default: float | None = None


_KD = Parameter("kd", "1", 0.0, 1.0)


@dataclass
class Model:
    """Base class: name, options, parameters, declared flags and the evaluation interface."""

    name: str
    parameters: tuple[Parameter, ...]
    options: dict = field(default_factory=dict)
    flags: dict = field(default_factory=dict)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    #: Whether the numba backend has single-precision kernels (``evaluate(precision="float32")``).
    float32 = False

    # -- public interface ------------------------------------------------------------------
    def evaluate(
        self, params: Mapping, wi, wo, *, backend: str = "numba", precision: str = "float64"
    ) -> np.ndarray:
        """f_r(ω_i, ω_o) in sr⁻¹, shape (N,) or (W, N) (see module docstring). With
        ``precision="float32"`` a float32 array where the model has the kernels for it
        (``float32``) and every parameter is one per set, float64 otherwise."""
        if precision not in PRECISIONS:
            raise ValueError(f"precision {precision!r}; use one of {', '.join(PRECISIONS)}")
        return self._run(params, wi, wo, backend, log=False, float32=precision == "float32")

    def log_evaluate(self, params: Mapping, wi, wo, *, backend: str = "numba") -> np.ndarray:
        """log f_r, computed in log space (−inf where f_r = 0, never NaN)."""
        return self._run(params, wi, wo, backend, log=True)

    # -- plumbing ----------------------------------------------------------------------------
    def _run(self, params, wi, wo, backend, log, float32=False):
        wi, wo, single = _directions(wi, wo)
        values = self._values(params)
        shape = np.broadcast_shapes(*(v.shape for v in values.values()), (wi.shape[0],))
        if len(shape) > 2:
            raise ValueError(
                f"parameter shapes {[v.shape for v in values.values()]} broadcast to {shape}; "
                "use scalars, (N,), (W, 1) or (W, N) arrays"
            )
        if backend == "numpy":
            out = self._numpy(values, wi, wo, log)
            out = np.broadcast_to(out, shape).astype(np.float64, copy=True)
        elif backend == "numba":
            rows = 1 if len(shape) == 1 else shape[0]
            cols = {k: _as_2d(v, rows, wi.shape[0]) for k, v in values.items()}
            float32 = float32 and self.float32 and all(c.shape[1] == 1 for c in cols.values())
            out = np.empty((rows, wi.shape[0]), np.float32 if float32 else np.float64)
            if out.size:
                self._numba(cols, wi, wo, log, out)
            if len(shape) == 1:
                out = out[0]
        else:
            raise ValueError(f"unknown backend {backend!r}; use 'numba' or 'numpy'")
        if single:
            out = out[..., 0]
        return out

    def _values(self, params: Mapping) -> dict[str, np.ndarray]:
        values = {}
        for p in self.parameters:
            if p.name in params:
                values[p.name] = np.asarray(params[p.name], dtype=np.float64)
            elif p.default is not None:
                values[p.name] = np.asarray(p.default, dtype=np.float64)
            else:
                raise KeyError(
                    f"model {self.name!r} needs parameter {p.name!r} "
                    f"(parameters: {', '.join(self.parameter_names)})"
                )
        return values

    def _numpy(self, v, wi, wo, log):  # pragma: no cover - abstract
        raise NotImplementedError

    def _numba(self, v, wi, wo, log, out):  # pragma: no cover - abstract
        raise NotImplementedError


def _directions(wi, wo):
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    single = wi.ndim == 1 and wo.ndim == 1
    wi, wo = np.broadcast_arrays(np.atleast_2d(wi), np.atleast_2d(wo))
    if wi.ndim != 2 or wi.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3); got {wi.shape}")
    return np.ascontiguousarray(wi), np.ascontiguousarray(wo), single


def _as_2d(v: np.ndarray, rows: int, n: int) -> np.ndarray:
    """A parameter as a C-contiguous (rows, 1) or (rows, n) array for the kernels."""
    if v.ndim == 0:
        return np.full((rows, 1), float(v))
    if v.ndim == 1:
        v = v[None, :]
    cols = 1 if v.shape[1] == 1 else n
    return np.ascontiguousarray(np.broadcast_to(v, (rows, cols)), dtype=np.float64)


def _flat_parameters(cols: Mapping, out: np.ndarray) -> tuple[dict[str, np.ndarray], bool]:
    """Parameter columns ((rows, 1), (rows, N) or scalars) → 1-D per-row arrays for a kernel's
    parameter table: one row per set if no column varies per sample, else one row per
    (set, sample), row w·N + j (second value True)."""
    rows, n = out.shape
    cols = {
        k: (_as_2d(np.asarray(c, dtype=np.float64), rows, n) if np.ndim(c) < 2 else c)
        for k, c in cols.items()
    }
    if any(c.shape[1] != 1 for c in cols.values()):
        flat = {k: np.broadcast_to(c, out.shape).ravel() for k, c in cols.items()}
        return {k: np.ascontiguousarray(v) for k, v in flat.items()}, True
    return {k: np.ascontiguousarray(c[:, 0]) for k, c in cols.items()}, False


def _parallel_geometry(out: np.ndarray, kernel: str) -> bool:
    # The per-pair pass is worth threads when the kernel itself runs threaded and N is not tiny.
    return out.shape[1] >= 2048 and _k._prefers_threads(kernel, out.size)


def _above(wi, wo):
    return (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)


def _combine(kd, spec, log):
    """kd/π + spec, or its log with spec given as log spec (log-sum-exp; −inf stays −inf)."""
    if not log:
        return kd / np.pi + spec
    with np.errstate(divide="ignore"):
        return np.logaddexp(np.log(kd / np.pi), spec)


class Lambert(Model):
    """f = kd/π (ρ = kd is the albedo; seed lecture "Diffuse BRDF")."""

    float32 = True

    def __init__(self, **options):
        if options:
            raise TypeError(f"lambert takes no options; got {sorted(options)}")
        super().__init__(
            "lambert",
            (_KD,),
            {},
            {"reciprocal": True, "energy_conserving": True, "isotropic": True},
        )

    def _numpy(self, v, wi, wo, log):
        above = _above(wi, wo)
        f = np.where(above, v["kd"] / np.pi, 0.0)
        if log:
            with np.errstate(divide="ignore"):
                return np.log(f)
        return f

    def _numba(self, v, wi, wo, log, out):
        # kd/π in out's precision: float32 halves the bytes of this store-bound loop
        kdpi = np.ascontiguousarray(np.divide(v["kd"], np.pi), dtype=out.dtype)
        _k.constant_above(kdpi, _above(wi, wo), log, out)


_LOBES = {
    "phong": _k.LOBE_PHONG,
    "phong-normalized": _k.LOBE_PHONG_NORMALIZED,
    "blinn-phong": _k.LOBE_BLINN_PHONG,
}


def blinn_phong_normalization(n):
    """N(n) = (n+2)(n+4) / (8π (2^(−n/2) + n)): ∫ N cos^n θ_h cos θ_o dω_o = 1 at normal incidence
    (F. Giesen, "On the Blinn-Phong normalization factor", 2009)."""
    n = np.asarray(n, dtype=np.float64)
    return (n + 2.0) * (n + 4.0) / (8.0 * np.pi * (np.exp2(-0.5 * n) + n))


class PhongFamily(Model):
    """Phong (seed), energy-normalised modified Phong, and normalised Blinn-Phong lobes + kd/π."""

    def __init__(self, name: str, **options):
        if options:
            raise TypeError(f"{name} takes no options; got {sorted(options)}")
        if name == "phong":
            ks = Parameter("ks", "sr^-1", 1e-6, 1e7, log=True)
            flags = {"reciprocal": True, "energy_conserving": False, "isotropic": True}
        else:
            ks = Parameter("ks", "1", 1e-6, 1.0, log=True)
            flags = {"reciprocal": True, "energy_conserving": True, "isotropic": True}
        super().__init__(name, (_KD, ks, Parameter("n", "1", 1.0, 1e6, log=True)), {}, flags)
        self._kind = _LOBES[name]

    def _base(self, wi, wo):
        if self._kind == _k.LOBE_BLINN_PHONG:
            s = wi + wo
            base = s[:, 2] / np.linalg.norm(s, axis=1)
        else:
            dot = wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1] + wi[:, 2] * wo[:, 2]
            base = 2.0 * (wi[:, 2] * wo[:, 2]) - dot  # l̂·r̂ with r̂ = 2(n̂·v̂)n̂ − v̂
        base = np.clip(base, 0.0, 1.0)
        return np.where(_above(wi, wo), base, 0.0)

    def _log_norm(self, n):
        if self._kind == _k.LOBE_PHONG:
            return np.zeros_like(n)
        if self._kind == _k.LOBE_PHONG_NORMALIZED:
            return np.log((n + 2.0) / (2.0 * np.pi))
        return np.log(blinn_phong_normalization(n))

    def _numpy(self, v, wi, wo, log):
        kd, ks, n = v["kd"], v["ks"], v["n"]
        base = self._base(wi, wo)
        with np.errstate(divide="ignore", invalid="ignore"):
            # n·log(base) instead of base**n: exact for n up to 1e6 and no overflow in between.
            spec = np.log(ks) + self._log_norm(n) + n * np.log(base)
            spec = np.where((base > 0.0) & (ks > 0.0), spec, -np.inf)
        f = _combine(kd, spec if log else np.exp(spec), log)
        return np.where(_above(wi, wo), f, -np.inf if log else 0.0)

    def _numba(self, v, wi, wo, log, out):
        geo = _k.lobe_geometry(wi, wo, self._kind, _parallel_geometry(out, "lobe"))
        cols = {k: v[k] for k in ("kd", "ks", "n")}
        per_sample = any(c.shape[1] != 1 for c in cols.values())
        if per_sample:  # one table row per (set, sample)
            flat = {k: np.broadcast_to(c, out.shape).ravel() for k, c in cols.items()}
        else:
            flat = {k: np.ascontiguousarray(c[:, 0]) for k, c in cols.items()}
        table = _k.lobe_parameter_table(flat["kd"], flat["ks"], flat["n"], self._kind)
        _k.lobe(geo, table, per_sample, log, out)


_DISTRIBUTIONS = {"beckmann": _k.DIST_BECKMANN, "ggx": _k.DIST_GGX}
_SHADOWING = {
    "v-cavity": _k.SHADOW_VCAVITY,
    "smith": _k.SHADOW_SMITH,
    "smith-rational": _k.SHADOW_SMITH_RATIONAL,
    "smith-correlated": _k.SHADOW_SMITH_CORRELATED,
}
_FRESNEL = {
    "dielectric": _k.FRESNEL_DIELECTRIC,
    "conductor": _k.FRESNEL_CONDUCTOR,
    "schlick": _k.FRESNEL_SCHLICK,
    "none": _k.FRESNEL_NONE,
}
_FRESNEL_PARAMETERS = {
    "dielectric": (Parameter("ior", "1", 1.0, 4.0, default=1.5),),
    "conductor": (Parameter("eta", "1", 0.01, 10.0, log=True), Parameter("k", "1", 0.0, 100.0)),
    "schlick": (Parameter("f0", "1", 0.0, 1.0),),
    "none": (),
}


def _choice(option: str, value: str, table: dict) -> str:
    if value not in table:
        raise ValueError(f"torrance-sparrow: {option}={value!r}; choose one of {', '.join(table)}")
    return value


class TorranceSparrow(Model):
    """f = kd/π + ks D G F/(4 cos θ_i cos θ_o); default options = the seed's exact formula."""

    float32 = True

    def __init__(
        self,
        distribution: str = "beckmann",
        shadowing: str = "v-cavity",
        fresnel: str = "dielectric",
    ):
        options = {
            "distribution": _choice("distribution", distribution, _DISTRIBUTIONS),
            "shadowing": _choice("shadowing", shadowing, _SHADOWING),
            "fresnel": _choice("fresnel", fresnel, _FRESNEL),
        }
        params = (
            _KD,
            Parameter("ks", "1", 1e-6, 10.0, log=True),
            Parameter("m", "1", 1e-3, 2.0, log=True),
            *_FRESNEL_PARAMETERS[fresnel],
        )
        flags = {
            "reciprocal": True,
            # Single scattering with a normalised D, a G₂ ≤ G₁ and F ≤ 1 loses energy, never
            # gains it (Heitz 2014); the rational G₁ overshoots the exact one by ≤ 0.35 %.
            "energy_conserving": True,
            "isotropic": True,
            "seed_form": options
            == {"distribution": "beckmann", "shadowing": "v-cavity", "fresnel": "dielectric"},
        }
        super().__init__("torrance-sparrow", params, options, flags)
        self._codes = (_DISTRIBUTIONS[distribution], _SHADOWING[shadowing], _FRESNEL[fresnel])

    def _fresnel_params(self, v):
        fres = self.options["fresnel"]
        if fres == "dielectric":
            return v["ior"], np.zeros(())
        if fres == "conductor":
            return v["eta"], v["k"]
        if fres == "schlick":
            return v["f0"], np.zeros(())
        return np.zeros(()), np.zeros(())

    def _numba(self, v, wi, wo, log, out):
        p1, p2 = self._fresnel_params(v)
        cols = {"kd": v["kd"], "ks": v["ks"], "m": v["m"]}
        cols["p1"] = _as_2d(p1, *out.shape) if p1.ndim < 2 else p1
        cols["p2"] = _as_2d(p2, *out.shape) if p2.ndim < 2 else p2
        geo = _k.microfacet_geometry(wi, wo, _parallel_geometry(out, "ts"), out.dtype)
        if all(c.shape[1] == 1 for c in cols.values()):
            flat = {k: np.ascontiguousarray(c[:, 0]) for k, c in cols.items()}
            kernel = _k.torrance_sparrow
        else:  # some parameter varies per sample: one table row per (set, sample)
            flat = {k: np.broadcast_to(c, out.shape).ravel() for k, c in cols.items()}
            kernel = _k.torrance_sparrow_per_sample
        dist, shadow, fres = self._codes
        table = _k.ts_parameter_table(
            flat["kd"], flat["ks"], flat["m"], flat["p1"], flat["p2"], dist
        )  # float64 (divisions and logs once per set), rounded once for a float32 output
        kernel(geo, table.astype(out.dtype, copy=False), dist, shadow, fres, log, out)

    def _numpy(self, v, wi, wo, log):
        opt = self.options
        kd, ks, m = v["kd"], v["ks"], v["m"]
        above = _above(wi, wo)
        # Evaluate on safe directions below the horizon and mask afterwards.
        wi_s = np.where(above[:, None], wi, [0.0, 0.0, 1.0])
        wo_s = np.where(above[:, None], wo, [0.0, 0.0, 1.0])
        s = wi_s + wo_s
        norm = np.linalg.norm(s, axis=1)
        t2 = _mf.tan2_theta(s)
        ch = s[:, 2] / norm
        vh = np.clip(0.5 * (np.sum(wi_s * s, axis=1) + np.sum(wo_s * s, axis=1)) / norm, 0, 1)
        ci, co = wi_s[:, 2], wo_s[:, 2]
        si, so = np.hypot(wi_s[:, 0], wi_s[:, 1]), np.hypot(wo_s[:, 0], wo_s[:, 1])
        d = _mf.beckmann(t2, m) if opt["distribution"] == "beckmann" else _mf.ggx(t2, m)
        if opt["shadowing"] == "v-cavity":
            g = _mf.v_cavity(ch, ci, co, vh) / (4.0 * (ci * co))
        else:
            kind = {"smith": "separable", "smith-rational": "rational"}.get(
                opt["shadowing"], "correlated"
            )
            if opt["distribution"] == "ggx" and kind == "rational":
                kind = "separable"  # Mitsuba: the rational fit is Beckmann-only
            g = 0.25 * _mf.g2_over_cos_cos(ci, si, co, so, m, opt["distribution"], kind)
        p1, p2 = self._fresnel_params(v)
        fres = {
            "dielectric": lambda: _fresnel.dielectric(vh, p1),
            "conductor": lambda: _fresnel.conductor(vh, p1, p2),
            "schlick": lambda: _fresnel.schlick(vh, p1),
            "none": lambda: np.ones_like(vh),
        }[opt["fresnel"]]()
        if log:
            with np.errstate(divide="ignore"):
                if opt["distribution"] == "beckmann":
                    log_d = -t2 / m**2 + 2.0 * np.log1p(t2) - np.log(np.pi * m**2)
                else:
                    r = (1.0 + t2) / (m**2 + t2)
                    log_d = np.log(m**2 * r * r) - np.log(np.pi)
                spec = np.log(ks) + log_d + np.log(g) + np.log(fres)
            f = _combine(kd, spec, True)
            return np.where(above, f, -np.inf)
        f = _combine(kd, ks * d * g * fres, False)
        return np.where(above, f, 0.0)


def names() -> list[str]:
    """Registered model names, variants included (:func:`fitting.registry.names`)."""
    from fitting import registry

    return registry.names()


def get(name: str, **options) -> Model:
    """A model by name, variant or alias, e.g. ``get("torrance-sparrow", distribution="ggx")``
    (:func:`fitting.registry.get`: unknown names or options raise with the allowed ones)."""
    from fitting import registry

    return registry.get(name, **options)

"""The seed lecture's models: Lambert, the Phong family and Torrance-Sparrow (docs/design.md §5).

Every model obeys the conventions of :mod:`fitting.models.base` (f_r in sr⁻¹, zero below the
horizon, (N,) or (W, N) results).

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
                   D_norm = exp(−tan²β/m²)/(π m² cos⁴β) (docs/design.md §5; tested to 1e-12).
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
"""

from __future__ import annotations

import numpy as np

from fitting.models import fresnel as _fresnel
from fitting.models import lobe_kernels as lk
from fitting.models import microfacet as _mf
from fitting.models import microfacet_kernels as mk
from fitting.models.base import (
    DISTRIBUTION_CODES,
    FRESNEL_CODES,
    FRESNEL_PARAMETERS,
    KD,
    SHADOWING_CODES,
    Model,
    Parameter,
    above_horizon,
    as_2d,
    combine,
    parallel_geometry,
)

__all__ = ["Lambert", "PhongFamily", "TorranceSparrow", "blinn_phong_normalization"]


class Lambert(Model):
    """f = kd/π (ρ = kd is the albedo; seed lecture "Diffuse BRDF")."""

    float32 = True

    def __init__(self, **options):
        if options:
            raise TypeError(f"lambert takes no options; got {sorted(options)}")
        super().__init__(
            "lambert",
            (KD,),
            {},
            {"reciprocal": True, "energy_conserving": True, "isotropic": True},
        )

    def _numpy(self, v, wi, wo, log):
        above = above_horizon(wi, wo)
        f = np.where(above, v["kd"] / np.pi, 0.0)
        if log:
            with np.errstate(divide="ignore"):
                return np.log(f)
        return f

    def _numba(self, v, wi, wo, log, out):
        # kd/π in out's precision: float32 halves the bytes of this store-bound loop
        kdpi = np.ascontiguousarray(np.divide(v["kd"], np.pi), dtype=out.dtype)
        lk.constant_above(kdpi, above_horizon(wi, wo), log, out)


_LOBES = {
    "phong": lk.LOBE_PHONG,
    "phong-normalized": lk.LOBE_PHONG_NORMALIZED,
    "blinn-phong": lk.LOBE_BLINN_PHONG,
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
        super().__init__(name, (KD, ks, Parameter("n", "1", 1.0, 1e6, log=True)), {}, flags)
        self._kind = _LOBES[name]

    def _base(self, wi, wo):
        if self._kind == lk.LOBE_BLINN_PHONG:
            s = wi + wo
            base = s[:, 2] / np.linalg.norm(s, axis=1)
        else:
            dot = wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1] + wi[:, 2] * wo[:, 2]
            base = 2.0 * (wi[:, 2] * wo[:, 2]) - dot  # l̂·r̂ with r̂ = 2(n̂·v̂)n̂ − v̂
        base = np.clip(base, 0.0, 1.0)
        return np.where(above_horizon(wi, wo), base, 0.0)

    def _log_norm(self, n):
        if self._kind == lk.LOBE_PHONG:
            return np.zeros_like(n)
        if self._kind == lk.LOBE_PHONG_NORMALIZED:
            return np.log((n + 2.0) / (2.0 * np.pi))
        return np.log(blinn_phong_normalization(n))

    def _numpy(self, v, wi, wo, log):
        kd, ks, n = v["kd"], v["ks"], v["n"]
        base = self._base(wi, wo)
        with np.errstate(divide="ignore", invalid="ignore"):
            # n·log(base) instead of base**n: exact for n up to 1e6 and no overflow in between.
            spec = np.log(ks) + self._log_norm(n) + n * np.log(base)
            spec = np.where((base > 0.0) & (ks > 0.0), spec, -np.inf)
        f = combine(kd, spec if log else np.exp(spec), log)
        return np.where(above_horizon(wi, wo), f, -np.inf if log else 0.0)

    def _numba(self, v, wi, wo, log, out):
        geo = lk.lobe_geometry(wi, wo, self._kind, parallel_geometry(out, "lobe"))
        cols = {k: v[k] for k in ("kd", "ks", "n")}
        per_sample = any(c.shape[1] != 1 for c in cols.values())
        if per_sample:  # one table row per (set, sample)
            flat = {k: np.broadcast_to(c, out.shape).ravel() for k, c in cols.items()}
        else:
            # fresh writable float64 copies (W values each): a read-only view would make numba
            # compile ts_parameter_table once more per combination of read-only inputs
            flat = {k: np.array(c[:, 0], dtype=np.float64) for k, c in cols.items()}
        table = lk.lobe_parameter_table(flat["kd"], flat["ks"], flat["n"], self._kind)
        lk.lobe(geo, table, per_sample, log, out)


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
            "distribution": _choice("distribution", distribution, DISTRIBUTION_CODES),
            "shadowing": _choice("shadowing", shadowing, SHADOWING_CODES),
            "fresnel": _choice("fresnel", fresnel, FRESNEL_CODES),
        }
        params = (
            KD,
            Parameter("ks", "1", 1e-6, 10.0, log=True),
            Parameter("m", "1", 1e-3, 2.0, log=True),
            *FRESNEL_PARAMETERS[fresnel],
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
        self._codes = (
            DISTRIBUTION_CODES[distribution],
            SHADOWING_CODES[shadowing],
            FRESNEL_CODES[fresnel],
        )

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
        cols["p1"] = as_2d(p1, *out.shape) if p1.ndim < 2 else p1
        cols["p2"] = as_2d(p2, *out.shape) if p2.ndim < 2 else p2
        geo = mk.microfacet_geometry(wi, wo, parallel_geometry(out, "ts"), out.dtype)
        if all(c.shape[1] == 1 for c in cols.values()):
            # fresh writable float64 copies (W values each): a read-only view would make numba
            # compile ts_parameter_table once more per combination of read-only inputs
            flat = {k: np.array(c[:, 0], dtype=np.float64) for k, c in cols.items()}
            kernel = mk.torrance_sparrow
        else:  # some parameter varies per sample: one table row per (set, sample)
            flat = {k: np.broadcast_to(c, out.shape).ravel() for k, c in cols.items()}
            kernel = mk.torrance_sparrow_per_sample
        dist, shadow, fres = self._codes
        table = mk.ts_parameter_table(
            flat["kd"], flat["ks"], flat["m"], flat["p1"], flat["p2"], dist
        )  # float64 (divisions and logs once per set), rounded once for a float32 output
        kernel(geo, table.astype(out.dtype, copy=False), dist, shadow, fres, log, out)

    def _numpy(self, v, wi, wo, log):
        opt = self.options
        kd, ks, m = v["kd"], v["ks"], v["m"]
        above = above_horizon(wi, wo)
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
            f = combine(kd, spec, True)
            return np.where(above, f, -np.inf)
        f = combine(kd, ks * d * g * fres, False)
        return np.where(above, f, 0.0)

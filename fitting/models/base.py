"""What every BRDF model shares (docs/design.md §3, §5): the :class:`Model` base with its evaluation
interface, :class:`Parameter`, and the helpers the model modules build on.

Every model returns f_r in sr⁻¹ (never f_r·cos θ_o), zero below the horizon (cos θ_i ≤ 0 or
cos θ_o ≤ 0), for direction pairs ``wi``, ``wo`` of shape (N, 3) (unit vectors in the sample
frame, both pointing away from the surface). Parameters are passed by name; scalars give shape
(N,), arrays of shape (W, 1) give (W, N) — W parameter sets such as MCMC walkers — and anything
else that broadcasts against (N,) or (W, N) is accepted too.

Two backends: ``backend="numba"`` (default; the fused kernels of
:mod:`fitting.models.microfacet_kernels` and :mod:`fitting.models.lobe_kernels`) and
``backend="numpy"`` (the reference written with :mod:`fitting.models.microfacet` and
:mod:`fitting.models.fresnel`, used to test the kernels).

Two precisions of the numba backend: float64 (default: least squares, whose finite-difference
steps of 1.5e-8 relative are below float32's resolution) and, for the models that have the
kernels (``Model.float32``: lambert, torrance-sparrow and its anisotropic twin),
``precision="float32"``: the same stages in single precision, about twice as fast (twice the
vector lanes, cheaper divides and square roots). Where the formulas are well conditioned the
values are within (64 + 3x) float32 ulps of float64 (x: Beckmann's exponent;
tests/fitting/test_float32_kernels.py); a conductor's Fresnel term for a noble metal and a
narrow anisotropic lobe lose more. The MCMC's likelihood uses float32 only where it measures
that rounding negligible beside the noise (:mod:`fitting.likelihood`). Per-sample parameters
and ``log_evaluate`` stay float64.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from fitting.models import microfacet_kernels as mk
from plumbing.numba_policy import prefers_threads

__all__ = [
    "PRECISIONS",
    "Parameter",
    "Model",
    "KD",
    "DISTRIBUTION_CODES",
    "SHADOWING_CODES",
    "FRESNEL_CODES",
    "FRESNEL_PARAMETERS",
    "as_directions",
    "as_2d",
    "flat_parameters",
    "parallel_geometry",
    "above_horizon",
    "combine",
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


KD = Parameter("kd", "1", 0.0, 1.0)


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
        wi, wo, single = as_directions(wi, wo)
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
            cols = {k: as_2d(v, rows, wi.shape[0]) for k, v in values.items()}
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


def as_directions(wi, wo):
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    single = wi.ndim == 1 and wo.ndim == 1
    wi, wo = np.broadcast_arrays(np.atleast_2d(wi), np.atleast_2d(wo))
    if wi.ndim != 2 or wi.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3); got {wi.shape}")
    return np.ascontiguousarray(wi), np.ascontiguousarray(wo), single


def as_2d(v: np.ndarray, rows: int, n: int) -> np.ndarray:
    """A parameter as a C-contiguous (rows, 1) or (rows, n) array for the kernels."""
    if v.ndim == 0:
        return np.full((rows, 1), float(v))
    if v.ndim == 1:
        v = v[None, :]
    cols = 1 if v.shape[1] == 1 else n
    return np.ascontiguousarray(np.broadcast_to(v, (rows, cols)), dtype=np.float64)


def flat_parameters(cols: Mapping, out: np.ndarray) -> tuple[dict[str, np.ndarray], bool]:
    """Parameter columns ((rows, 1), (rows, N) or scalars) → 1-D per-row arrays for a kernel's
    parameter table: one row per set if no column varies per sample, else one row per
    (set, sample), row w·N + j (second value True)."""
    rows, n = out.shape
    cols = {
        k: (as_2d(np.asarray(c, dtype=np.float64), rows, n) if np.ndim(c) < 2 else c)
        for k, c in cols.items()
    }
    # Fresh writable float64 copies: a read-only view (a broadcast, a caller's frozen array)
    # would make numba compile the kernel once more for each mix of read-only inputs.
    if any(c.shape[1] != 1 for c in cols.values()):
        return {k: np.array(np.broadcast_to(c, out.shape)).ravel() for k, c in cols.items()}, True
    return {k: np.array(c[:, 0], dtype=np.float64) for k, c in cols.items()}, False


def parallel_geometry(out: np.ndarray, kernel: str) -> bool:
    # The per-pair pass is worth threads when the kernel itself runs threaded and N is not tiny.
    return out.shape[1] >= 2048 and prefers_threads(kernel, out.size)


def above_horizon(wi, wo):
    return (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)


def combine(kd, spec, log):
    """kd/π + spec, or its log with spec given as log spec (log-sum-exp; −inf stays −inf)."""
    if not log:
        return kd / np.pi + spec
    with np.errstate(divide="ignore"):
        return np.logaddexp(np.log(kd / np.pi), spec)


DISTRIBUTION_CODES = {"beckmann": mk.DIST_BECKMANN, "ggx": mk.DIST_GGX}
SHADOWING_CODES = {
    "v-cavity": mk.SHADOW_VCAVITY,
    "smith": mk.SHADOW_SMITH,
    "smith-rational": mk.SHADOW_SMITH_RATIONAL,
    "smith-correlated": mk.SHADOW_SMITH_CORRELATED,
}
FRESNEL_CODES = {
    "dielectric": mk.FRESNEL_DIELECTRIC,
    "conductor": mk.FRESNEL_CONDUCTOR,
    "schlick": mk.FRESNEL_SCHLICK,
    "none": mk.FRESNEL_NONE,
}
FRESNEL_PARAMETERS = {
    "dielectric": (Parameter("ior", "1", 1.0, 4.0, default=1.5),),
    "conductor": (Parameter("eta", "1", 0.01, 10.0, log=True), Parameter("k", "1", 0.0, 100.0)),
    "schlick": (Parameter("f0", "1", 0.0, 1.0),),
    "none": (),
}

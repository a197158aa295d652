"""Parameter space and priors for BRDF fits (issue 7, docs/design.md §4 naming).

A model parameter ``p`` fitted per channel becomes ``p_CH`` (``kd_R``); a shared one keeps its
bare name (``m``). Parameters whose :class:`fitting.models.Parameter` has ``log=True`` are
*sampled* as ``u = ln p``. Their prior is log-uniform on [lower, upper], i.e.
π(p) ∝ 1/p, which is exactly uniform in u — so in the sampled space every prior here is flat on
a box and the log-prior is a constant (0) inside the box and −∞ outside. Uniform parameters
are sampled as themselves. The optional energy-conservation prior (directional albedo ≤ 1)
is a hook: a callable returning an extra log-prior per walker.

Priors file (TOML)::

    energy_conservation = false      # optional
    [parameters.m]                   # a bare model name applies to every channel
    lower = 0.01
    upper = 0.8
    [parameters.kd_R]                # or one fitted name
    upper = 0.9
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from plumbing.config import ConfigError, Strict, load_model
from plumbing.errors import UserError

__all__ = [
    "DISCREPANCY",
    "FRESNEL_PARAMETERS",
    "ParameterSpec",
    "ParameterSpace",
    "PriorBound",
    "PriorsConfig",
    "PriorsError",
    "load_priors",
    "albedo_prior",
]

#: Name, bounds of the fitted fractional model-discrepancy parameter s (σ_tot² = σ² + (s f)²).
DISCREPANCY = ("discrepancy", 1e-4, 1.0)
#: Model parameter names treated as Fresnel parameters (shared across channels by default).
FRESNEL_PARAMETERS = frozenset({"ior", "eta", "k", "f0", "F0", "eta_k"})


class PriorsError(UserError, ValueError):
    """A priors file or prior declaration is invalid. The message is one line."""


class PriorBound(Strict):
    """Bounds override for one parameter (natural units)."""

    lower: float | None = None
    upper: float | None = None


class PriorsConfig(Strict):
    """Contents of a priors TOML file."""

    energy_conservation: bool = False
    parameters: dict[str, PriorBound] = {}


def load_priors(path: str | os.PathLike) -> PriorsConfig:
    """Read a priors file (TOML or JSON: data only); raises PriorsError with a one-line reason
    naming the file, the key and what is allowed (plumbing.config)."""
    try:
        return load_model(path, PriorsConfig, PriorsError)
    except ConfigError as exc:  # missing, unreadable or not TOML: the same line, as PriorsError
        raise PriorsError(str(exc)) from None


@dataclass(frozen=True)
class ParameterSpec:
    """One fitted parameter: ``name`` (e.g. kd_R), the model parameter ``base`` (kd) and the
    ``channel`` it applies to (None when shared). Bounds are natural units."""

    name: str
    base: str
    channel: str | None
    unit: str
    lower: float
    upper: float
    log: bool
    #: A nuisance parameter's Gaussian prior σ and centre in the sampled space (ln s for a
    #: scale, degrees for an angle; fitting.nuisance); None: the flat box prior.
    prior_sigma: float | None = None
    prior_center: float = 0.0

    @property
    def internal_bounds(self) -> tuple[float, float]:
        if self.log:
            return math.log(self.lower), math.log(self.upper)
        return self.lower, self.upper


def _fixed_value(key: str, raw, lower: float, upper: float, what: str) -> float:
    """A --fix value: finite and inside [lower, upper], the parameter's own range (the model
    is undefined or unphysical outside it, and an export or report would carry the value on).
    `what` names the range in the message."""
    try:
        value = float(raw)
    except (TypeError, ValueError):
        raise PriorsError(f"--fix {key}={raw!r}: not a number") from None
    if not (math.isfinite(value) and lower <= value <= upper):
        raise PriorsError(f"--fix {key}={raw}: outside {what} [{lower:g}, {upper:g}]")
    return value


@dataclass
class ParameterSpace:
    """Flat parameter vector θ (sampled space) ↔ named natural-unit parameters.

    ``fixed`` holds natural values of parameters held fixed, keyed by fitted name (``kd_R`` or
    ``m``); they are not part of θ. ``specs`` must not change after construction (bounds are
    cached).
    """

    specs: tuple[ParameterSpec, ...]
    model_parameters: tuple[str, ...]
    channels: tuple[str, ...]
    shared: frozenset[str]
    fixed: dict[str, float] = field(default_factory=dict)
    energy_prior: Callable[[Mapping[str, np.ndarray]], np.ndarray] | None = None
    #: The shared errors carried as nuisance parameters (fitting.nuisance.SharedErrors).
    shared_errors: object | None = None

    @classmethod
    def build(
        cls,
        model,
        channels: Sequence[str],
        *,
        shared: Sequence[str] | None = None,
        fix: Mapping[str, float] | None = None,
        priors: PriorsConfig | None = None,
        discrepancy: bool = False,
    ) -> ParameterSpace:
        """Parameters of ``model`` for ``channels``; ``shared=None`` means m + Fresnel params."""
        names = tuple(p.name for p in model.parameters)
        if shared is None:
            shared = [n for n in names if n == "m" or n in FRESNEL_PARAMETERS]
        shared_set = frozenset(shared)
        unknown = shared_set - set(names)
        if unknown:
            raise PriorsError(
                f"--shared {', '.join(sorted(unknown))}: not a parameter of {model.name} "
                f"(parameters: {', '.join(names)})"
            )
        fix = dict(fix or {})
        overrides = dict(priors.parameters) if priors is not None else {}
        specs: list[ParameterSpec] = []
        fixed: dict[str, float] = {}
        known: set[str] = set(names)
        for p in model.parameters:
            targets = (
                [(p.name, None)]
                if p.name in shared_set
                else [(f"{p.name}_{c}", c) for c in channels]
            )
            for fitted, ch in targets:
                known.add(fitted)
                lower, upper = float(p.lower), float(p.upper)
                for key in (p.name, fitted):  # the specific name overrides the bare one
                    if key in overrides:
                        b = overrides[key]
                        lower = lower if b.lower is None else float(b.lower)
                        upper = upper if b.upper is None else float(b.upper)
                if key_fixed := next((k for k in (fitted, p.name) if k in fix), None):
                    fixed[fitted] = _fixed_value(
                        key_fixed, fix[key_fixed], p.lower, p.upper, f"{p.name}'s range"
                    )
                    continue
                if not lower < upper:
                    raise PriorsError(f"prior for {fitted}: lower {lower} must be below {upper}")
                if not p.lower <= lower < upper <= p.upper:
                    # The model's range is where it is defined and evaluated safely (kd < 0
                    # gives negative f, m ≤ 0 a division by zero): a prior narrows it.
                    raise PriorsError(
                        f"prior for {fitted}: [{lower:g}, {upper:g}] is outside {p.name}'s range "
                        f"[{p.lower:g}, {p.upper:g}]; a prior may narrow that range, not widen it"
                    )
                if p.log and lower <= 0:
                    raise PriorsError(
                        f"prior for {fitted}: log-uniform needs lower > 0, got {lower}"
                    )
                specs.append(ParameterSpec(fitted, p.name, ch, p.unit, lower, upper, p.log))
        if discrepancy:
            name, lo, hi = DISCREPANCY
            if name in fix:
                # 0 (no model error) is allowed although the sampled prior starts at lo > 0.
                fixed[name] = _fixed_value(name, fix[name], 0.0, hi, "the discrepancy's range")
            else:
                specs.append(ParameterSpec(name, name, None, "1", lo, hi, True))
            known.add(name)
        bad = (set(fix) | set(overrides)) - known
        if bad:
            raise PriorsError(
                f"unknown parameter(s) {', '.join(sorted(bad))} for {model.name} "
                f"(known: {', '.join(sorted(known))})"
            )
        return cls(tuple(specs), names, tuple(channels), shared_set, fixed)

    # -- vector <-> names --------------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return [s.name for s in self.specs]

    @property
    def ndim(self) -> int:
        return len(self.specs)

    @cached_property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of θ in the sampled (internal) space."""
        b = np.array([s.internal_bounds for s in self.specs], dtype=np.float64).reshape(-1, 2)
        return b[:, 0], b[:, 1]

    @cached_property
    def _gaussian(self) -> list[int]:
        """Indices of the nuisance parameters (Gaussian prior)."""
        return [i for i, s in enumerate(self.specs) if s.prior_sigma is not None]

    @cached_property
    def is_log(self) -> np.ndarray:
        return np.array([s.log for s in self.specs], dtype=bool)

    def to_natural(self, theta: np.ndarray) -> np.ndarray:
        """θ (..., D) in the sampled space → natural units (exp of the log parameters)."""
        theta = np.asarray(theta, dtype=np.float64)
        with np.errstate(over="ignore"):
            return np.where(self.is_log, np.exp(theta), theta)

    def to_internal(self, values: np.ndarray) -> np.ndarray:
        values = np.asarray(values, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.is_log, np.log(values), values)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def natural_dict(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        """θ (W, D) → {fitted name: (W,) natural values} including fixed ones."""
        nat = self.to_natural(np.atleast_2d(theta))
        out = {s.name: nat[:, i] for i, s in enumerate(self.specs)}
        for k, v in self.fixed.items():
            out[k] = np.full(nat.shape[0], v)
        return out

    def channel_params(self, natural: Mapping[str, np.ndarray], channel: str) -> dict:
        """Model parameters for one channel, each of shape (W, 1) for broadcasting over samples."""
        out = {}
        for base in self.model_parameters:
            key = base if base in self.shared else f"{base}_{channel}"
            out[base] = np.asarray(natural[key], dtype=np.float64)[:, None]
        return out

    def discrepancy(self, natural: Mapping[str, np.ndarray]) -> np.ndarray | None:
        return natural.get(DISCREPANCY[0])

    # -- prior --------------------------------------------------------------------------------
    def log_prior(self, theta: np.ndarray) -> np.ndarray:
        """ln π(θ) up to a constant, (W,): 0 inside the box (flat in the sampled space — which
        is log-uniform for log parameters), −∞ outside or where θ is not finite; plus the
        energy-prior hook when set."""
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        lo, hi = self.bounds
        inside = np.all(np.isfinite(theta) & (theta >= lo) & (theta <= hi), axis=1)
        lp = np.where(inside, 0.0, -np.inf)
        for i in self._gaussian:
            spec = self.specs[i]
            lp -= 0.5 * ((theta[:, i] - spec.prior_center) / spec.prior_sigma) ** 2
        if self.energy_prior is not None and inside.any():
            extra = np.asarray(self.energy_prior(self.natural_dict(theta[inside])), float)
            lp[inside] += np.where(np.isfinite(extra), extra, -np.inf)
        return lp


def albedo_prior(
    model, space: ParameterSpace, *, n_theta: int = 6, n_grid: int = 24, tolerance: float = 1e-3
) -> Callable[[Mapping[str, np.ndarray]], np.ndarray]:
    """Energy-conservation prior: −∞ where the directional albedo exceeds 1 + tolerance.

    a(ω_i) = ∫_Ω f_r(ω_i, ω_o) cos θ_o dω_o  (sr⁻¹ · sr = 1), estimated with a fixed midpoint
    rule in (cos²θ_o, φ_o) — with u = cos²θ_o, cos θ_o dω_o = ½ du dφ — at ``n_theta`` incidence
    angles up to 80°. A midpoint rule underestimates sharp lobes, so this is a soft check for
    the diffuse + rough part, not a proof of energy conservation for m → 0.
    """
    u = (np.arange(n_grid) + 0.5) / n_grid
    phi = (np.arange(2 * n_grid) + 0.5) / (2 * n_grid) * 2 * np.pi
    uu, pp = np.meshgrid(u, phi, indexing="ij")
    ct = np.sqrt(uu.ravel())
    st = np.sqrt(1 - uu.ravel())
    wo = np.stack([st * np.cos(pp.ravel()), st * np.sin(pp.ravel()), ct], axis=1)
    weight = 0.5 * (1.0 / n_grid) * (2 * np.pi / (2 * n_grid))
    thetas = np.linspace(0.0, np.radians(80.0), n_theta)
    wis = [np.tile([np.sin(t), 0.0, np.cos(t)], (wo.shape[0], 1)) for t in thetas]

    def log_prior(natural: Mapping[str, np.ndarray]) -> np.ndarray:
        n = next(iter(natural.values())).shape[0]
        ok = np.ones(n, dtype=bool)
        for ch in space.channels:
            params = space.channel_params(natural, ch)
            for wi in wis:
                with np.errstate(all="ignore"):
                    a = np.sum(model.evaluate(params, wi, wo), axis=-1) * weight
                ok &= np.isfinite(a) & (a <= 1 + tolerance)
        return np.where(ok, 0.0, -np.inf)

    return log_prior

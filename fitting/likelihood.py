"""Log-likelihood of a BRDF model given a sample table, vectorised over emcee walkers.

Model (per sample j, channel c; f̂ = model f_r, f the measurement, σ its 1-σ error):

* Gaussian: ln L = Σ_j −½ [ r_j²/v_j + ln(2π v_j) ],  r = f − f̂,
  v_j = σ_j² + (s f̃_j)², where s ≥ 0 is the optional fitted fractional model discrepancy
  (real materials never follow a model exactly; without s the posterior is overconfident).
  f̃_j is the value the model error is a fraction of. By default it is the prediction f̂_j(θ);
  `frozen_at(θ₀)` gives the likelihood with it frozen at f̂_j(θ₀) (fit_samples uses the
  least-squares optimum). Why freeze: with f̂(θ) in v, over-predicting a sample costs at most
  ≈ 1/(2s²) + ln f̂ while under-predicting costs without bound, so a mismatched model learns to
  overshoot wherever few samples sit (the real-materials study found held-out errors of
  1000s of % from that). Why not the measured f_j: σ would then correlate with each sample's
  noise, and a weighted fit biases low (coverage of m fell to 0.87 at 95 %). A frozen, smooth
  f̃ avoids both: the penalty is quadratic both ways and independent of the noise.
* Student-t (``kind="student-t"``, fixed ν): ln L = Σ_j ln Γ((ν+1)/2) − ln Γ(ν/2)
  − ½ ln(ν π v_j) − (ν+1)/2 · ln(1 + r_j²/(ν v_j)); the same scale v_j as above.
* Saturated (flags & 1) and dark (flags & 2) samples are censored observations by default
  (``censor=True``; issue 18: dropping them biased kd and m of a dark-background metal, whose
  samples were 70 % dark; ``censor=False`` excludes them) — the Tobit likelihood. A saturated
  reading f is the clip level, so the truth is *above* it: ln P(Y > f) = ln Φ((f̂ − f)/√v).
  A dark sample is one whose reading fell below the detection limit c = dark_snr·σ (the
  calibration's rule, ``ReduceOptions.min_snr``, 3 by default and recorded in the samples'
  metadata): it contributes ln P(Y < c) = ln Φ((c − f̂)/√v), c = max(f, dark_snr·σ). Why c and
  not the reading: a reading flagged *because* it is low is a noisy value selected for being
  low; bounding the truth by it (P(Y < f)) biases f̂ low — on the dark-conductor test scene
  the kd interval then missed the truth on 8 of 8 seeds and m came out +4 sd. P(Y < c) is the
  exact probability of the flag under the noise model, so the censored likelihood is exact.
  Φ is evaluated as scipy.special.log_ndtr, which stays accurate far in the tail
  (ln Φ(−40) ≈ −804, not −∞). Censored terms use the Gaussian even in Student-t mode
  (documented simplification).
* Samples flagged below-horizon or masked (flags & 12), and rows with non-finite f or σ or
  σ ≤ 0, never enter; a value below zero (flagged 16 or not) enters as the measurement it is
  — the Gaussian is defined there, and leaving such values out selects the high draws of a
  dark part. The flags' roles are ``brdfdata.samples.FLAG_ROLES``, which the binned path, the
  verdicts and the report read too.

The result is finite or −∞, never NaN: −∞ outside the prior support or where the model is not
finite for any used sample.

Precision: the model is evaluated in float64 unless ``precision`` is set to "float32"
(:meth:`Likelihood.choose_precision`, which the MCMC calls; least squares stays float64, its
finite-difference steps being below float32's resolution). The sums are float64 either way.
float32 rounds f̂_j by a few float32 ulps (6e-8) where the model is well conditioned, by more
where it is not (a conductor's Fresnel term subtracts nearly equal numbers for a noble metal;
an anisotropic lobe's rotation by φ₀ cancels for a narrow α: up to ~5e-4 relative at the
priors' edges), and a change δ_j of f̂_j moves ln L by ≈ Σ_j z_j δ_j/σ_j (z_j = r_j/√v_j). So
no fixed bound decides: :meth:`choose_precision` evaluates ln L in both precisions at points
where the sampler will go (the least-squares optimum and draws of its Laplace approximation)
and takes float32 only if they differ by less than F32_LNL_LIMIT = 0.01 everywhere there (a 1 %
change of a Metropolis acceptance ratio); many precise rows or an ill-conditioned material
stay float64.
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.special import gammaln, log_ndtr

from brdfdata.directions import normalize, spherical_to_vector
from brdfdata.samples import DARK_SNR, SampleTable, row_kinds
from fitting.likelihood_kernels import gauss_discrepancy_sum
from fitting.nuisance import ANGLE_NUISANCES, arm_deltas, arm_rows, measured_geometry, to_si
from fitting.priors import ParameterSpace
from plumbing.errors import UserError

__all__ = [
    "NoUsableSamples",
    "ChannelData",
    "Likelihood",
    "LIKELIHOOD_KINDS",
    "F32_LNL_LIMIT",
]


class NoUsableSamples(UserError, ValueError):
    """A table with no row a fit can use (every row masked, below the horizon or not finite)."""


LIKELIHOOD_KINDS = ("gaussian", "student-t")

#: The largest change of ln L from float32 rounding the MCMC accepts (module docstring).
F32_LNL_LIMIT = 0.01


_LN_2PI = float(np.log(2 * np.pi))
#: Model values held at once by one likelihood pass: walkers × rows. A batch of θ is split
#: into passes of at most this many (W, N) elements, so every temporary of a pass is ≤ 32 MB
#: whatever the table's size: 32 walkers over 10⁶ rows would otherwise hold 256 MB per array
#: (the sandwich's 73-point stencil, 584 MB), several at once. Each pass is still millions of
#: elements, so the kernels' per-call cost stays negligible.
PASS_ELEMENTS = 4_000_000


@dataclass(frozen=True)
class ChannelData:
    """The samples of one channel, split into exact (``f``) and censored rows."""

    channel: str
    wi: np.ndarray  # (N, 3)
    wo: np.ndarray  # (N, 3)
    f: np.ndarray  # (N,)
    sigma: np.ndarray  # (N,)
    theta_i: np.ndarray
    theta_o: np.ndarray
    kind: np.ndarray  # (N,) int8: 0 exact, 1 saturated (censored above), 2 dark (censored below)
    #: Rows a censored sample stands for (a bin of fitting.binning; 1 for exact rows, whose
    #: bin is already one sample of the combined σ); None: every row is one observation.
    weight: np.ndarray | None = None
    #: Per row, what the arm-angle nuisances need (fitting.nuisance.arm_rows).
    arm: dict | None = None
    #: The capture (pose) each row was measured in, or None: rows of one pose share its angle
    #: errors, the clusters of the mismatch sandwich (fitting.mismatch).
    cluster: np.ndarray | None = None
    #: Per row, the lamp's extent: the model averaged over the lamp's disk over the model at
    #: its centre, frozen at θ₀ (Likelihood.frozen_at); None: a point lamp.
    lamp: np.ndarray | None = None

    def censored_sum(self, terms: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Σ of (W, n) ``terms`` of the ``mask`` rows (n = mask.sum()), each weighted by its
        row count."""
        if self.weight is None:
            return terms.sum(axis=1)
        return terms @ self.weight[mask]

    @property
    def exact(self) -> np.ndarray:
        return self.kind == 0

    @cached_property
    def sigma2(self) -> np.ndarray:
        return np.ascontiguousarray(self.sigma**2)


def _weighted(d: ChannelData, fm: np.ndarray, weighting: str) -> np.ndarray:
    """Residuals (W, n) of ``d``'s exact rows for their model values ``fm`` (W, n).

    ``sigma``: r = (f − f̂)/σ.  ``ngan``: Ngan et al. 2005's metric (docs/design.md §6) — plain L2 on
    f·cos θ_i weighted by sin θ_i sin θ_o, i.e. r = √(sin θ_i sin θ_o) · (f − f̂) cos θ_i."""
    ex = d.exact
    diff = d.f[ex] - fm
    if weighting == "sigma":
        return diff / d.sigma[ex]
    if weighting == "ngan":
        w = np.sqrt(np.abs(np.sin(d.theta_i[ex]) * np.sin(d.theta_o[ex])))
        return w * diff * np.cos(d.theta_i[ex])
    raise ValueError(f"weighting {weighting!r}: use 'sigma' or 'ngan'")


class Likelihood:
    """ln p(θ | data) = ln π(θ) + ln L(θ), callable on θ of shape (W, D) → (W,) or (D,) → float.

    The model is evaluated once per channel per call with parameters of shape (W, 1).
    """

    def __init__(
        self,
        model,
        table: SampleTable,
        space: ParameterSpace,
        *,
        kind: str = "gaussian",
        nu: float = 4.0,
        censor: bool = True,
        channels: Sequence[str] | None = None,
        dark_snr: float = DARK_SNR,
    ) -> None:
        if kind not in LIKELIHOOD_KINDS:
            raise ValueError(f"likelihood {kind!r}: use one of {', '.join(LIKELIHOOD_KINDS)}")
        if not nu > 0:
            raise ValueError(f"Student-t ν must be > 0, got {nu}")
        self.model = model
        self.space = space
        self.kind = kind
        self.nu = float(nu)
        self.censor = bool(censor)
        self.dark_snr = float(dark_snr)
        channels = list(channels if channels is not None else space.channels)
        kinds = row_kinds(table)  # FLAG_ROLES: the one reading of the flags
        usable, sat, dark = kinds.usable.copy(), kinds.saturated, kinds.dark
        in_channels = np.isin(table.channel, channels)
        # Counted whether or not they enter, so a fit can say what it did with them.
        self.n_saturated = int(np.sum(usable & in_channels & sat))
        self.n_dark = int(np.sum(usable & in_channels & dark))
        self.n_considered = int(np.sum(usable & in_channels))
        if not self.censor:
            usable &= ~sat & ~dark
        self.data: list[ChannelData] = []
        self._geometry_memo: dict[int, tuple] = {}  # _geometry: the last shifts and result
        # A dark row's value becomes its censoring bound, the detection limit (module docstring).
        f_all = np.asarray(table.f, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            f_all = np.where(dark, np.maximum(f_all, float(dark_snr) * table.sigma), f_all)
        counts = table.extra.get("n_rows")
        # the arms' pose per row only for a fit that carries their angles (fitting.nuisance)
        shared = space.shared_errors
        arm = (
            arm_rows(table, shared.bow_half_side_m, shared.flat_field)
            if shared is not None and shared.angle_sigma_deg
            # the lamp's extent needs each row's point on the sample (its emission angle)
            else arm_rows(table)
            if _lamp_cone(table.metadata) is not None
            else None
        )
        captures = table.extra.get("capture_id")
        for ch in channels:
            sel = usable & (table.channel == ch)
            kind_arr = np.where(sat[sel], 1, np.where(dark[sel], 2, 0)).astype(np.int8)
            weight = (
                None
                if counts is None
                else np.where(kind_arr == 0, 1.0, np.asarray(counts[sel], dtype=np.float64))
            )
            self.data.append(
                ChannelData(
                    ch,
                    # per channel, not table.wi[sel]: no n × 3 temporaries of every row
                    spherical_to_vector(table.theta_i[sel], table.phi_i[sel]),
                    spherical_to_vector(table.theta_o[sel], table.phi_o[sel]),
                    f_all[sel],
                    np.asarray(table.sigma[sel], dtype=np.float64),
                    np.asarray(table.theta_i[sel], dtype=np.float64),
                    np.asarray(table.theta_o[sel], dtype=np.float64),
                    kind_arr,
                    weight,
                    None
                    if arm is None
                    else {k: np.ascontiguousarray(v[sel]) for k, v in arm.items()},
                    None if captures is None else np.asarray(captures[sel], dtype=np.int64),
                )
            )
        if shared is not None and shared.ambient_intensity:
            for d in self.data:
                _ambient_rows(d, shared.ambient_intensity)
        self.n = int(sum(d.f.size for d in self.data))
        if self.n == 0:
            raise NoUsableSamples(
                "no usable samples to fit: every row is flagged MASKED or BELOW_HORIZON, or not "
                "finite — check the table's flags column (gonio calibrate sets it)"
            )
        self._f_ref: list[np.ndarray] | None = None  # discrepancy reference f̃, per channel
        self._lamp_cone = _lamp_cone(table.metadata)  # the lamp disk's angular radius, or None
        self._lamp: list[np.ndarray] | None = None  # its per-row factor, frozen (frozen_at)
        #: The model's precision in :meth:`predict` ("float64", or "float32": choose_precision).
        self.precision = "float64"
        self.precision_reason = "float64 by default"
        self._angle_ref: tuple | None = None  # arm-zero linearisation (frozen_at)
        # Constant of the Student-t density, precomputed once.
        self._t_const = float(
            gammaln((self.nu + 1) / 2) - gammaln(self.nu / 2) - 0.5 * np.log(self.nu * np.pi)
        )

    # -- model ----------------------------------------------------------------------------------
    def choose_precision(self, probes: np.ndarray) -> tuple[str, float]:
        """Use float32 for the model if it has the kernels for it and ln L in float32 differs
        from float64 by less than F32_LNL_LIMIT at every one of ``probes`` (K, D), points in the
        sampled space where the sampler will go; else float64. Returns (the choice, the largest
        difference: NaN for a model without float32 kernels, inf where float32 changes which
        points have a finite ln L or none has) and sets ``precision`` and ``precision_reason``
        (one line, for the fit's diagnostics and the report)."""
        self.precision = "float64"
        if not getattr(self.model, "float32", False):
            self.precision_reason = f"{self.model.name} has no float32 kernels"
            return self.precision, float("nan")
        probes = np.atleast_2d(np.asarray(probes, dtype=np.float64))
        try:
            ll64 = self.log_likelihood(probes)
            self.precision = "float32"
            ll32 = self.log_likelihood(probes)
        finally:
            self.precision = "float64"
        ok = np.isfinite(ll64)
        n = len(probes)
        if not ok.any():
            self.precision_reason = f"ln L is not finite at any of the {n} points checked"
            return self.precision, float("inf")
        if not np.array_equal(ok, np.isfinite(ll32)):
            self.precision_reason = f"float32 changed which of the {n} points checked are finite"
            return self.precision, float("inf")
        diff = float(np.max(np.abs(ll32[ok] - ll64[ok])))
        if diff < F32_LNL_LIMIT:
            self.precision = "float32"
            self.precision_reason = f"ln L within {diff:.1g} of float64 at the {n} points checked"
        else:
            self.precision_reason = (
                f"float32 would move ln L by {diff:.2g} ≥ {F32_LNL_LIMIT} (many or precise rows)"
            )
        return self.precision, diff

    @contextmanager
    def sampling_precision(self, probes: np.ndarray) -> Iterator[tuple[str, float]]:
        """``choose_precision(probes)`` for the block (a sampler's run), float64 again after it
        whatever happens: yields (the choice, the largest difference)."""
        try:
            yield self.choose_precision(probes)
        finally:
            self.precision = "float64"

    def frozen_at(self, theta: np.ndarray, *, angles: bool = True) -> Likelihood:
        """This likelihood with its references frozen at θ₀ (D,), as a fit samples it: the
        discrepancy's reference f̃ at the model's prediction there, then (``angles``) the arms'
        zero errors linearised about θ₀'s. A new object; this one is unchanged (its f̃ stays the
        prediction f̂(θ), the arms exact)."""
        frozen = copy.copy(self)
        frozen._freeze_lamp(theta)
        frozen._freeze_discrepancy(theta)
        if angles:
            frozen._freeze_angles(theta)
        return frozen

    @property
    def discrepancy_reference(self) -> list[np.ndarray] | None:
        """The frozen f̃ per channel (each (N_c,)), or None when f̃ is the prediction itself."""
        return self._f_ref

    def _freeze_lamp(self, theta: np.ndarray) -> None:
        """The lamp's extent (metadata ``gonio.lamp``: the rig's lamp radius r and distance d):
        a Lambertian disk facing the sample lights each point from a cone of half-angle
        a = r/d, and calibration divides by the irradiance of a point lamp at its centre, so the
        measured f is the disk average of f(ω', ω_o) cos θ' over f's centre value's
        cos θ_c, times the disk's emission cos α toward the row's point p (the disk faces the
        sample's centre: a point x off it sees the lamp at α ≈ x/d, 0.13 % dimmer at the edge of
        a 50 mm sample at 0.5 m, which an isotropic point lamp's calibration does not know;
        with the arms' positions, else α = 0). Per row,
        c = cos α Σ_k w_k f(ω_k, ω_o) cos θ_k / (f(ω_c, ω_o) cos θ_c) over Radon's
        7-point disk rule (centre ¼, six points at radius √(2/3) a, ⅛ each: exact for degree
        5 over the disk), ω_k = ω_c + a (u_k e₁ + v_k e₂) normalised, e₁, e₂ ⊥ ω_c. Frozen at θ₀
        like the discrepancy's reference: c depends on θ only through the lobe's curvature,
        whose change over a posterior's width moves c by far less than c − 1 (≲ 1e-3 here).
        Why: a 5 mm lamp at 0.5 m (a = 0.01 rad) broadened a Beckmann lobe of m = 0.2 enough to
        put m's error at +0.47 of its half-width on average over 30 realistic rigs, and the
        mismatch widening then made its intervals too wide (sd of error/half-width 0.78); with a
        point lamp, +0.13 and 1.03 (docs/simulator.md)."""
        if self._lamp_cone is None:
            return
        x0 = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        natural = self.space.natural_dict(x0)
        factors = []
        for d in self.data:
            p0 = self.space.channel_params(natural, d.channel)
            e1, e2 = _perpendicular_basis(d.wi)
            with np.errstate(all="ignore"):
                f0 = np.asarray(self.model.evaluate(p0, d.wi, d.wo), float).reshape(-1)
                total = np.zeros(d.wi.shape[0])
                for u, v, weight in _DISK_RULE:
                    wk = normalize(d.wi + self._lamp_cone * (u * e1 + v * e2))
                    fk = np.asarray(self.model.evaluate(p0, wk, d.wo), float).reshape(-1)
                    total += weight * fk * wk[:, 2]
                c = total / (f0 * d.wi[:, 2]) * _emission_cos(d)
            factors.append(np.where(np.isfinite(c) & (c > 0), c, 1.0))
        self._lamp = factors

    def _freeze_discrepancy(self, theta: np.ndarray) -> None:
        """Freeze the discrepancy's reference f̃ at the model's prediction for θ (D,). Where the
        model is not finite there, the measured |f| is used."""
        fms = self.predict(np.atleast_2d(np.asarray(theta, dtype=np.float64)))
        self._f_ref = [
            np.where(np.isfinite(fm[0]), np.abs(fm[0]), np.abs(d.f))
            for d, fm in zip(self.data, fms, strict=True)
        ]

    def _scale_ref(self, i: int, fm: np.ndarray) -> np.ndarray:
        """f̃ for channel i: frozen (N,) or the prediction (W, N)."""
        return fm if self._f_ref is None else self._f_ref[i]

    def predict(
        self, theta: np.ndarray, data: Sequence[ChannelData] | None = None
    ) -> list[np.ndarray]:
        """Model values per channel, each (W, N_c), for θ (W, D) in the sampled space; of
        ``data`` (blocks of rows, :meth:`exact_blocks`) instead of every row when given."""
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        natural = self.space.natural_dict(theta)
        angles = {n: to_si(n, natural[n]) for n in ANGLE_NUISANCES if n in natural}
        out = []
        for i, d in enumerate(self.data if data is None else data):
            params = self.space.channel_params(natural, d.channel)
            linear = angles and self._angle_ref is not None and data is None
            shifts = arm_deltas(d.arm, angles) if angles and not linear else {}
            with np.errstate(all="ignore"):
                if linear:
                    fm = self._evaluate_linearised(i, params, angles)
                elif any(np.any(v != 0) for v in shifts.values()):
                    fm = self._evaluate_shifted(d, params, shifts)
                else:  # the arms where they were recorded
                    fm = self.model.evaluate(params, d.wi, d.wo, precision=self.precision)
            # float32 stays float32 (each consumer sums in float64; no converted copy)
            fm = np.asarray(fm)
            if fm.dtype != np.float32:
                fm = fm.astype(np.float64, copy=False)
            fm = np.broadcast_to(fm, (theta.shape[0], d.f.size))
            lamp = d.lamp if data is not None else (self._lamp[i] if self._lamp else None)
            if lamp is not None:
                fm = fm * lamp.astype(fm.dtype, copy=False)
            falloff = natural.get("flat_falloff_pct")
            if falloff is not None and d.arm is not None and "field_r2" in d.arm:
                # the flat source's profile the master flat divided in (fitting.nuisance)
                fm = fm / (1.0 - to_si("flat_falloff_pct", falloff)[:, None] * d.arm["field_r2"])
            scale = natural.get(f"scale_{d.channel}")
            fm = fm if scale is None else fm * scale[:, None]
            bend = natural.get("linearity_pct")
            if bend is not None and d.arm is not None and "bend_level" in d.arm:
                # the camera's bend calibration left in: 1 + b · level (calibration.linearity)
                fm = fm * (1.0 + to_si("linearity_pct", bend)[:, None] * d.arm["bend_level"])
            ambient = natural.get("ambient_mW")
            if ambient is not None and d.arm is not None and "ambient_per_W" in d.arm:
                # light the lamp does not cause, divided by the lamp's irradiance (nuisance)
                fm = fm + to_si("ambient_mW", ambient)[:, None] * d.arm["ambient_per_W"]
            out.append(fm)
        return out

    def _freeze_angles(self, theta: np.ndarray) -> None:
        """Linearise the arms' zero errors about θ₀'s (the MCMC's hot path).

        f(p, δ) = f(p, δ₀) · (1 + Σ_k (δ_k − δ₀_k) ∂ln f/∂δ_k), the log-derivatives taken
        once at (p₀, δ₀) by central differences. Each arm's δ_k per row is linear in the angle
        nuisances ν (fitting.nuisance.arm_deltas), so the sum is (ν − ν₀) · G per row with
        G_ν = Σ_k ∂δ_k/∂ν ∂ln f/∂δ_k, also taken once: one matrix product per call of the
        chain instead of the arms' per-row sums (about a quarter of a realistic fit's chain,
        measured). Exact at δ₀ and, the model being smooth in the angles, off by
        ½ ∂²f/∂δ² Δδ² + ∂²ln f/∂δ∂p Δδ Δp: with Δδ a posterior's width around a least-squares
        δ₀ (≈ 0.01°, at most the prior's 0.2–0.3°) and a lobe of width m, of relative size
        Δδ²/m² ≤ 1e-4 at m = 0.05 — far below a sample's noise."""
        x0 = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        natural = self.space.natural_dict(x0)
        angles = {n: to_si(n, natural[n]) for n in ANGLE_NUISANCES if n in natural}
        if not angles:
            self._angle_ref = None
            return
        kin = getattr(self.space.shared_errors, "kinematics", "two-arm")
        h = np.radians(1e-3)  # 0.001°: central differences, truncation ~h², rounding ~ε/h
        ref = []
        for d in self.data:
            p0 = self.space.channel_params(natural, d.channel)
            delta0 = {a: v[0] for a, v in arm_deltas(d.arm, angles).items()}  # (N,) per arm
            with np.errstate(all="ignore"):
                wi0, wo0, ratio0 = measured_geometry(d.wi, d.wo, d.arm, delta0, kin)
                f0 = np.asarray(self.model.evaluate(p0, wi0, wo0), float).reshape(-1) * ratio0
                grads = {}
                for arm in delta0:
                    fs = []
                    # 10 µm for the lamp's and the camera's distance
                    step = 1e-5 if arm in ("light_r", "camera_r") else h
                    for sign in (1.0, -1.0):
                        dd = dict(delta0, **{arm: delta0[arm] + sign * step})
                        wi, wo, ratio = measured_geometry(d.wi, d.wo, d.arm, dd, kin)
                        f = np.asarray(self.model.evaluate(p0, wi, wo), float).reshape(-1)
                        fs.append(f * ratio)
                    g = (fs[0] - fs[1]) / (2 * step) / f0
                    grads[arm] = np.where(np.isfinite(g), g, 0.0)
            gain = np.zeros((len(angles), d.f.size))  # G (n_ν, N): ln f per unit of each ν
            for j, name in enumerate(angles):
                for arm, per_unit in arm_deltas(d.arm, {name: np.ones(1)}).items():
                    gain[j] += per_unit[0] * grads[arm]
            nu0 = np.array([v[0] for v in angles.values()])
            ref.append((wi0, wo0, ratio0, gain, nu0))
        self._angle_ref = ref

    def _evaluate_linearised(self, i: int, params: dict, angles: dict) -> np.ndarray:
        """The model at the arms' frozen directions, times 1 + (ν − ν₀) · G (_freeze_angles)
        for the angle nuisances `angles` {name: (W,) SI}, in _freeze_angles' order."""
        wi0, wo0, ratio0, gain, nu0 = self._angle_ref[i]
        fm = self.model.evaluate(params, wi0, wo0, precision=self.precision) * ratio0
        nu = np.stack([np.asarray(v, dtype=np.float64) for v in angles.values()], axis=-1)
        return fm * (1.0 + (nu - nu0) @ gain)

    def _evaluate_shifted(self, d: ChannelData, params: dict, shifts: dict) -> np.ndarray:
        """The model per walker at the directions its arm-zero nuisances give (W, N): one
        kernel call over the W·N direction pairs, each row with its walker's parameters."""
        kin = getattr(self.space.shared_errors, "kinematics", "two-arm")
        n_walkers = next(iter(shifts.values())).shape[0]
        wi, wo, ratio = self._geometry(d, shifts, kin)
        n = d.f.size
        wi = np.broadcast_to(wi, (n_walkers, n, 3)).reshape(-1, 3)
        wo = np.broadcast_to(wo, (n_walkers, n, 3)).reshape(-1, 3)
        rows = {k: np.broadcast_to(v, (n_walkers, n)).reshape(-1) for k, v in params.items()}
        f = np.asarray(self.model.evaluate(rows, wi, wo), dtype=np.float64).reshape(n_walkers, n)
        return f * np.broadcast_to(ratio, (n_walkers, n))

    def _geometry(self, d: ChannelData, shifts: dict, kin: str):
        """measured_geometry of the channel at these arm shifts, the last result again when the
        shifts are the same: a least-squares Jacobian moves one parameter at a time, and for
        the model's parameters and the scale nuisances the arms stay where they were (about
        half the evaluations of a nuisance fit's least squares, measured)."""
        last = self._geometry_memo.get(id(d))
        if (
            last is not None
            and last[0].keys() == shifts.keys()
            and all(np.array_equal(last[0][k], v) for k, v in shifts.items())
        ):
            return last[1]
        out = measured_geometry(d.wi, d.wo, d.arm, shifts, kin)
        self._geometry_memo[id(d)] = ({k: np.array(v) for k, v in shifts.items()}, out)
        return out

    def _per_pass(self, walkers: int) -> int:
        """How many θ one likelihood pass takes (PASS_ELEMENTS)."""
        return max(1, min(walkers, PASS_ELEMENTS // max(self.n, 1)))

    def log_likelihood(self, theta: np.ndarray) -> np.ndarray:
        """ln L for θ (W, D) → (W,), without the prior. −∞ where the model is not finite."""
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        step = self._per_pass(theta.shape[0])
        if step < theta.shape[0]:
            return np.concatenate(
                [self.log_likelihood(theta[i : i + step]) for i in range(0, len(theta), step)]
            )
        natural = self.space.natural_dict(theta)
        s = self.space.discrepancy(natural)
        total = np.zeros(theta.shape[0])
        for i, (d, fm) in enumerate(zip(self.data, self.predict(theta), strict=True)):
            total += self._channel_ll(d, fm, s, self._scale_ref(i, fm))
        return np.where(np.isnan(total), -np.inf, total)

    def _channel_ll(
        self, d: ChannelData, fm: np.ndarray, s: np.ndarray | None, ref: np.ndarray
    ) -> np.ndarray:
        if self.kind == "gaussian" and not d.kind.any():
            return self._gaussian_fast(d, fm, s, ref)
        with np.errstate(all="ignore"):
            var = d.sigma**2 if s is None else d.sigma**2 + (s[:, None] * ref) ** 2
            r = d.f - fm
            bad = ~np.isfinite(fm).all(axis=1)
            if d.kind.any():
                ex = d.exact
                ll = self._exact(r[:, ex], var[:, ex] if var.ndim == 2 else var[ex]).sum(axis=1)
                sd = np.sqrt(var)
                z = r / sd  # (f − f̂)/√v
                sat = d.kind == 1
                dark = d.kind == 2
                # Saturated: P(Y > f) = Φ((f̂ − f)/√v); dark: P(Y < f) = Φ((f − f̂)/√v).
                ll = (
                    ll
                    + d.censored_sum(log_ndtr(-z[:, sat]), sat)
                    + d.censored_sum(log_ndtr(z[:, dark]), dark)
                )
            else:
                ll = self._exact(r, var).sum(axis=1)
        return np.where(bad, -np.inf, ll)

    @staticmethod
    def _gaussian_fast(
        d: ChannelData, fm: np.ndarray, s: np.ndarray | None, ref: np.ndarray
    ) -> np.ndarray:
        """The same Gaussian sum in fewer passes — the MCMC hot path. A non-finite
        f̂ makes the sum inf/NaN, mapped to −∞ (so no separate isfinite pass is needed)."""
        with np.errstate(all="ignore"):
            if s is None:
                r = d.f - fm
                r *= r
                r /= d.sigma2
                ll = -0.5 * (r.sum(axis=1) + np.sum(np.log(d.sigma**2)) + d.f.size * _LN_2PI)
            else:
                # Fused numba pass (fitting.likelihood_kernels): Σ r²/v + ln v with v = σ² + (s f̃)².
                ref2 = ref if ref.ndim == 2 else ref[None, :]
                acc = gauss_discrepancy_sum(
                    d.f,
                    d.sigma2,
                    np.ascontiguousarray(fm),
                    np.ascontiguousarray(s, dtype=np.float64),
                    np.ascontiguousarray(ref2),
                )
                ll = -0.5 * (acc + d.f.size * _LN_2PI)
        return np.where(np.isfinite(ll), ll, -np.inf)

    def pointwise_log_likelihood(self, theta: np.ndarray) -> np.ndarray:
        """ln L_j per sample for θ (W, D) → (W, n), channels concatenated in ``self.data``
        order. The same terms as :meth:`log_likelihood` (which sums them), kept apart for
        WAIC / PSIS-LOO (:mod:`fitting.compare`). −∞ where the model is not finite."""
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        step = self._per_pass(theta.shape[0])
        if step < theta.shape[0]:
            return np.concatenate(
                [
                    self.pointwise_log_likelihood(theta[i : i + step])
                    for i in range(0, len(theta), step)
                ]
            )
        natural = self.space.natural_dict(theta)
        s = self.space.discrepancy(natural)
        out = []
        for i, (d, fm) in enumerate(zip(self.data, self.predict(theta), strict=True)):
            with np.errstate(all="ignore"):
                ref = self._scale_ref(i, fm)
                var = d.sigma2 if s is None else d.sigma2 + (s[:, None] * ref) ** 2
                var = np.broadcast_to(var, fm.shape)
                r = d.f - fm
                if d.kind.any():
                    ll = np.empty(fm.shape)
                    ex = d.exact
                    ll[:, ex] = self._exact(r[:, ex], var[:, ex])
                    z = r / np.sqrt(var)
                    sat, dark = d.kind == 1, d.kind == 2
                    ll[:, sat] = log_ndtr(-z[:, sat])
                    ll[:, dark] = log_ndtr(z[:, dark])
                    if d.weight is not None:
                        ll *= d.weight  # exact rows have weight 1
                else:  # every row exact: no masked copies of the (W, n) arrays
                    ll = self._exact(r, var)
                ll[~np.isfinite(fm)] = -np.inf
            out.append(ll)
        ll = np.concatenate(out, axis=1)
        ll[np.isnan(ll)] = -np.inf
        return ll

    def _exact(self, r: np.ndarray, var: np.ndarray) -> np.ndarray:
        if self.kind == "gaussian":  # −½ (r²/v + ln v + ln 2π), in place: one (W, n) array
            out = r * r
            out /= var
            out += np.log(var)
            out += _LN_2PI
            out *= -0.5
            return out
        return (
            self._t_const
            - 0.5 * np.log(var)
            - 0.5 * (self.nu + 1) * np.log1p(r * r / (self.nu * var))
        )

    # -- posterior --------------------------------------------------------------------------------
    def log_prob(self, theta: np.ndarray) -> np.ndarray:
        """ln π(θ) + ln L(θ); (W, D) → (W,), (D,) → float. Never NaN.

        The model is only evaluated for walkers inside the prior support (outside, the model
        might not even be defined, e.g. m ≤ 0).
        """
        theta = np.asarray(theta, dtype=np.float64)
        single = theta.ndim == 1
        theta2 = np.atleast_2d(theta)
        lp = self.space.log_prior(theta2)
        ok = np.isfinite(lp)
        if ok.any():
            lp[ok] += self.log_likelihood(theta2[ok])
        lp = np.where(np.isnan(lp), -np.inf, lp)
        return float(lp[0]) if single else lp

    __call__ = log_prob

    # -- residuals (least squares, goodness of fit) ----------------------------------------------
    def residuals(self, theta: np.ndarray, weighting: str = "sigma") -> np.ndarray:
        """Residual vector over exact (uncensored) samples for one θ (D,).

        ``sigma``: r = (f − f̂)/σ.  ``ngan``: Ngan et al. 2005's metric (docs/design.md §6) — plain
        L2 on f·cos θ_i weighted by sin θ_i sin θ_o, i.e. r = √(sin θ_i sin θ_o) · (f − f̂) cos θ_i.
        Non-finite model values give a large finite residual so the optimiser backs off
        (likelihood._weighted).
        """
        fms = self.predict(np.atleast_2d(theta))
        parts = zip(self.data, fms, strict=True)
        r = np.concatenate([_weighted(d, fm[:, d.exact], weighting)[0] for d, fm in parts])
        return np.where(np.isfinite(r), r, 1e10)

    def exact_blocks(self, rows: int) -> Iterator[ChannelData]:
        """The exact rows in blocks of at most ``rows`` rows of one channel each, in the order of
        :meth:`residuals`, made one at a time (a block is a copy of its rows only)."""
        for i, d in enumerate(self.data):
            idx = np.flatnonzero(d.exact)
            lamp = self._lamp[i] if self._lamp else None
            for start in range(0, idx.size, rows):
                take = idx[start : start + rows]
                yield ChannelData(
                    d.channel,
                    d.wi[take],
                    d.wo[take],
                    d.f[take],
                    d.sigma[take],
                    d.theta_i[take],
                    d.theta_o[take],
                    d.kind[take],
                    None if d.weight is None else d.weight[take],
                    None if d.arm is None else {k: v[take] for k, v in d.arm.items()},
                    None if d.cluster is None else d.cluster[take],
                    None if lamp is None else lamp[take],
                )

    def block_residuals(
        self, theta: np.ndarray, block: ChannelData, weighting: str = "sigma"
    ) -> np.ndarray:
        """:meth:`residuals` of one block's rows (all exact) for θ (W, D) → (W, n_block)."""
        (fm,) = self.predict(np.atleast_2d(theta), [block])
        r = _weighted(block, fm, weighting)
        return np.where(np.isfinite(r), r, 1e10)

    @property
    def clusters(self) -> np.ndarray | None:
        """The capture of every row, channels concatenated as pointwise_log_likelihood's
        columns; None when the samples do not say (imported data: rows independent)."""
        if any(d.cluster is None for d in self.data):
            return None
        return np.concatenate([d.cluster for d in self.data])

    def chi2_selected(self, theta: np.ndarray) -> tuple[float, float] | None:
        """Mean and variance of the exact rows' χ² = Σ ((f − f̂)/σ)² at θ (D,), given that each
        was *selected* by reading above the detection limit c_j = dark_snr·σ_j — so whenever the
        table has dark rows (the calibration's rule: a reading below c is flagged dark, every
        other one is exact), whether they are censored or dropped. None when no row is dark.

        Why: a row whose truth sits near c is kept only when its noise went up, so its residual
        is a normal truncated below at a_j = (c_j − f̂_j)/σ_j, not a normal, and χ² ~ χ²_n no
        longer holds (issue 43: flagging a dark table's rows below 3σ raised a false "model
        misses the data"). With λ_j = φ(a_j)/(1 − Φ(a_j)) (the inverse Mills ratio, from
        log-densities so it stays finite for large a): E[z²] = 1 + a λ, E[z⁴] = 3 + (a³ + 3a) λ
        (Johnson, Kotz & Balakrishnan, Continuous Univariate Distributions 1, §10.1); rows are
        independent, so the sum's mean and variance are the sums."""
        if self.n_dark == 0:
            return None
        fms = self.predict(np.atleast_2d(np.asarray(theta, dtype=np.float64)))
        mean = var = 0.0
        for d, fm in zip(self.data, fms, strict=True):
            e = d.exact
            a = self.dark_snr - fm[0, e] / d.sigma[e]
            a = np.where(np.isfinite(a), a, -np.inf)
            with np.errstate(over="ignore", invalid="ignore"):
                lam = np.exp(-0.5 * a * a - 0.5 * np.log(2 * np.pi) - log_ndtr(-a))
            lam = np.where(np.isfinite(a), lam, 0.0)
            a0 = np.where(np.isfinite(a), a, 0.0)
            m2 = 1.0 + a0 * lam
            m4 = 3.0 + (a0**3 + 3.0 * a0) * lam
            mean += float(np.sum(m2))
            var += float(np.sum(m4 - m2 * m2))
        return mean, var

    @property
    def n_exact(self) -> int:
        return int(sum(int(d.exact.sum()) for d in self.data))


#: Radon's 7-point rule on the unit disk (u, v, weight): exact for polynomials of degree ≤ 5
#: (Stroud, Approximate Calculation of Multiple Integrals, 1971, S2:5-1).
_DISK_RULE = ((0.0, 0.0, 0.25),) + tuple(
    (
        math.sqrt(2.0 / 3.0) * math.cos(k * math.pi / 3),
        math.sqrt(2.0 / 3.0) * math.sin(k * math.pi / 3),
        0.125,
    )
    for k in range(6)
)


def _lamp_cone(metadata: dict[str, str]) -> float | None:
    """The lamp disk's angular radius r/d (rad) from metadata ``gonio.lamp``, or None."""
    text = metadata.get("gonio.lamp")
    if not text:
        return None
    try:
        lamp = json.loads(text)
        cone = float(lamp["radius_m"]) / float(lamp["distance_m"])
    except (ValueError, TypeError, KeyError, ZeroDivisionError):
        return None
    return cone if math.isfinite(cone) and cone > 0 else None


def _ambient_rows(d: ChannelData, intensity_w_sr: dict[str, float]) -> None:
    """Per row of `d`, what 1 W m⁻² sr⁻¹ of light leaving the sample that the lamp did not cause
    adds to its calibrated f: r² / (I_c cos θ_i), r the lamp's distance to the row's point
    (fitting.nuisance, ``ambient_mW``), into ``d.arm["ambient_per_W"]``."""
    i_c = intensity_w_sr.get(d.channel)
    if d.arm is None or "light_pos" not in d.arm or not i_c:
        return
    r2 = np.sum((d.arm["light_pos"] - d.arm["point"]) ** 2, axis=1)
    d.arm["ambient_per_W"] = r2 / (i_c * d.wi[:, 2])


def _emission_cos(d: ChannelData) -> np.ndarray | float:
    """cos α per row: the angle at a lamp facing the sample's centre between its axis and the
    row's point p on the sample (from the arms' positions, fitting.nuisance.arm_rows); 1
    without them."""
    if d.arm is None or "light_pos" not in d.arm:
        return 1.0
    light = d.arm["light_pos"]
    return np.sum(normalize(-light) * normalize(d.arm["point"] - light), axis=1)


def _perpendicular_basis(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to each unit row of ``w`` (N, 3) and to each other."""
    helper = np.where(np.abs(w[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = normalize(np.cross(w, helper))
    return e1, np.cross(w, e1)

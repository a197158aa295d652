"""The camera's response measured from the run's own HDR brackets, and its correction.

A camera's response bends near its full well: the EMVA 1288 linearity error of machine-vision
sensors is 0.1–1 %. Uncorrected, a bright specular pixel reads up to that much high while a dim
diffuse one does not, so the lobe's shape (m) and the amplitudes move together — 0.5 % moved m
by two of its posterior sd on the realistic rig. The datasheet's figure states a size, not the
curve of this camera at this gain and temperature, so gonio measures it from frames every
bracketed run already has.

Model (the first term of any smooth response, the form EMVA 1288 §6.2's linearity fit uses
between 5 % and 95 % of saturation):

    y_measured = y (1 + β y / Y),   y = DN − dark,   Y = white − black (the clip, DN),

so two brackets of one pose, exposures t_s < t_l (R = t_l/t_s), read at one pixel

    d = y_l − R y_s = R y_s,true · (β (R − 1) y_s,true / Y) + ε R y_s,true,

where ε is any error of the exposure ratio (quantised shutters, the lamp's level between the
brackets, a flicker): one per pair of exposures, fitted as an intercept — or one per pose and
pair when the data say it differs pose by pose (LinearityStats._by_pose), so that only the level
dependence within a pose, the bend, sets β. Per pixel, q = d / (R ȳ_s) and u = ȳ_s (R − 1)/Y
with ȳ_s the *neighbours'* mean of the short bracket (calibration.hdr.local_mean: never the
pixel's own value, whose noise would correlate with both q and u and bias the slope; a ratio of
the pixel's own values is biased by Var(y_s)/y_s², which varies with the level just as β does).
β is the weighted least-squares slope of q on u over every usable pixel of the sampled poses,
with those intercepts; its σ from the weights, inflated by √(χ²/dof) when the
scatter is larger than the noise model says.

Usable: both brackets unsaturated with margin — the long bracket's predicted level R ȳ_s
between 5 % (below, dark-frame errors ∝ 1/y dominate) and 80 % of Y (above, its own noise can
reach the clip and the unsaturated ones are a biased selection) — and every neighbour valid.

The correction applies y = 2 y_m / (1 + √(1 + 4 β y_m / Y)) (the exact inverse) to every
bracket before the merge, when β differs from 0 by more than 3 σ; otherwise the response is
called linear within what the brackets can see, and both cases are stated in the samples'
budget with what remains (σ_β · Y at the clip). Each sample records the level at which the merge
read it (`bend_level`, from the flux of the regions around it, never its own noisy value:
calibration.reduce._region_level), and the fit carries what remains over those levels as a
nuisance (fitting.nuisance, ``linearity_pct``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calibration.hdr import local_mean

__all__ = ["Linearity", "LinearityStats", "bend_level", "linearise_dn"]

#: The long bracket's predicted level, as a fraction of the clip, where pixels are used.
LEVEL_RANGE = (0.05, 0.80)
#: |β| / σ_β above which the measured bend is corrected (a 3σ detection: with no bend the
#: correction would otherwise add noise to every sample for nothing).
DETECT_Z = 3.0
#: Poses read for the measurement (spread over the run): the estimate's σ falls as 1/√pixels,
#: and a lab's 5 MP frames give plenty in a few poses; the sampled frames are read once more.
MAX_POSES = 32


@dataclass(frozen=True)
class Linearity:
    """The measured bend β (fraction of the clip level Y) and whether it is corrected."""

    beta: float
    sigma: float
    pixels: int
    poses: int
    clip_dn: float
    corrected: bool
    #: Whether the exposure ratio's error was fitted per pose (LinearityStats._by_pose).
    per_pose: bool = False

    def describe(self) -> dict:
        return {
            "beta": self.beta,
            "sigma": self.sigma,
            "pixels": self.pixels,
            "poses": self.poses,
            "clip_dn": self.clip_dn,
            "corrected": self.corrected,
            "per_pose": self.per_pose,
        }

    def words(self) -> str:
        what = (
            f"measured from the brackets ({self.pixels} pixels of {self.poses} poses): "
            f"{100 * self.beta:+.3g} ± {100 * self.sigma:.2g} % at the clip"
        )
        if self.corrected:
            return f"{what}, corrected; what remains ≤ {100 * self.sigma:.2g} % of f (1σ)"
        return f"{what}: linear within that, not corrected"


def bend_level(flux_e_s: np.ndarray, exposures_s: list, noise_e: list, clip_e: float) -> np.ndarray:
    """Per pixel, the fraction of the clip Y at which the HDR merge read it: Σ_k w_k φ t_k / Y
    over the brackets below the clip, w_k = t_k² / (φ t_k + σ_k²) the merge's own weights
    (calibration.hdr.merge_brackets), φ the pixel's merged flux (e⁻/s per photosite) and σ_k
    the bracket's signal-independent noise (e⁻). A bend b (y_m = y (1 + b y / Y) in every
    bracket) moves the merged flux by the factor 1 + b · level, to first order; 1 where every
    bracket is at the clip."""
    phi = np.maximum(np.asarray(flux_e_s, dtype=np.float64), 0.0)
    num = np.zeros_like(phi)
    den = np.zeros_like(phi)
    for t, sd in zip(exposures_s, noise_e, strict=True):
        y = phi * float(t)
        ok = y < clip_e
        w = np.where(ok, float(t) ** 2 / (y + max(float(sd), 1e-6) ** 2), 0.0)
        num += w * y / clip_e
        den += w
    return np.divide(num, den, out=np.ones_like(phi), where=den > 0)


def linearise_dn(y_dn: np.ndarray, beta: float, clip_dn: float) -> np.ndarray:
    """The linear signal y of measured signals y_m = y (1 + β y / Y) (DN above dark), by the
    exact inverse; y_m ≤ 0 (noise about the dark level) stays as it is."""
    y = np.asarray(y_dn, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        root = np.sqrt(np.maximum(1.0 + 4.0 * beta * y / clip_dn, 1e-12))
    return np.where(y > 0, 2.0 * y / (1.0 + root), y)


@dataclass
class LinearityStats:
    """The usable pixels of each pose's bracket pairs, per pose and pair of exposures: their
    own signals (y_s, y_l), the short bracket's neighbours' mean ȳ_s and the weight of their
    difference. Kept (four numbers a pixel), so that `result` can iterate: the model is first
    order in β, and a 5 % bend read 4.4 % in one step; linearised with the last estimate, what
    bend remains is measured again (three steps: the remainder shrinks as β²)."""

    clip_dn: float
    # (pose, t_s, t_l) → (ratio, [ys, yl, m, w] arrays)
    groups: dict = field(default_factory=dict)
    poses: int = 0

    def add_pose(self, dn: list, offsets: list, exposures_s: list, gain: float,
                 read_e: list, white_dn: float, cfa: bool) -> None:  # fmt: skip
        """Each adjacent pair of this pose's brackets (sorted by exposure)."""
        order = np.argsort(exposures_s)
        used = False
        for a, b in zip(order[:-1], order[1:], strict=True):
            ts, tl = float(exposures_s[a]), float(exposures_s[b])
            if tl / ts < 1.5:  # too close: the bend differs little between the two
                continue
            used |= self._add_pair(
                np.asarray(dn[a], np.float64) - np.asarray(offsets[a], np.float64),
                np.asarray(dn[b], np.float64) - np.asarray(offsets[b], np.float64),
                (np.asarray(dn[a]) < white_dn - 0.5) & (np.asarray(dn[b]) < white_dn - 0.5),
                tl / ts, (self.poses, round(ts, 9), round(tl, 9)), gain, read_e[a], read_e[b],
                cfa,
            )  # fmt: skip
        self.poses += int(used)

    def _add_pair(self, y_s, y_l, unsat, ratio, key, gain, read_s, read_l, cfa) -> bool:
        m_s = local_mean(y_s, unsat, cfa=cfa)
        level = ratio * m_s / self.clip_dn
        with np.errstate(invalid="ignore"):
            use = unsat & (level > LEVEL_RANGE[0]) & (level < LEVEL_RANGE[1])
        # every neighbour valid too (local_mean skips invalid ones; near the clip or an edge
        # the mean would lean on fewer, brighter or darker, pixels)
        use &= local_mean(unsat.astype(np.float64), np.ones_like(unsat), cfa=cfa) > 0.999
        if not np.any(use):
            return False
        m = m_s[use]
        # Var(d) in DN² from the neighbours' level (shot noise y/k, read noise σ²/k²): a weight
        # from the pixel's own value would correlate with its noise.
        var_d = (
            ratio * m / gain + ratio**2 * m / gain + (read_l**2 + ratio**2 * read_s**2) / gain**2
        )
        self.groups[key] = (ratio, (y_s[use], y_l[use], m, (ratio * m) ** 2 / var_d))
        return True

    def _step(self, beta: float, by_pose: bool) -> tuple[float, float, float, int, int] | None:
        """(δβ, Σ w (u − ū)², χ², pixels, intercepts): the bend left after linearising with β,
        with one intercept per pose and pair of exposures (`by_pose`) or per pair."""
        stats: dict = {}  # intercept group → [Σw, Σwu, Σwq, Σwuu, Σwuq, Σwqq]
        n = 0
        for key, (ratio, (ys, yl, m, w)) in self.groups.items():
            if beta:
                ys, yl, m = (linearise_dn(v, beta, self.clip_dn) for v in (ys, yl, m))
            q = (yl - ratio * ys) / (ratio * m)
            u = m * (ratio - 1.0) / self.clip_dn
            acc = stats.setdefault(key if by_pose else key[1:], np.zeros(6))
            acc += [w.sum(), (w * u).sum(), (w * q).sum(), (w * u * u).sum(), (w * u * q).sum(),
                    (w * q * q).sum()]  # fmt: skip
            n += q.size
        sxx = sxy = syy = 0.0
        for s_w, s_u, s_q, s_uu, s_uq, s_qq in stats.values():
            sxx += s_uu - s_u * s_u / s_w
            sxy += s_uq - s_u * s_q / s_w
            syy += s_qq - s_q * s_q / s_w
        if n == 0 or sxx <= 0:
            return None
        slope = sxy / sxx
        return slope, sxx, max(syy - slope * sxy, 0.0), n, len(stats)

    def _by_pose(self) -> bool:
        """Whether the exposure ratio's error differs pose by pose (a flicker, the lamp's level
        between brackets): one intercept per pose then, at the cost of the leverage between
        poses (σ_β 0.12 % against 0.09 % on the realistic rig). Nested least squares: the
        per-pose intercepts' drop in χ², in units of the noise, against χ²(extra intercepts);
        per pose when p < 1e-3."""
        from scipy.stats import chi2 as chi2_dist

        pair, pose = self._step(0.0, False), self._step(0.0, True)
        if pair is None or pose is None or pose[4] <= pair[4]:
            return False
        dof = pose[3] - pose[4] - 1
        if dof < 1:
            return False
        noise = max(pose[2] / dof, 1e-300)
        return bool(chi2_dist.sf((pair[2] - pose[2]) / noise, pose[4] - pair[4]) < 1e-3)

    def result(self) -> Linearity | None:
        """β and σ_β (None without a usable pair)."""
        by_pose = self._by_pose()
        beta = 0.0
        for _ in range(3):
            step = self._step(beta, by_pose)
            if step is None:
                return None
            # a remaining bend β' on top of β: (1 + βx)(1 + β'x) ≈ 1 + (β + β')x
            beta += step[0]
        _slope, sxx, chi2, n, groups = step
        dof = n - groups - 1
        if dof < 1:
            return None
        sigma = math.sqrt(1.0 / sxx) * math.sqrt(max(1.0, chi2 / dof))
        found = bool(abs(beta) > DETECT_Z * sigma)
        return Linearity(float(beta), float(sigma), n, self.poses, float(self.clip_dn),
                         corrected=found, per_pose=by_pose)  # fmt: skip

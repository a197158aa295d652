"""Auto-exposure per pose: which exposure to take next, from the frames taken so far.

Pure decision logic — no devices, no decoding. The runner hands in, for every frame of a pose,
the linear levels of the sample-region pixels (0 = black level, 1 = the camera's clip level);
`frame_stats` condenses them to a few numbers (stored with the frame in the manifest, so a
resumed pose re-decides from exactly what the first session saw) and `next_exposure` decides.

Goal for a pose (issue 5): some frame whose sample region has **no saturated pixel**, and
**enough signal** — the `signal_percentile` pixel of the region at `target_signal` or more in a
frame where it is itself unsaturated. Every frame taken is kept as an HDR bracket: the short
frame serves the bright pixels (a specular peak), the long one the dim ones, and calibration
merges all brackets of a pose with noise-optimal weights (Hasinoff et al. 2010), so nothing is
wasted. Exposures are rungs of the ladder t_k = start_s·ratio^k within [min_s, max_s]:
repeatable, a finite set of master darks covers them, and a real shutter has discrete stops.

The level of an unsaturated pixel is linear in exposure, s(t) = Φ·t (docs/design.md §7, linear RAW),
so the rung that brings the signal pixel from level s_b at t_b to the target is the smallest
t_k ≥ t_b·target/s_b.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from acquisition.config import AutoExposureConfig

__all__ = [
    "FrameStats",
    "Decision",
    "frame_stats",
    "exposure_ladder",
    "next_exposure",
    "pose_signal",
]


@dataclass(frozen=True)
class FrameStats:
    """What auto-exposure keeps of one frame's sample region (levels: fraction of clip)."""

    exposure_s: float
    n_pixels: int
    n_saturated: int  # pixels at or above the saturation level
    peak: float  # highest level
    signal: float  # the signal-percentile level
    mean: float  # mean level (saturated pixels included, at their clipped value)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FrameStats:
        return cls(
            exposure_s=float(d["exposure_s"]),
            n_pixels=int(d["n_pixels"]),
            n_saturated=int(d["n_saturated"]),
            peak=float(d["peak"]),
            signal=float(d["signal"]),
            mean=float(d["mean"]),
        )


@dataclass(frozen=True)
class Decision:
    """`exposure_s` of the next frame, or None when the pose is finished; `reason` says why."""

    exposure_s: float | None
    reason: str


def frame_stats(levels: np.ndarray, exposure_s: float, settings: AutoExposureConfig) -> FrameStats:
    """Condense the sample region's linear levels (any shape; NaN ignored) of one frame."""
    v = np.asarray(levels, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        raise ValueError("no sample-region pixel in the frame (is the sample in view?)")
    return FrameStats(
        exposure_s=float(exposure_s),
        n_pixels=int(v.size),
        n_saturated=int(np.count_nonzero(v >= settings.saturation_level)),
        peak=float(v.max()),
        signal=float(np.percentile(v, settings.signal_percentile)),
        mean=float(v.mean()),
    )


def exposure_ladder(settings: AutoExposureConfig) -> tuple[float, ...]:
    """Every exposure auto-exposure may choose, ascending: start_s·ratio^k within [min_s, max_s]
    (1e-9 relative slack so that a bound given as an exact rung is kept)."""
    r, t0 = settings.ratio, settings.start_s
    lo = math.ceil(math.log(settings.min_s / t0) / math.log(r) - 1e-9)
    hi = math.floor(math.log(settings.max_s / t0) / math.log(r) + 1e-9)
    return tuple(float(t0 * r**k) for k in range(lo, hi + 1))


def _same(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-9 * max(a, b)


def next_exposure(history: Sequence[FrameStats], settings: AutoExposureConfig) -> Decision:
    """The next exposure for a pose given its frames so far (in capture order), or None.

    1. No frame yet: `start_s`.
    2. Every frame has a saturated pixel: one rung below the shortest, if there is one.
    3. Signal: take the longest frame whose signal pixel is unsaturated (s_b, t_b). If
       s_b ≥ target: done. Else the smallest rung ≥ t_b·target/s_b (capped at max_s); if that
       rung was already taken, stop (the signal pixel saturates there, or max_s is reached).
    At most `max_brackets` frames are taken. The reason says which goal was not reachable.
    """
    if not history:
        return Decision(settings.start_s, "start")
    ladder = exposure_ladder(settings)
    taken = [h.exposure_s for h in history]
    full = len(history) >= settings.max_brackets
    clean = [h for h in history if h.n_saturated == 0]
    if not clean:
        shortest = min(taken)
        below = [t for t in ladder if t < shortest and not _same(t, shortest)]
        if below and not full:
            return Decision(below[-1], "saturated: one rung shorter")
    # Either a clean frame exists, or none can be had (min_s or max_brackets): go on to the
    # signal goal, which the saturated pixels do not prevent (HDR takes them from shorter
    # frames, or flags them).
    tail = "" if clean else " (sample region saturated even at the shortest exposure)"
    usable = [h for h in history if h.signal < settings.saturation_level]
    if not usable:
        return Decision(None, "signal pixel saturated in every frame" + tail)
    best = max(usable, key=lambda h: h.exposure_s)
    if best.signal >= settings.target_signal:
        return Decision(None, "ok: enough signal" + (", no saturated pixel" if clean else tail))
    if full:
        return Decision(None, "max_brackets reached before the signal target" + tail)
    if best.signal > 0:
        need = best.exposure_s * settings.target_signal / best.signal
        above = [t for t in ladder if t >= need * (1 - 1e-9)]
        nxt = above[0] if above else ladder[-1]
    else:  # no light on the signal pixel at all: the longest rung is the best there is
        nxt = ladder[-1]
    if any(_same(nxt, t) for t in taken):
        why = "max_s reached" if _same(nxt, ladder[-1]) else "signal pixel saturates one rung up"
        return Decision(None, f"signal below target: {why}" + tail)
    return Decision(nxt, "signal below target: longer exposure")


def pose_signal(history: Sequence[FrameStats]) -> float:
    """Relative brightness of a pose's sample region: mean level per second of exposure.

    From the longest frame with no saturated pixel (linear there, s = Φ·t); if every frame
    saturated, from the shortest one — a lower bound, but such a pose is brighter than any
    unsaturated one at the same exposure, which is what peak finding needs.
    """
    if not history:
        raise ValueError("no frame for this pose")
    clean = [h for h in history if h.n_saturated == 0]
    h = (
        max(clean, key=lambda h: h.exposure_s)
        if clean
        else min(history, key=lambda h: h.exposure_s)
    )
    return h.mean / h.exposure_s

"""Calibration frames of a run, and master darks per exposure.

Calibration frames (darks, flats, reference-target captures) are kept raw, like the measurement
frames (docs/design.md §4: "raw data is kept"), under ``RUN/calibration/<kind>/`` and listed in the
manifest's calibration table (acquisition.store; recorded by the plan's calibration phases,
acquisition.calibration_capture, or a retake with `gonio capture KIND RUN`). `calibration_frames`
gives the newest complete take of a kind. The reduce step builds the masters from these raw
frames every time, so a better master-building method can be re-run on an old run.

Master dark (EMVA 1288 §2; dark signal μ_d = black + (dark_rate·t + DSNU)/K⁻¹ per pixel): the mean
of N dark frames at the *same* exposure, per pixel, in DN. Subtracting it instead of the nominal
black level removes the dark current and the dark-signal non-uniformity (DSNU, a fixed pattern).
Its temporal variance σ_d² (read noise + dark-current shot noise + quantisation, in DN², the mean
over pixels of each pixel's sample variance across the N frames) is the signal-independent noise
of a light frame at that exposure; the master itself carries σ_d²/N.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

import plumbing.numba_policy  # noqa: F401 — the vector width, chosen before a kernel here compiles
from acquisition.store import RunStore
from calibration.decode import DecodedFrame, FrameError, decode_frame
from plumbing.errors import UserError
from plumbing.prefetch import prefetched

__all__ = [
    "CalibrationFrameError",
    "calibration_frames",
    "calibration_take_description",
    "decoded_frames",
    "MasterDark",
    "DarkLibrary",
    "master_dark",
    "load_darks",
    "DARK_MATCH_REL",
]


class CalibrationFrameError(UserError, ValueError):
    """Calibration frames that cannot be used; one-line message."""


def calibration_frames(run_dir: str | Path, kind: str) -> list[dict]:
    """Entries of the newest complete take of `kind` ("dark", "flat", "reference"): dicts with
    kind, take, exposure_s, path (inside the run), sha256 and the kind's own keys (reference:
    pose, axes_rad, light_measured); [] when none was recorded. A take that was started but
    never completed, with no complete one before it, is an error naming the fix."""
    with RunStore.open(run_dir) as store:
        take, note = store.usable_calibration_take(kind)
        if not take:
            if note:
                raise CalibrationFrameError(note)
            return []
        return [r.entry() for r in store.calibration_captures(kind, take)]


def calibration_take_description(run_dir: str | Path, kind: str) -> dict:
    """What the newest complete take of `kind` recorded about itself ({} if none)."""
    with RunStore.open(run_dir) as store:
        take, _ = store.usable_calibration_take(kind)
        info = store.calibration_take_info(kind, take) if take else None
        return {} if info is None else dict(info["description"])


def decoded_frames(run_dir: Path, entries: list[dict]) -> Iterator[DecodedFrame]:
    """The entries' frames, decoded as the master that takes them asks, the next two on both
    cores while the master works on this one (plumbing.prefetch); all of one shape. Masters
    accumulate frame by frame: holding every frame at once and then a stack of them cost
    2 × N frames of float64 — 12 GB for the default 32 flats of a 24 MP camera
    (benchmarks/bench_camera_scale.py)."""

    def decode(e: dict) -> DecodedFrame:
        try:
            return decode_frame(run_dir / e["path"], e.get("sha256"))
        except FrameError as exc:
            raise CalibrationFrameError(f"{e['kind']} frame unusable: {exc}") from None

    shape = None
    for frame in prefetched(decode, entries, ahead=2):  # the masters wait on the decoder
        if shape is None:
            shape = frame.dn.shape
        elif frame.dn.shape != shape:
            raise CalibrationFrameError(
                f"calibration frames of different shapes {sorted({shape, frame.dn.shape})}"
            )
        yield frame


def _decode_all(run_dir: Path, entries: list[dict]) -> Iterator[np.ndarray]:
    """The entries' frames' DN (as decoded: float32 or float64), see `decoded_frames`."""
    for frame in decoded_frames(run_dir, entries):
        yield frame.dn


@dataclass(frozen=True)
class MasterDark:
    exposure_s: float
    dn: np.ndarray  # per-pixel mean dark signal (DN), same layout as the frames
    temporal_var_dn2: float  # signal-independent variance of ONE frame (DN²), pixel-averaged
    n_frames: int

    @property
    def master_var_dn2(self) -> float:
        """Variance of the master itself (the mean of n_frames frames)."""
        return self.temporal_var_dn2 / self.n_frames


def master_dark(frames: Iterable[np.ndarray], exposure_s: float) -> MasterDark:
    """Per-pixel mean of dark frames at one exposure, and their temporal variance (DN²).

    Accumulated one frame at a time (Welford's update: the mean and the sum of squared
    deviations per pixel), so memory does not grow with the number of frames."""
    n, mean, m2 = 0, None, None
    for f in frames:
        x = np.asarray(f)
        n += 1
        if mean is None:
            mean, m2 = x.astype(np.float64), np.zeros(x.shape)
            continue
        _welford_update(mean.reshape(-1), m2.reshape(-1), x.reshape(-1), float(n))
    if n < 2:
        raise CalibrationFrameError("a master dark needs at least 2 frames")
    var = float(np.mean(m2 / (n - 1)))  # unbiased per pixel, then averaged
    return MasterDark(float(exposure_s), mean, var, n)


@numba.njit(cache=True, nogil=True)
def _welford_update(mean, m2, x, n):
    """One frame into the running mean and sum of squared deviations, in place, in one pass:
    δ = x − mean; mean += δ/n; m2 += δ·(x − mean) (numpy's whole-array steps, same rounding)."""
    for k in range(mean.shape[0]):
        v = np.float64(x[k])
        delta = v - mean[k]
        mean[k] += delta / n
        m2[k] += delta * (v - mean[k])


#: A dark and a frame match when their exposures agree to 0.1 %: what differs then is the dark
#: current over 0.1 % of t (≤ 0.01 e⁻ at 10 e⁻/s for 1 s, far below a read noise of a few e⁻),
#: while two exposures a plan means apart are ≥ 1/3 stop (26 %) apart on a shutter table and
#: far more than a line period (≤ 30 µs) apart on a sensor. One camera's report of one asked
#: exposure is the same every time; the slack is for a report rounded differently (µs, a float).
DARK_MATCH_REL = 1e-3


@dataclass(frozen=True)
class DarkLibrary:
    masters: dict[float, MasterDark]
    # The masters' DN as one array (exposures ascending), the masters' own `dn` views into it
    # (load_darks): a pose's brackets then take their darks as one view, not a stacked copy.
    stack: np.ndarray | None = None

    def for_exposure(self, exposure_s: float) -> MasterDark:
        """The master taken at this exposure (the exposures the frames had, store.exposure_taken)
        within DARK_MATCH_REL; dark current is linear in t but DSNU and hot pixels need not be,
        so we do not extrapolate."""
        for t, m in self.masters.items():
            if abs(t - exposure_s) <= DARK_MATCH_REL * max(t, exposure_s):
                return m
        have = ", ".join(f"{t:g}" for t in sorted(self.masters))
        raise CalibrationFrameError(f"no master dark for exposure {exposure_s:g} s (have: {have})")

    def stacked(self, exposures_s: list[float]) -> np.ndarray | None:
        """The masters of `exposures_s`, in that order, as one (B, …) view of `stack` when they
        are consecutive in it (brackets recorded shortest first, as plans do); else None."""
        if self.stack is None or not exposures_s:
            return None
        order = sorted(self.masters)  # the stack's order
        try:
            idx = [order.index(self.for_exposure(e).exposure_s) for e in exposures_s]
        except (CalibrationFrameError, ValueError):
            return None
        if idx != list(range(idx[0], idx[0] + len(idx))):
            return None
        return self.stack[idx[0] : idx[0] + len(idx)]


def load_darks(run_dir: str | Path) -> DarkLibrary | None:
    """Master darks from the run's dark frames, one per exposure; None if none were recorded."""
    run_dir = Path(run_dir)
    entries = calibration_frames(run_dir, "dark")
    if not entries:
        return None
    by_t: dict[float, list[dict]] = {}
    for e in entries:
        by_t.setdefault(float(e["exposure_s"]), []).append(e)
    masters = {t: master_dark(_decode_all(run_dir, es), t) for t, es in sorted(by_t.items())}
    stack = np.stack([m.dn for m in masters.values()])  # the masters' arrays are then freed
    masters = {
        t: MasterDark(m.exposure_s, stack[k], m.temporal_var_dn2, m.n_frames)
        for k, (t, m) in enumerate(masters.items())
    }
    return DarkLibrary(masters, stack)

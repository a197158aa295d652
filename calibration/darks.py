"""Calibration frames on disk, and master darks per exposure.

Calibration frames (darks, flats) are kept raw, like the measurement frames (DESIGN §4: "raw data
is kept"), under ``RUN/calibration/<kind>/`` and listed in ``RUN/calibration/frames.json``:

    {"frames": [{"kind": "dark", "exposure_s": 0.002, "path": "calibration/dark/...dng",
                 "sha256": "..."}, ...]}

They are recorded by a calibration step (`record_frames`) that takes any ``capture(exposure_s)
-> Frame`` callable: on a lab rig the camera with the lens capped (darks) or facing a uniform
source (flats); in the simulator ``SimCamera.capture_dark`` / ``capture_flat``. The reduce step
builds the masters from these raw frames every time, so a better master-building method can be
re-run on an old run.

Master dark (EMVA 1288 §2; dark signal μ_d = black + (dark_rate·t + DSNU)/K⁻¹ per pixel): the mean
of N dark frames at the *same* exposure, per pixel, in DN. Subtracting it instead of the nominal
black level removes the dark current and the dark-signal non-uniformity (DSNU, a fixed pattern).
Its temporal variance σ_d² (read noise + dark-current shot noise + quantisation, in DN², the mean
over pixels of each pixel's sample variance across the N frames) is the signal-independent noise
of a light frame at that exposure; the master itself carries σ_d²/N.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.decode import FrameError, decode_frame
from fitting.atomic import atomic_write_bytes

__all__ = [
    "CalibrationFrameError",
    "CALIBRATION_DIR",
    "INDEX_NAME",
    "record_frames",
    "calibration_frames",
    "MasterDark",
    "DarkLibrary",
    "master_dark",
    "load_darks",
]

CALIBRATION_DIR = "calibration"
INDEX_NAME = "frames.json"


class CalibrationFrameError(ValueError):
    """Calibration frames that cannot be used; one-line message."""


def _atomic_write(path: Path, data: bytes) -> None:
    # temp file + fsync + rename: a crash never leaves a half-written frame or index.
    atomic_write_bytes(path, data)


def calibration_frames(run_dir: str | Path, kind: str | None = None) -> list[dict]:
    """Entries of ``RUN/calibration/frames.json`` (all, or of one kind); [] if none recorded."""
    index = Path(run_dir) / CALIBRATION_DIR / INDEX_NAME
    if not index.exists():
        return []
    try:
        entries = json.loads(index.read_text())["frames"]
    except (ValueError, KeyError, TypeError):
        raise CalibrationFrameError(f"{index}: not a calibration frame index") from None
    return [e for e in entries if kind is None or e.get("kind") == kind]


def record_frames(
    run_dir: str | Path,
    kind: str,
    capture: Callable[[float], object],
    exposures_s: list[float] | tuple[float, ...],
    n_frames: int,
) -> list[dict]:
    """Capture ``n_frames`` frames per exposure with ``capture(exposure_s) -> Frame`` (an
    ``acquisition.protocols.Frame``: ``data`` bytes + ``suffix``) and file them as ``kind``
    ("dark" or "flat"). Each frame is written atomically, then the index is rewritten atomically.
    """
    if kind not in ("dark", "flat"):
        raise ValueError(f"kind must be 'dark' or 'flat' (got {kind!r})")
    if n_frames < 2:
        raise ValueError("need at least 2 frames (the temporal variance needs two)")
    run_dir = Path(run_dir)
    folder = run_dir / CALIBRATION_DIR / kind
    folder.mkdir(parents=True, exist_ok=True)
    entries = calibration_frames(run_dir)
    new = []
    for t in exposures_s:
        for k in range(n_frames):
            frame = capture(float(t))
            name = f"{kind}-{float(t):.6g}s-{k:03d}{frame.suffix}"
            _atomic_write(folder / name, frame.data)
            new.append(
                {
                    "kind": kind,
                    "exposure_s": float(t),
                    "path": f"{CALIBRATION_DIR}/{kind}/{name}",
                    "sha256": hashlib.sha256(frame.data).hexdigest(),
                }
            )
    paths = {e["path"] for e in new}
    entries = [e for e in entries if e["path"] not in paths] + new
    _atomic_write(
        run_dir / CALIBRATION_DIR / INDEX_NAME,
        json.dumps({"frames": entries}, indent=1).encode(),
    )
    return new


def _decode_all(run_dir: Path, entries: list[dict]) -> list[np.ndarray]:
    out = []
    for e in entries:
        try:
            out.append(np.asarray(decode_frame(run_dir / e["path"]).dn, dtype=np.float64))
        except FrameError as exc:
            raise CalibrationFrameError(f"{e['kind']} frame unusable: {exc}") from None
    shapes = {a.shape for a in out}
    if len(shapes) != 1:
        raise CalibrationFrameError(f"calibration frames of different shapes {sorted(shapes)}")
    return out


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


def master_dark(frames: list[np.ndarray], exposure_s: float) -> MasterDark:
    """Per-pixel mean of dark frames at one exposure, and their temporal variance (DN²)."""
    stack = np.stack([np.asarray(f, dtype=np.float64) for f in frames])
    if stack.shape[0] < 2:
        raise CalibrationFrameError("a master dark needs at least 2 frames")
    var = float(np.mean(np.var(stack, axis=0, ddof=1)))  # unbiased per pixel, then averaged
    return MasterDark(float(exposure_s), stack.mean(axis=0), var, stack.shape[0])


@dataclass(frozen=True)
class DarkLibrary:
    masters: dict[float, MasterDark]

    def for_exposure(self, exposure_s: float) -> MasterDark:
        """The master taken at this exposure (relative match 1e-6); dark current is linear in
        t but DSNU and hot pixels need not be, so we do not extrapolate."""
        for t, m in self.masters.items():
            if abs(t - exposure_s) <= 1e-6 * max(t, exposure_s):
                return m
        have = ", ".join(f"{t:g}" for t in sorted(self.masters))
        raise CalibrationFrameError(f"no master dark for exposure {exposure_s:g} s (have: {have})")


def load_darks(run_dir: str | Path) -> DarkLibrary | None:
    """Master darks from the run's dark frames, one per exposure; None if none were recorded."""
    run_dir = Path(run_dir)
    entries = calibration_frames(run_dir, "dark")
    if not entries:
        return None
    by_t: dict[float, list[dict]] = {}
    for e in entries:
        by_t.setdefault(float(e["exposure_s"]), []).append(e)
    return DarkLibrary({t: master_dark(_decode_all(run_dir, es), t) for t, es in by_t.items()})

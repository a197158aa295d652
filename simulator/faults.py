"""Fault knobs for the simulated devices that are not on the servo bus: a camera that returns
no frame, and a disk that fills up. (Bus faults live in `simulator.dxl.faults`; the light's
`fail_to_turn_on` and a lamp that dies are attributes of `simulator.light.EmulatedLight`.)

* `FaultyCamera` wraps any `acquisition.protocols.Camera` (the simulated `SimCamera` here) and,
  when told to, raises the driver contract's `DeviceFault` instead of returning a frame — what
  a tethered camera does when the shutter fires but no file arrives, or the USB link drops.
  The frame the camera would have produced is not consumed: a real camera that misses simply
  has no frame, so the next capture is a fresh exposure.
* `full_disk` makes the atomic file writer (`plumbing.atomic`, used by the run store for every
  frame) fail with ``OSError(ENOSPC)`` once a byte budget is used up — a disk that fills up,
  injected in-process so it needs no root and no mount.

Both are deterministic for a given seed / budget.
"""

from __future__ import annotations

import errno
import os
import threading
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from acquisition.protocols import DeviceFault, Frame

__all__ = ["CameraFaults", "FaultyCamera", "DiskBudget", "full_disk"]


class CameraFaults:
    """What goes wrong with the camera: `fail_next(n)` scripted misses, a probability
    `miss_p` per capture (seeded), or `dead` (every capture fails until revived)."""

    def __init__(self, rng: np.random.Generator | int | None = 0) -> None:
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.miss_p = 0.0
        self.dead = False
        self._scripted = 0
        self.counts: Counter[str] = Counter()  # faults actually injected
        self._lock = threading.Lock()

    def fail_next(self, count: int = 1) -> None:
        with self._lock:
            self._scripted += int(count)

    def clear(self) -> None:
        with self._lock:
            self.miss_p, self.dead, self._scripted = 0.0, False, 0

    def should_fail(self) -> str | None:
        """The reason the next capture fails, or None. One draw per capture when miss_p > 0."""
        with self._lock:
            if self.dead:
                reason = "camera not responding"
            elif self._scripted > 0:
                self._scripted -= 1
                reason = "no frame returned"
            elif self.miss_p > 0 and self.rng.random() < self.miss_p:
                reason = "no frame returned"
            else:
                return None
            self.counts["camera_miss"] += 1
            return reason


class FaultyCamera:
    """A `Camera` that consults `faults` before every capture; everything else is delegated."""

    def __init__(self, camera: Any, faults: CameraFaults) -> None:
        self._camera = camera
        self.faults = faults

    def capture(self, exposure_s: float) -> Frame:
        reason = self.faults.should_fail()
        if reason is not None:
            raise DeviceFault(f"camera: {reason} (exposure {exposure_s:g} s)")
        return self._camera.capture(exposure_s)

    def __getattr__(self, name: str) -> Any:  # describe(), supported_exposures(), sensor, ...
        return getattr(self._camera, name)


class DiskBudget:
    """Bytes the simulated disk still accepts; `None` = unlimited. Thread-safe."""

    def __init__(self, free_bytes: int | None) -> None:
        self.free_bytes = free_bytes
        self.refused = 0  # writes refused with ENOSPC
        self._lock = threading.Lock()

    def take(self, n: int) -> bool:
        with self._lock:
            if self.free_bytes is None:
                return True
            if n > self.free_bytes:
                self.free_bytes = 0  # a partial write fills the disk, as on a real one
                self.refused += 1
                return False
            self.free_bytes -= n
            return True


class _BudgetedFile:
    """A binary file whose writes draw on a `DiskBudget`; past it they raise ENOSPC the way
    a real `write(2)` does (errno ENOSPC, no filename)."""

    def __init__(self, fh: Any, budget: DiskBudget) -> None:
        self._fh = fh
        self._budget = budget

    def write(self, data: bytes) -> int:
        if not self._budget.take(len(data)):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self._fh.write(data)

    def __enter__(self) -> _BudgetedFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self._fh.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._fh, name)


@contextmanager
def full_disk(free_bytes: int | None) -> Iterator[DiskBudget]:
    """Within the block, files written through `plumbing.atomic` (every frame of a run) share
    `free_bytes` of disk; then each write fails with ENOSPC. Set `budget.free_bytes = None`
    to free the disk again (the operator cleared space)."""
    import builtins

    import plumbing.atomic as atomic

    budget = DiskBudget(free_bytes)
    real_open = builtins.open

    def budget_open(file: Any, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        fh = real_open(file, mode, *args, **kwargs)
        return _BudgetedFile(fh, budget) if any(c in mode for c in "wax+") else fh

    # A module global shadows the builtin for that module only: SQLite and everything else
    # keep writing, exactly the case where only the large frame files no longer fit.
    atomic.open = budget_open  # type: ignore[attr-defined]
    try:
        yield budget
    finally:
        del atomic.open  # type: ignore[attr-defined]

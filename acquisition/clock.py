"""Clocks. Drivers never call time.sleep directly: they take a Clock, so the same driver code
runs in real time on a rig and in virtual time against the simulated rig, where a 3-second move
costs no wall time but is still accounted as lab time.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "SystemClock", "VirtualClock", "register_clock", "get_clock"]


@runtime_checkable
class Clock(Protocol):
    def now(self) -> float:
        """Seconds on this clock's time line (monotonic)."""

    def sleep(self, seconds: float) -> None:
        """Let `seconds` pass on this clock."""


class SystemClock:
    """Wall-clock time for real hardware."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class VirtualClock:
    """Time that advances only when someone sleeps (or `advance` is called). Thread-safe."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = float(start_s)
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def sleep(self, seconds: float) -> None:
        self.advance(seconds)

    def advance(self, seconds: float) -> None:
        if seconds > 0:
            with self._lock:
                self._t += float(seconds)


_CLOCKS: dict[str, Clock] = {"system": SystemClock()}


def register_clock(name: str, clock: Clock) -> None:
    """Backends (e.g. the simulator) register their clock under a name a rig config can use."""
    _CLOCKS[name] = clock


def get_clock(name: str) -> Clock:
    try:
        return _CLOCKS[name]
    except KeyError:
        raise KeyError(f"unknown clock {name!r}; known: {', '.join(sorted(_CLOCKS))}") from None

"""Harness for fuzzing the bus and the light protocol, shared by the fuzz tests and
`benchmarks/bench_fuzz.py`: a hang watchdog and a device whose replies a callback rewrites.
"""

from __future__ import annotations

import contextlib
import signal
import time
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

from simulator.dxl.faults import Reply

__all__ = ["HANG_S", "Hang", "watchdog", "MangledReplies"]

HANG_S = 5.0  # no single fuzz input may take longer: that would be a hang


class Hang(BaseException):
    """Raised by the watchdog; BaseException so no `except Exception` in the code under
    test can swallow it."""


@contextlib.contextmanager
def watchdog(seconds: float = HANG_S) -> Iterator[None]:
    """Raise Hang if the block does not return within `seconds` (SIGALRM; the SDK polls in
    Python, so the signal lands)."""

    def fire(signum, frame):  # noqa: ANN001 - signal handler signature
        raise Hang(f"no return within {seconds} s")

    # pytest-timeout arms the same timer (SIGALRM); hand it back with its time left.
    old = signal.signal(signal.SIGALRM, fire)
    t0 = time.monotonic()
    outer_s, outer_interval = signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        if outer_s > 0:
            left = max(outer_s - (time.monotonic() - t0), 1e-3)
            signal.setitimer(signal.ITIMER_REAL, left, outer_interval)


class MangledReplies:
    """A device for `dxlsim://` / `lightsim://`: a real emulator (`handle(bytes) -> [Reply]`)
    whose replies `fn` rewrites. `fn` returns the new bytes, or `(kind, bytes)` to have the
    kinds of rewrite counted in `kinds`. `count` is the number of replies rewritten."""

    def __init__(self, device: Any, fn: Callable[[bytes], bytes | tuple[str, bytes]]) -> None:
        self.device, self.fn = device, fn
        self.count = 0
        self.kinds: Counter[str] = Counter()

    def handle(self, data: bytes) -> list[Reply]:
        out = []
        for r in self.device.handle(data):
            result = self.fn(r.data)
            if isinstance(result, tuple):
                kind, result = result
                self.kinds[kind] += 1
            self.count += 1
            out.append(Reply(result))
        return out

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

from simulator.dxl import protocol as P
from simulator.dxl.faults import Reply

__all__ = ["HANG_S", "Hang", "watchdog", "MangledReplies", "MANGLE_KINDS", "mangle_reply"]

HANG_S = 5.0  # no single fuzz input may take longer: that would be a hang


class Hang(BaseException):
    """Raised by the watchdog; BaseException so no `except Exception` in the code under
    test can swallow it."""


@contextlib.contextmanager
def watchdog(seconds: float = HANG_S) -> Iterator[None]:
    """Raise Hang if the block does not return within `seconds` (SIGALRM; the SDK polls in
    Python, so the signal lands)."""

    def fire(signum, frame):
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


#: How a status packet can be rewritten on its way back to the driver.
MANGLE_KINDS = (
    "keep",
    "drop",
    "truncate",
    "flip",
    "crc",
    "refix",
    "refix_len",
    "refix_err",
    "garbage_before",
    "garbage_after",
    "duplicate",
    "random",
)


def mangle_reply(
    kind: str, nums: tuple[int, int, int] | list[int], blob: bytes, pkt: bytes
) -> bytes:
    """Rewrite status packet `pkt` as `kind`, every choice taken from three non-negative
    integers and a byte string (drawn by hypothesis in the tests, by a numpy Generator in the
    benchmark), so both sides fuzz the driver the same way."""
    u, v, w = nums
    b = bytearray(pkt)
    if kind == "keep":
        return pkt
    if kind == "drop":
        return b""
    if kind == "truncate":
        return pkt[: u % len(pkt)]
    if kind == "flip":
        for pos in (u, v, w)[: 1 + w % 3]:
            b[(pos // 8) % len(b)] ^= 1 << (pos % 8)
        return bytes(b)
    if kind == "crc":
        b[-1] ^= 1 + u % 255
        return bytes(b)
    if kind in ("refix", "refix_len", "refix_err"):
        # Mutate, then give it a *correct* CRC so the SDK accepts it and the driver must judge.
        if kind == "refix":
            b[4 + u % (len(b) - 6)] = v & 0xFF
        elif kind == "refix_len":
            body = (bytes(b[8:-2]) + blob)[: u % 41]
            b = bytearray(b[:7]) + b"\x55" + body
            b[5:7] = (len(b) - 7 + 2).to_bytes(2, "little")
            b += b"\0\0"
        else:
            b[8] = u & 0xFF  # error byte: any error number, alert bit
        crc = P.crc16(bytes(b[:-2]))
        b[-2], b[-1] = crc & 0xFF, crc >> 8
        return bytes(b)
    if kind == "garbage_before":
        return (blob or b"\x00") + pkt
    if kind == "garbage_after":
        return pkt + (blob or b"\xff")
    if kind == "duplicate":
        return pkt + pkt
    return blob

"""Fault injection for the emulated Dynamixel bus.

Two kinds of faults, both reproducible from a seed:

* **Reply faults** (what the host sees on the wire), per servo or for every servo, either
  probabilistic (`ReplyFaults(drop_p=0.2, ...)`, drawn from a seeded numpy Generator) or
  scripted per packet (`inject_next("drop", servo_id=3, count=2)`):
    - ``drop``: no status packet -> SDK ``COMM_RX_TIMEOUT`` (after its wall-time timeout);
    - ``truncate``: only the first k < n bytes arrive -> ``COMM_RX_CORRUPT``;
    - ``bad_crc``: the CRC is wrong -> ``COMM_RX_CORRUPT``;
    - ``delay``: the reply arrives `delay_s` seconds (wall time) late; longer than the SDK's
      packet timeout (~34 ms + 10 bit-times per byte) it becomes ``COMM_RX_TIMEOUT``.
  The instruction itself is still executed by the servo (as on a real bus, where the status
  packet is what gets lost).
* **Device faults** (the servo's physics), applied through the bus: hardware alerts
  (overload, overheat, voltage, ...) now or scheduled at a clock time / after N packets,
  a stuck axis, and a position offset between reported and true angle.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

__all__ = [
    "REPLY_FAULT_KINDS",
    "ReplyFaults",
    "Reply",
    "ScheduledAlert",
    "FiredAlert",
    "FaultInjector",
]

REPLY_FAULT_KINDS = ("drop", "truncate", "bad_crc", "delay")


@dataclass(frozen=True)
class ReplyFaults:
    """Per-reply fault probabilities (each in [0, 1], checked in this order)."""

    drop_p: float = 0.0
    truncate_p: float = 0.0
    bad_crc_p: float = 0.0
    delay_p: float = 0.0
    delay_s: float = 0.1

    def __post_init__(self) -> None:
        for name in ("drop_p", "truncate_p", "bad_crc_p", "delay_p"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {p}")
        if self.delay_s < 0:
            raise ValueError(f"delay_s must be >= 0, got {self.delay_s}")


@dataclass(frozen=True)
class Reply:
    """Bytes a device puts on the wire, `delay_s` seconds (wall time) after the request."""

    data: bytes
    delay_s: float = 0.0


@dataclass
class ScheduledAlert:
    servo_id: int
    bits: int
    at_time_s: float | None = None
    after_packets: int | None = None
    persistent: bool = False
    # Fire only while the servo is mid-move (a profile under way, neither at its start nor
    # arrived): an arm that jams or hits something trips on the way, not at rest.
    while_moving: bool = False
    armed_at_s: float | None = None  # while_moving: only moves starting from here count


@dataclass(frozen=True)
class FiredAlert:
    """An injected alert as it fired, with the servo's state at that instant (the emulator's
    truth, for tests that must show *when* it happened)."""

    servo_id: int
    bits: int
    time_s: float
    moving: bool  # a motion profile was under way
    ticks_to_goal: float  # |goal - position| when it fired


class FaultInjector:
    """Decides, reply by reply, what goes wrong. Deterministic for a given seed/Generator."""

    def __init__(self, rng: np.random.Generator | int | None = 0) -> None:
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self._default = ReplyFaults()
        self._per_servo: dict[int, ReplyFaults] = {}
        self._scripted: list[tuple[int | None, str, float]] = []
        self.alerts: list[ScheduledAlert] = []
        self.counts: Counter[str] = Counter()  # faults actually injected, by kind

    def configure(self, faults: ReplyFaults, servo_id: int | None = None) -> None:
        """Set probabilistic reply faults for one servo, or for all (servo_id None)."""
        if servo_id is None:
            self._default = faults
        else:
            self._per_servo[servo_id] = faults

    def clear(self) -> None:
        self._default = ReplyFaults()
        self._per_servo.clear()
        self._scripted.clear()
        self.alerts.clear()

    def inject_next(
        self, kind: str, servo_id: int | None = None, count: int = 1, delay_s: float = 0.1
    ) -> None:
        """Script the next `count` replies (of `servo_id`, or of any servo) to fail as `kind`."""
        if kind not in REPLY_FAULT_KINDS:
            raise ValueError(f"unknown fault {kind!r}; known: {', '.join(REPLY_FAULT_KINDS)}")
        self._scripted.extend([(servo_id, kind, delay_s)] * count)

    def schedule_alert(self, alert: ScheduledAlert) -> None:
        self.alerts.append(alert)

    def _pick(self, servo_id: int) -> tuple[str, float] | None:
        for i, (sid, kind, delay_s) in enumerate(self._scripted):
            if sid is None or sid == servo_id:
                del self._scripted[i]
                return kind, delay_s
        f = self._per_servo.get(servo_id, self._default)
        # One uniform draw per reply keeps the random stream aligned across configurations.
        u = self.rng.random()
        edges = np.cumsum([f.drop_p, f.truncate_p, f.bad_crc_p, f.delay_p])
        for kind, edge in zip(REPLY_FAULT_KINDS, edges, strict=True):
            if u < edge:
                return kind, f.delay_s
        return None

    def apply(self, servo_id: int, packet: bytes) -> Reply | None:
        """The reply that actually reaches the wire for `packet` from `servo_id` (None: lost)."""
        picked = self._pick(servo_id)
        if picked is None:
            return Reply(packet)
        kind, delay_s = picked
        self.counts[kind] += 1
        if kind == "drop":
            return None
        if kind == "truncate":
            k = int(self.rng.integers(1, len(packet)))  # 1..n-1 bytes arrive
            return Reply(packet[:k])
        if kind == "bad_crc":
            return Reply(packet[:-1] + bytes([packet[-1] ^ 0x5A]))
        return Reply(packet, delay_s=delay_s)

"""Light-controller emulator speaking the gonio light protocol (docs/light-protocol.md).

Protocol (ASCII, one command per line, terminated by LF; a CR before the LF is ignored;
commands are case-insensitive; every command gets exactly one reply line ending in LF):

    IDN?            -> IDN GONIO,LIGHTSIM,<name>,1.0
    ON              -> OK                      (ERR LAMP_FAIL if the lamp does not strike)
    OFF             -> OK
    INT <level>     -> OK                      level: decimal in [0, 1]; else ERR RANGE
    INT?            -> INT <level>             commanded level, 3 decimals
    STAT?           -> STAT <ON|OFF> <level> <measured> <OK|FAULT:<reason>>
    CLR             -> OK                      clears a latched fault
    anything else   -> ERR UNKNOWN <command>;  a malformed argument -> ERR SYNTAX

`<measured>` is the controller's monitor photodiode, relative to a nominal lamp at level 1:

    measured = level · (1 + drift_per_hour · hours_on) · (1 + σ·N(0, 1))

where hours_on counts clock time since the lamp was last switched on (`drift_per_hour` e.g.
-0.01 for an LED losing 1 %/h while warming) and σ = `monitor_noise` (seeded Generator).
When off, measured is 0.000. Options: `fail_to_turn_on` (ON fails with ERR LAMP_FAIL and the
fault `LAMP_FAIL` latches until CLR), drift, noise. Reachable in-process as `lightsim://NAME`
(`register_light(name, light)`), or over a pty with `simulator.dxl.transport.PtyTransport`.
"""

from __future__ import annotations

import threading

import numpy as np

from acquisition.clock import Clock
from simulator.dxl.faults import Reply
from simulator.serial_urls import install

__all__ = ["EmulatedLight", "register_light", "get_light", "unregister_light"]

IDN = "GONIO,LIGHTSIM"


class EmulatedLight:
    """A light controller: on/off, relative intensity, a drifting monitor reading."""

    def __init__(
        self,
        clock: Clock,
        *,
        name: str = "light",
        drift_per_hour: float = 0.0,
        monitor_noise: float = 0.0,
        fail_to_turn_on: bool = False,
        rng: np.random.Generator | int | None = 0,
    ) -> None:
        self.clock = clock
        self.name = name
        self.drift_per_hour = float(drift_per_hour)
        self.monitor_noise = float(monitor_noise)
        self.fail_to_turn_on = bool(fail_to_turn_on)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.is_on = False
        self.level = 1.0
        self.fault: str | None = None
        self._on_since = 0.0
        self._buf = bytearray()
        self.lock = threading.Lock()

    def true_level(self) -> float:
        """The lamp's actual relative output (what the sample receives): commanded level with
        the drift since switch-on, without the monitor's noise. 0 when off."""
        if not self.is_on:
            return 0.0
        hours = (self.clock.now() - self._on_since) / 3600.0
        return max(self.level * (1.0 + self.drift_per_hour * hours), 0.0)

    def measured(self) -> float:
        """Monitor reading (relative); the ground truth the simulated camera should use."""
        if not self.is_on:
            return 0.0
        hours = (self.clock.now() - self._on_since) / 3600.0
        value = self.level * (1.0 + self.drift_per_hour * hours)
        if self.monitor_noise:
            value *= 1.0 + self.monitor_noise * float(self.rng.standard_normal())
        return max(value, 0.0)

    def command(self, line: str) -> str:
        """Execute one command line (without terminator) and return the reply (without LF)."""
        parts = line.strip().split()
        if not parts:
            return "ERR SYNTAX"
        cmd, args = parts[0].upper(), parts[1:]
        if cmd == "IDN?" and not args:
            return f"IDN {IDN},{self.name},1.0"
        if cmd == "ON" and not args:
            if self.fail_to_turn_on:
                self.fault = "LAMP_FAIL"
                return "ERR LAMP_FAIL"
            if not self.is_on:
                self.is_on, self._on_since = True, self.clock.now()
            return "OK"
        if cmd == "OFF" and not args:
            self.is_on = False
            return "OK"
        if cmd == "INT":
            if len(args) != 1:
                return "ERR SYNTAX"
            try:
                level = float(args[0])
            except ValueError:
                return "ERR SYNTAX"
            if not 0.0 <= level <= 1.0:  # also rejects nan
                return "ERR RANGE"
            self.level = level
            return "OK"
        if cmd == "INT?" and not args:
            return f"INT {self.level:.3f}"
        if cmd == "STAT?" and not args:
            state = "ON" if self.is_on else "OFF"
            health = "OK" if self.fault is None else f"FAULT:{self.fault}"
            return f"STAT {state} {self.level:.3f} {self.measured():.3f} {health}"
        if cmd == "CLR" and not args:
            self.fault = None
            return "OK"
        if cmd in {"IDN?", "ON", "OFF", "INT?", "STAT?", "CLR"}:
            return "ERR SYNTAX"
        return f"ERR UNKNOWN {parts[0][:32]}"

    def handle(self, data: bytes) -> list[Reply]:
        """Byte-stream interface shared with the bus emulator (URL handler, pty transport)."""
        out: list[Reply] = []
        with self.lock:
            self._buf += data
            while b"\n" in self._buf:
                raw, _, rest = bytes(self._buf).partition(b"\n")
                self._buf = bytearray(rest)
                text = raw.rstrip(b"\r").decode("ascii", errors="replace")
                # errors="replace": an echoed unknown command may hold non-ASCII characters
                # (found by fuzzing: b"\xff\n" raised UnicodeEncodeError); they go out as "?".
                reply = self.command(text) + "\n"
                out.append(Reply(reply.encode("ascii", errors="replace")))
        return out


_LIGHTS: dict[str, EmulatedLight] = {}
_LOCK = threading.Lock()


def register_light(name: str, light: EmulatedLight) -> None:
    """Make `light` reachable as `lightsim://NAME`."""
    install()
    with _LOCK:
        _LIGHTS[name] = light


def get_light(name: str) -> EmulatedLight:
    with _LOCK:
        try:
            return _LIGHTS[name]
        except KeyError:
            known = ", ".join(sorted(_LIGHTS)) or "none"
            raise KeyError(
                f"no emulated light named {name!r} (known: {known}); "
                "call simulator.light.register_light first"
            ) from None


def unregister_light(name: str) -> None:
    with _LOCK:
        _LIGHTS.pop(name, None)


install()

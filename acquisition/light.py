"""`SerialLight`: the light-controller driver (gonio light protocol, docs/light-protocol.md).

Strict request/response over pySerial: one command line out, one reply line back. The port
is opened with `serial_for_url`, so a device path, a pty, or the simulator's `lightsim://NAME`
all work (the simulator installs that URL handler; this module never imports it).
"""

from __future__ import annotations

import math
import threading

import serial

from acquisition.clock import Clock, SystemClock
from acquisition.protocols import DeviceFault, LightStatus

__all__ = ["SerialLight", "ManualLight", "LightError"]


class LightError(DeviceFault):
    """The light controller answered with an error, garbage, or not at all."""


class SerialLight:
    """Light source on a serial line (implements `LightSource`).

    Parameters
    ----------
    url: device path or pySerial URL (`lightsim://NAME` for the emulator).
    clock: time line for `settle_s` after switching/changing intensity.
    baudrate, timeout_s: serial settings; `timeout_s` bounds the wait for each reply line.
    retries: resends of a command whose reply did not come (timeout) or was garbled.
    settle_s: clock time to wait after ON / INT before the level is trusted.
    """

    def __init__(
        self,
        url: str,
        clock: Clock | None = None,
        *,
        baudrate: int = 9600,
        timeout_s: float = 1.0,
        retries: int = 2,
        settle_s: float = 0.0,
    ) -> None:
        self.url = url
        self.clock: Clock = clock if clock is not None else SystemClock()
        self.retries = retries
        self.settle_s = settle_s
        self._lock = threading.Lock()
        try:
            self._ser = serial.serial_for_url(
                url, baudrate=baudrate, timeout=timeout_s, exclusive=True
            )
        except ValueError as exc:
            hint = (
                " (lightsim:// needs `import simulator.light` first)"
                if url.lower().startswith("lightsim://")
                else ""
            )
            raise LightError(f"cannot open light controller {url!r}: {exc}{hint}") from exc
        except (serial.SerialException, OSError) as exc:
            raise LightError(f"cannot open light controller {url!r}: {exc}") from exc
        self._ser.reset_input_buffer()

    # -- wire -----------------------------------------------------------------------------
    def query(self, command: str) -> str:
        """Send one command, return its reply line (without LF); raise LightError on ERR."""
        if "\n" in command or "\r" in command:
            raise ValueError(f"command must be a single line, got {command!r}")
        with self._lock:
            attempts = self.retries + 1
            for _ in range(attempts):
                self._ser.reset_input_buffer()
                self._ser.write(command.encode("ascii") + b"\n")
                raw = self._ser.read_until(b"\n")
                if raw.endswith(b"\n"):
                    reply = raw.decode("ascii", errors="replace").strip()
                    break
            else:
                raise LightError(
                    f"light {self.url}: no reply to {command!r} after {attempts} attempt(s)"
                )
        if reply.startswith("ERR"):
            raise LightError(f"light {self.url}: {command!r} failed: {reply}")
        return reply

    def _expect_ok(self, command: str) -> None:
        reply = self.query(command)
        if reply != "OK":
            raise LightError(f"light {self.url}: {command!r} answered {reply!r}, expected OK")

    # -- LightSource protocol -------------------------------------------------------------
    def identify(self) -> str:
        reply = self.query("IDN?")
        if not reply.startswith("IDN "):
            raise LightError(f"light {self.url}: unexpected IDN? reply {reply!r}")
        return reply[4:]

    def on(self) -> None:
        self._expect_ok("ON")
        self.clock.sleep(self.settle_s)

    def off(self) -> None:
        self._expect_ok("OFF")

    def set_intensity(self, level: float) -> None:
        level = float(level)
        if not 0.0 <= level <= 1.0:  # also rejects NaN
            raise ValueError(f"light intensity must be in [0, 1], got {level}")
        self._expect_ok(f"INT {level:.3f}")
        self.clock.sleep(self.settle_s)

    def status(self) -> LightStatus:
        reply = self.query("STAT?")
        parts = reply.split()
        try:
            if len(parts) != 5 or parts[0] != "STAT" or parts[1] not in ("ON", "OFF"):
                raise ValueError
            level, measured = float(parts[2]), float(parts[3])
            # float() also takes "nan"/"inf": garbage that must not become a reading
            # (found by fuzzing). The protocol's ranges: level in [0, 1], measured >= 0.
            if not (0.0 <= level <= 1.0 and 0.0 <= measured < math.inf):
                raise ValueError
            if parts[4] != "OK" and not parts[4].startswith("FAULT:"):
                raise ValueError
        except ValueError:
            raise LightError(f"light {self.url}: malformed STAT? reply {reply!r}") from None
        health = parts[4]
        fault = None if health == "OK" else health.removeprefix("FAULT:")
        return LightStatus(on=parts[1] == "ON", intensity=level, measured=measured, fault=fault)

    def clear_fault(self) -> None:
        self._expect_ok("CLR")

    def close(self) -> None:
        with self._lock:
            if self._ser.is_open:
                self._ser.close()


class ManualLight:
    """A lamp switched by hand (`[light] url = "manual"`): no controller, no monitor.

    The runner asks the operator to switch it on (acquisition.operator step "lamp_on") and
    waits `warmup_s`; `status()` then reports it on at the commanded level with no monitor
    reading, so calibration cannot correct drift (the samples' metadata and the report say
    so). `off()` cannot act: it is recorded, and the run log asks for the lamp to be switched
    off by hand.
    """

    def __init__(self) -> None:
        self._on = False
        self._level = 1.0

    def identify(self) -> str:
        return "manual lamp (no controller)"

    def on(self) -> None:
        self._on = True

    def off(self) -> None:
        self._on = False

    def set_intensity(self, level: float) -> None:
        level = float(level)
        if not 0.0 <= level <= 1.0:
            raise ValueError(f"light intensity must be in [0, 1], got {level}")
        self._level = level

    def status(self) -> LightStatus:
        return LightStatus(on=self._on, intensity=self._level, measured=None)

    def close(self) -> None:
        pass

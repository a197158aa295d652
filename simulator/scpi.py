"""A SCPI lamp power supply emulator: the SCPI-99 power-supply commands in front of the lamp model
of `simulator.light.EmulatedLight` (the same lamp the simulated camera sees), served over a pty
with `simulator.dxl.transport.PtyTransport` (the pretend lab serves it as `DIR/scpi`), so the real
PyVISA + pyvisa-py drive it as an ASRL instrument.

Commands (one line, LF-terminated, `;` separates several; headers case-insensitive, long or short
form — OUTPut, SOURce, CURRent, VOLTage, MEASure, SYSTem, ERRor, INSTrument, NSELect, PROTection,
CLEar — with the optional nodes [SOURce:], [:LEVel][:IMMediate][:AMPLitude], OUTPut[:STATe] and
SYSTem:ERRor[:NEXT] omitted or not):

    *IDN?  *CLS  *RST
    OUTP ON|OFF|1|0      OUTP?                      output state (0/1)
    CURR <A>   CURR?     VOLT <V>   VOLT?           set point; 0 ≤ value ≤ full scale
    MEAS:CURR?  MEAS:VOLT?                          the lamp's monitor × full scale
    SYST:ERR?                                       the oldest error, `0,"No error"` if none
    INST:NSEL <n>   INST:NSEL?                      output channel (1 only here)
    OUTP:PROT:CLE                                   clears a protection trip

Queries answer one line; commands answer nothing (SCPI), so errors go to the queue (16 deep,
-350 on overflow): -102 syntax, -113 undefined header, -222 data out of range, -221 settings
conflict, -300 device-specific (a latched protection trip). The level seen by the lamp is
set point / full scale.

Faults for tests: `trip(reason)` latches a protection trip (output off, error -300 queued, OUTP ON
refused with -221 until OUTP:PROT:CLE or `clear_trip()`); `mute = True` answers nothing (a hung
instrument: every query times out on the host).
"""

from __future__ import annotations

import threading
from collections import deque

from simulator.dxl.faults import Reply
from simulator.light import EmulatedLight

__all__ = ["ScpiSupply", "IDN_MAKER"]

IDN_MAKER = "GONIO,SCPI-LAMP-SIM"
_LONG = {
    "OUTPUT": "OUTP", "SOURCE": "SOUR", "CURRENT": "CURR", "VOLTAGE": "VOLT",
    "MEASURE": "MEAS", "SYSTEM": "SYST", "ERROR": "ERR", "INSTRUMENT": "INST",
    "NSELECT": "NSEL", "PROTECTION": "PROT", "CLEAR": "CLE", "LEVEL": "LEV",
    "IMMEDIATE": "IMM", "AMPLITUDE": "AMPL", "STATE": "STAT", "NEXT": "NEXT",
}  # fmt: skip
_OPTIONAL = {"SOUR", "LEV", "IMM", "AMPL", "STAT", "NEXT"}
_QUEUE_DEPTH = 16


def _header(text: str) -> str:
    """The canonical short header: `:SOURce:CURRent:LEVel` → `CURR`, `syst:err:next?` →
    `SYST:ERR?`. Unknown mnemonics are kept (and answered -113)."""
    query = text.endswith("?")
    nodes = []
    for raw in text.rstrip("?").strip(":").upper().split(":"):
        short = _LONG.get(raw, raw)
        if short not in _OPTIONAL:
            nodes.append(short)
    return ":".join(nodes) + ("?" if query else "")


class ScpiSupply:
    """A one-output lamp supply in current or voltage mode (see the module docstring)."""

    def __init__(self, lamp: EmulatedLight, *, name: str = "lamp", full_scale: float = 1.0) -> None:
        self.lamp = lamp
        self.name = name
        self.full_scale = float(full_scale)  # A or V at lamp level 1
        self.setpoint = {"CURR": 0.0, "VOLT": 0.0}
        self.errors: deque[str] = deque()
        self.tripped: str | None = None
        self.mute = False
        self.commands: list[str] = []  # every line received, for tests
        self._buf = bytearray()
        self.lock = threading.Lock()

    # -- faults -----------------------------------------------------------------------------
    def trip(self, reason: str = "overtemperature") -> None:
        """Latch a protection trip: the output goes off and stays off until cleared."""
        with self.lock:
            self.tripped = reason
            self.lamp.command("OFF")
            self._error(-300, f"Device-specific error;protection tripped: {reason}")

    def clear_trip(self) -> None:
        with self.lock:
            self.tripped = None

    # -- the instrument ---------------------------------------------------------------------
    def _error(self, code: int, message: str) -> None:
        if len(self.errors) >= _QUEUE_DEPTH - 1:
            if len(self.errors) == _QUEUE_DEPTH - 1:
                self.errors.append('-350,"Queue overflow"')
            return
        self.errors.append(f'{code},"{message}"')

    def _set_lamp_level(self) -> None:
        level = max(self.setpoint.values()) / self.full_scale
        self.lamp.command(f"INT {min(max(level, 0.0), 1.0):.6f}")

    def _number(self, args: list[str]) -> float | None:
        if len(args) != 1:
            self._error(-102, "Syntax error")
            return None
        try:
            value = float(args[0])
        except ValueError:
            self._error(-102, "Syntax error")
            return None
        if not 0.0 <= value <= self.full_scale:  # also rejects nan
            self._error(-222, "Data out of range")
            return None
        return value

    def _output(self, args: list[str]) -> None:
        if len(args) != 1 or args[0].upper() not in ("ON", "OFF", "1", "0"):
            self._error(-102, "Syntax error")
            return
        on = args[0].upper() in ("ON", "1")
        if on and self.tripped is not None:
            self._error(-221, f"Settings conflict;protection tripped: {self.tripped}")
            return
        self.lamp.command("ON" if on else "OFF")

    def execute(self, text: str) -> str | None:
        """One SCPI message unit; its reply (queries) or None (commands)."""
        head, *args = text.strip().split()
        h = _header(head)
        lamp = self.lamp
        if h == "*IDN?":
            return f"{IDN_MAKER},{self.name},1.0"
        if h == "*CLS":
            self.errors.clear()
        elif h == "*RST":
            self.setpoint = {"CURR": 0.0, "VOLT": 0.0}
            lamp.command("OFF")
            self._set_lamp_level()
        elif h == "OUTP":
            self._output(args)
        elif h == "OUTP?":
            return "1" if lamp.is_on else "0"
        elif h in ("CURR", "VOLT"):
            value = self._number(args)
            if value is not None:
                self.setpoint[h] = value
                self._set_lamp_level()
        elif h in ("CURR?", "VOLT?"):
            return f"{self.setpoint[h[:-1]]:.6g}"
        elif h in ("MEAS:CURR?", "MEAS:VOLT?"):
            return f"{lamp.measured() * self.full_scale:.6f}"
        elif h == "SYST:ERR?":
            return self.errors.popleft() if self.errors else '0,"No error"'
        elif h == "INST:NSEL":
            if args != ["1"]:
                self._error(-222, "Data out of range")
        elif h == "INST:NSEL?":
            return "1"
        elif h == "OUTP:PROT:CLE":
            self.tripped = None
        else:
            self._error(-113, "Undefined header")
            return None
        return None

    def handle(self, data: bytes) -> list[Reply]:
        """Byte-stream interface shared with the other emulators (pty transport)."""
        out: list[Reply] = []
        with self.lock:
            self._buf += data
            while b"\n" in self._buf:
                raw, _, rest = bytes(self._buf).partition(b"\n")
                self._buf = bytearray(rest)
                line = raw.rstrip(b"\r").decode("ascii", errors="replace")
                self.commands.append(line)
                if self.mute:
                    continue
                replies = [r for unit in line.split(";") if unit.strip()
                           for r in [self.execute(unit)] if r is not None]  # fmt: skip
                if replies:
                    out.append(Reply((";".join(replies) + "\n").encode("ascii", "replace")))
        return out

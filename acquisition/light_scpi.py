"""`ScpiLight`: a lamp on a SCPI power supply or LED driver, through PyVISA (`light.backend =
"scpi"`; settings in `[light.scpi]`, acquisition.device_config.ScpiConfig).

The run's level l ∈ [0, 1] is the output quantity l · full_scale (amperes in current mode, volts
in voltage mode; a lamp's output follows its current far more closely than its voltage, hence
the default). The drift monitor is the supply's own measurement (`MEAS:CURR?` by default)
divided by its value at level 1: a halogen lamp's radiance follows its current (≈ I^3.4 near
nominal), so a drifting current is what the monitor shows first.

SCPI-99 error handling: after every command and query the error queue is read (`SYST:ERR?`);
any entry other than `0,"No error"` is a `LightError` (a `DeviceFault`: the runner stops
safely) naming the command and every queued error. A reply that does not come within
`timeout_s` is re-asked `retries` times (queries are side-effect free), then a `LightError`.
The queue is cleared (`*CLS`) once when the supply is opened, so errors of an earlier session
are not blamed on this one.

PyVISA's backend is `visa_library`: "@py" (pyvisa-py: serial ASRL, TCPIP, USBTMC), "" (the
system's VISA), or "FILE.yaml@sim" (pyvisa-sim). The import is guarded: without PyVISA the
backend is one line saying `pip install "gonio[visa]"`.
"""

from __future__ import annotations

import threading
from typing import Any

from acquisition.clock import Clock, SystemClock
from acquisition.device_config import ScpiConfig
from acquisition.light import LightError
from acquisition.protocols import LightStatus

__all__ = ["ScpiLight", "scpi_light", "parse_scpi_error", "INSTALL_HINT"]

INSTALL_HINT = (
    "light.backend \"scpi\" needs PyVISA: pip install 'gonio[visa]' (pyvisa, pyvisa-py for "
    "serial/TCPIP/USB, pyvisa-sim for simulated instruments)"
)
_MAX_QUEUED_ERRORS = 20  # SCPI queues hold ≥ 2 entries; real supplies 10–30


def parse_scpi_error(reply: str) -> tuple[int, str]:
    """`-222,"Data out of range"` → (-222, 'Data out of range'). Raises ValueError."""
    code, _, message = reply.strip().partition(",")
    return int(code.strip().lstrip("+")), message.strip().strip('"')


def _truthy(reply: str) -> bool:
    value = reply.strip().upper()
    if value in ("1", "ON"):
        return True
    if value in ("0", "OFF"):
        return False
    raise ValueError(reply)


class ScpiLight:
    """Implements `LightSource` on a SCPI supply (see the module docstring).

    Parameters
    ----------
    resource: VISA resource string ("ASRL/dev/ttyUSB1::INSTR", "TCPIP::10.0.0.5::INSTR"...).
    settings: the `[light.scpi]` table.
    clock: the time line for `settings.settle_s`.
    baudrate: serial speed for ASRL resources.
    """

    def __init__(
        self,
        resource: str,
        settings: ScpiConfig,
        clock: Clock | None = None,
        *,
        baudrate: int = 9600,
    ) -> None:
        try:
            import pyvisa
        except ImportError:
            raise LightError(INSTALL_HINT) from None
        self._pyvisa = pyvisa
        self.resource = resource
        self.settings = settings
        self.clock: Clock = clock if clock is not None else SystemClock()
        self._level = 0.0
        self._lock = threading.Lock()
        self._rm = self._inst = None
        try:
            self._rm = pyvisa.ResourceManager(settings.visa_library)
            self._inst = self._rm.open_resource(
                resource,
                read_termination=settings.read_termination,
                write_termination=settings.write_termination,
                timeout=int(round(settings.timeout_s * 1000)),
            )
            if resource.upper().startswith("ASRL") and hasattr(self._inst, "baud_rate"):
                self._inst.baud_rate = baudrate
        except (pyvisa.Error, ValueError, OSError) as exc:  # VisaIOError, bad name, no port
            self.close()
            raise LightError(f"cannot open SCPI light {resource!r}: {exc}") from exc
        try:
            self._write(settings.clear)
            if settings.channel is not None:
                self.command(settings.select_channel.format(channel=settings.channel))
            self.check_errors(settings.clear)
        except BaseException:
            self.close()
            raise

    # -- wire -----------------------------------------------------------------------------
    def _write(self, text: str) -> None:
        try:
            self._inst.write(text)
        except self._pyvisa.Error as exc:
            raise LightError(f"light {self.resource}: cannot send {text!r}: {exc}") from exc

    def _ask(self, text: str) -> str:
        """One query with `retries` re-asks after a timeout; no error-queue check."""
        pyvisa = self._pyvisa
        attempts = self.settings.retries + 1
        last: Exception | None = None
        for _ in range(attempts):
            try:
                return str(self._inst.query(text)).strip()
            except pyvisa.VisaIOError as exc:
                last = exc
                if exc.error_code != pyvisa.constants.StatusCode.error_timeout:
                    break
                try:  # a late reply must not be read as the answer to the next query
                    self._inst.flush(pyvisa.constants.BufferOperation.discard_read_buffer)
                except (pyvisa.Error, NotImplementedError, AttributeError):
                    pass
        what = "no reply" if "TMO" in str(last) or "imeout" in str(last) else "failed"
        raise LightError(
            f"light {self.resource}: {what} to {text!r} after {attempts} attempt(s) "
            f"(timeout {self.settings.timeout_s:g} s): {last}"
        )

    def check_errors(self, after: str) -> None:
        """Read the SCPI error queue until empty; raise LightError if it held anything."""
        errors = []
        for _ in range(_MAX_QUEUED_ERRORS):
            reply = self._ask(self.settings.error_query)
            try:
                code, message = parse_scpi_error(reply)
            except ValueError:
                raise LightError(
                    f"light {self.resource}: {self.settings.error_query!r} answered {reply!r}, "
                    'not CODE,"MESSAGE"'
                ) from None
            if code == 0:
                break
            errors.append(f'{code},"{message}"')
        if errors:
            raise LightError(f"light {self.resource}: {after!r} → SCPI error {'; '.join(errors)}")

    def command(self, text: str) -> None:
        """Send a command (no reply), then check the error queue."""
        with self._lock:
            self._write(text)
            self.check_errors(text)

    def query(self, text: str) -> str:
        """Ask, then check the error queue; the reply without its terminator."""
        with self._lock:
            reply = self._ask(text)
            self.check_errors(text)
            return reply

    # -- LightSource protocol -------------------------------------------------------------
    def identify(self) -> str:
        return self.query("*IDN?")

    def on(self) -> None:
        self.command(self.settings.output_on)
        self.clock.sleep(self.settings.settle_s)

    def off(self) -> None:
        self.command(self.settings.output_off)

    def set_intensity(self, level: float) -> None:
        level = float(level)
        if not 0.0 <= level <= 1.0:  # also rejects NaN
            raise ValueError(f"light intensity must be in [0, 1], got {level}")
        self.command(self.settings.level_command.format(value=level * self.settings.full_scale))
        self._level = level
        self.clock.sleep(self.settings.settle_s)

    def status(self) -> LightStatus:
        s = self.settings
        reply = self.query(s.output_query)
        try:
            on = _truthy(reply)
        except ValueError:
            raise LightError(
                f"light {self.resource}: {s.output_query!r} answered {reply!r}, not 0/1/ON/OFF"
            ) from None
        reading = self.query(s.monitor_command)
        try:
            measured = float(reading) / (s.monitor_full_scale or s.full_scale)
        except ValueError:
            raise LightError(
                f"light {self.resource}: {s.monitor_command!r} answered {reading!r}, not a number"
            ) from None
        if not 0.0 <= measured < float("inf"):  # "nan" and negative readings are no reading
            raise LightError(f"light {self.resource}: monitor reading {reading!r} out of range")
        return LightStatus(on=on, intensity=self._level, measured=measured)

    def clear_fault(self) -> None:
        self.command(self.settings.clear)

    def close(self) -> None:
        for obj in (self._inst, self._rm):
            if obj is not None:
                try:
                    obj.close()
                except Exception:  # closing a session whose device is gone: nothing to undo
                    pass
        self._inst = self._rm = None


def scpi_light(config: Any, clock: Clock | None = None) -> ScpiLight:
    """Factory for `LIGHT_BACKENDS["scpi"]` from a RigConfig."""
    light = config.light
    return ScpiLight(light.url, light.scpi, clock, baudrate=light.baudrate)

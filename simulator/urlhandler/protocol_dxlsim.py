"""pySerial URL handler `dxlsim://NAME`: an in-process port onto the EmulatedBus registered as
NAME in `simulator.dxl.registry`. Open with `serial.serial_for_url("dxlsim://NAME")` after
`simulator.dxl.install()` (importing `simulator.dxl` does it)."""

from __future__ import annotations

from simulator.dxl.registry import get_bus
from simulator.urlhandler._base import EmulatedSerial

__all__ = ["Serial"]


class Serial(EmulatedSerial):
    SCHEME = "dxlsim"

    def _lookup(self, name: str):
        return get_bus(name)

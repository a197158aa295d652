"""pySerial URL handler `lightsim://NAME`: an in-process port onto the EmulatedLight registered
as NAME with `simulator.light.register_light`."""

from __future__ import annotations

from simulator.light import get_light
from simulator.urlhandler._base import EmulatedSerial

__all__ = ["Serial"]


class Serial(EmulatedSerial):
    SCHEME = "lightsim"

    def _lookup(self, name: str):
        return get_light(name)

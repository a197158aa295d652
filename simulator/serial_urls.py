"""Let pySerial open the simulated devices by URL: `dxlsim://NAME` and `lightsim://NAME`.

pySerial's `serial_for_url` imports `<package>.protocol_<scheme>` for every package in
`serial.protocol_handler_packages`; :func:`install` adds :mod:`simulator.urlhandler` (the
handlers) to that list (idempotent). Kept apart from the handlers, which import the emulated
devices that call this: so the devices sit below their handlers.
"""

from __future__ import annotations

import serial

__all__ = ["install", "PACKAGE"]

PACKAGE = "simulator.urlhandler"


def install() -> None:
    """Let `serial.serial_for_url` open `dxlsim://` and `lightsim://` URLs."""
    if PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(PACKAGE)

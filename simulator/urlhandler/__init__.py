"""pySerial URL handlers for the simulated devices: `dxlsim://NAME` and `lightsim://NAME`.

pySerial's `serial_for_url` imports `<package>.protocol_<scheme>` for every package in
`serial.protocol_handler_packages`; `install()` adds this package to that list (idempotent).
"""

from __future__ import annotations

import serial

__all__ = ["install", "PACKAGE"]

PACKAGE = "simulator.urlhandler"


def install() -> None:
    """Let `serial.serial_for_url` open `dxlsim://` and `lightsim://` URLs."""
    if PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(PACKAGE)

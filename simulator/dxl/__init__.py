"""Dynamixel Protocol 2.0 bus emulator (X-series), reachable by the unmodified ROBOTIS SDK
over a pseudo-terminal (`transport.PtyTransport`) or in-process as `dxlsim://NAME`.

Importing this package installs the `dxlsim://` / `lightsim://` pyserial URL handlers
(`install()` is idempotent and may be called again explicitly).
"""

from __future__ import annotations

from simulator.dxl.bus import ALERT_BITS, EmulatedBus
from simulator.dxl.faults import FaultInjector, Reply, ReplyFaults
from simulator.dxl.registry import get_bus, register_bus, unregister_bus
from simulator.dxl.servo import Servo
from simulator.dxl.transport import PtyTransport
from simulator.serial_urls import install

__all__ = [
    "ALERT_BITS",
    "EmulatedBus",
    "FaultInjector",
    "Reply",
    "ReplyFaults",
    "Servo",
    "PtyTransport",
    "register_bus",
    "get_bus",
    "unregister_bus",
    "install",
]

install()

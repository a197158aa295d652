"""Named emulated buses, so a URL (`dxlsim://NAME`) can reach one in-process."""

from __future__ import annotations

import threading

from simulator.dxl.bus import EmulatedBus

__all__ = ["register_bus", "get_bus", "unregister_bus", "bus_names"]

_BUSES: dict[str, EmulatedBus] = {}
_LOCK = threading.Lock()


def register_bus(name: str, bus: EmulatedBus) -> None:
    """Make `bus` reachable as `dxlsim://NAME` (replaces a bus of the same name)."""
    with _LOCK:
        _BUSES[name] = bus


def get_bus(name: str) -> EmulatedBus:
    with _LOCK:
        try:
            return _BUSES[name]
        except KeyError:
            known = ", ".join(sorted(_BUSES)) or "none"
            raise KeyError(
                f"no emulated bus named {name!r} (known: {known}); "
                "call simulator.dxl.registry.register_bus first"
            ) from None


def unregister_bus(name: str) -> None:
    with _LOCK:
        _BUSES.pop(name, None)


def bus_names() -> list[str]:
    with _LOCK:
        return sorted(_BUSES)

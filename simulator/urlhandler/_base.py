"""Shared in-process serial port for emulated devices (template: pySerial's protocol_loop).

A device object has `handle(data: bytes) -> list[Reply]` (bytes plus a wall-time delay). A
write hands the bytes to the device at once; its replies become readable when their delay
has passed, so a non-blocking reader (the ROBOTIS SDK polls with timeout=0) sees a real
device's timing: immediate answers, late answers, or none.
"""

from __future__ import annotations

import threading
import time
import urllib.parse
from typing import Any

from serial.serialutil import PortNotOpenError, SerialBase, SerialException, Timeout, to_bytes

__all__ = ["EmulatedSerial"]


class EmulatedSerial(SerialBase):
    """Base class; subclasses set SCHEME and implement `_lookup(name)`."""

    SCHEME = ""
    BAUDRATES = (
        9600,
        19200,
        38400,
        57600,
        115200,
        230400,
        460800,
        500000,
        576000,
        921600,
        1000000,
        1152000,
        2000000,
        2500000,
        3000000,
        3500000,
        4000000,
        4500000,
    )

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.device: Any = None
        self._rx: list[tuple[float, bytes]] = []  # (ready_at wall time, bytes)
        self._rx_lock = threading.Lock()
        super().__init__(*args, **kwargs)

    def _lookup(self, name: str) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        parts = urllib.parse.urlsplit(self._port)
        if parts.scheme.lower() != self.SCHEME:
            raise SerialException(f"expected {self.SCHEME}://NAME, got {self._port!r}")
        name = parts.netloc or parts.path.lstrip("/")
        try:
            self.device = self._lookup(name)
        except KeyError as exc:
            raise SerialException(str(exc.args[0]) if exc.args else str(exc)) from None
        self.is_open = True
        self.reset_input_buffer()

    def close(self) -> None:
        self.is_open = False
        self.device = None
        super().close()

    def _reconfigure_port(self) -> None:
        pass  # baud rate, parity... mean nothing in-process

    # -- data -----------------------------------------------------------------------------
    def _ready(self) -> int:
        now = time.monotonic()
        with self._rx_lock:
            return sum(len(d) for t, d in self._rx if t <= now)

    @property
    def in_waiting(self) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        return self._ready()

    def _take(self, size: int) -> bytes:
        now = time.monotonic()
        out = bytearray()
        with self._rx_lock:
            while self._rx and len(out) < size and self._rx[0][0] <= now:
                t, d = self._rx[0]
                need = size - len(out)
                out += d[:need]
                if len(d) > need:
                    self._rx[0] = (t, d[need:])
                else:
                    self._rx.pop(0)
        return bytes(out)

    def read(self, size: int = 1) -> bytes:
        if not self.is_open:
            raise PortNotOpenError()
        timeout = Timeout(self._timeout)
        data = bytearray()
        while len(data) < size:
            data += self._take(size - len(data))
            if len(data) >= size or timeout.expired() or timeout.is_non_blocking:
                break
            with self._rx_lock:
                pending = bool(self._rx)
            if not pending and not timeout.is_infinite:
                # nothing will ever arrive without another write: wait out the timeout
                time.sleep(min(timeout.time_left(), 0.001))
            else:
                time.sleep(0.0002)
        return bytes(data)

    def write(self, data: Any) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        data = to_bytes(data)
        replies = self.device.handle(data)
        now = time.monotonic()
        with self._rx_lock:
            for r in replies:
                if r.data:
                    self._rx.append((now + r.delay_s, r.data))
            self._rx.sort(key=lambda item: item[0])
        return len(data)

    def reset_input_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        with self._rx_lock:
            self._rx.clear()

    def reset_output_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()

    @property
    def out_waiting(self) -> int:
        return 0

    def _update_break_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True

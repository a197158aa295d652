"""Pseudo-terminal transport: a real device path (/dev/pts/N) onto an emulated device.

A daemon thread reads the pty master, hands the bytes to the device (`handle(data) ->
list[Reply]`, an EmulatedBus or the light emulator) and writes the replies back, honouring
each reply's wall-time delay. Any program that opens `port_path` — the unmodified ROBOTIS
SDK's PortHandler, pyserial, a terminal — talks to the emulator as to a USB adapter.

    with PtyTransport(bus) as t:
        port = PortHandler(t.port_path)
"""

from __future__ import annotations

import os
import select
import sys
import threading
import time
import tty
from typing import Any

__all__ = ["PtyTransport"]

# The SDK on the other end busy-polls with a wall-clock timeout of ~36 ms. In one process the
# emulator thread needs the GIL ~3 times per request, and CPython hands it over only every
# `switchinterval` (5 ms) to a busy thread — on a loaded 2-core CI host that adds up to a
# missed reply. While any PtyTransport runs, the interval is lowered to 0.5 ms (restored after).
_FAST_SWITCH_S = 5e-4
_switch_lock = threading.Lock()
_switch_users = 0
_switch_saved = 0.005


def _fast_switch(on: bool) -> None:
    global _switch_users, _switch_saved
    with _switch_lock:
        if on:
            if _switch_users == 0:
                _switch_saved = sys.getswitchinterval()
                sys.setswitchinterval(min(_switch_saved, _FAST_SWITCH_S))
            _switch_users += 1
        elif _switch_users > 0:
            _switch_users -= 1
            if _switch_users == 0:
                sys.setswitchinterval(_switch_saved)


class PtyTransport:
    """Bridge a pseudo-terminal to `device`. `port_path` is the slave device path."""

    def __init__(self, device: Any, *, start: bool = True) -> None:
        self.device = device
        self._master, self._slave = os.openpty()
        # Raw mode: no echo, no line discipline, no CR/LF translation — binary packets.
        tty.setraw(self._slave)
        tty.setraw(self._master)
        self.port_path = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"pty:{self.port_path}", daemon=True)
        self.error: BaseException | None = None
        self._started = False
        if start:
            self.start()

    def start(self) -> None:
        if not self._thread.is_alive() and not self._stop.is_set():
            _fast_switch(True)
            self._started = True
            self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                r, _, _ = select.select([self._master], [], [], 0.05)
                if not r:
                    continue
                try:
                    data = os.read(self._master, 4096)
                except OSError:  # EIO when no slave is open: keep serving
                    time.sleep(0.005)
                    continue
                if not data:
                    continue
                t0 = time.monotonic()
                for reply in self.device.handle(data):
                    wait = t0 + reply.delay_s - time.monotonic()
                    if wait > 0:
                        time.sleep(wait)
                    if reply.data:
                        os.write(self._master, reply.data)
        except BaseException as exc:  # surfaced to tests via .error
            self.error = exc

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        if self._started:
            _fast_switch(False)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> PtyTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

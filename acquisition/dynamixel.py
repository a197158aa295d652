"""Dynamixel X-series driver on the ROBOTIS SDK (`dynamixel_sdk`, Protocol 2.0).

`DynamixelBus` owns one port and one lock and wraps every SDK call: it retries on a missing
or corrupt status packet (`COMM_RX_TIMEOUT`, `COMM_RX_CORRUPT`, a CRC error reported by the
servo), decodes the status error byte into a named `DynamixelError`, and on a hardware alert
(error bit 7) reads Hardware Error Status (70) and either reboots the servo and restores
torque and goal, or raises `HardwareAlert` (a `DeviceFault`), as configured.

The port is opened with `serial.serial_for_url(..., exclusive=True)`, so one URL scheme
reaches a USB adapter (`/dev/ttyUSB0`), a pseudo-terminal (`/dev/pts/N`), or the simulator's
in-process emulator (`dxlsim://NAME`, once the simulator has installed its URL handler).
This module never imports the simulator.

`DynamixelAxis` maps servo ticks to an axis angle (e-Manual: 4096 ticks per servo revolution),

    angle_rad = zero_offset_rad + direction · ticks · (2π / 4096) / gear_ratio
    ticks     = round((angle_rad − zero_offset_rad) · direction · gear_ratio · 4096 / (2π))

with `gear_ratio` = servo turns per axis turn and `zero_offset_rad` = axis angle at tick 0.
Soft limits are checked before anything is sent.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Literal

import serial
from dynamixel_sdk import (
    COMM_PORT_BUSY,
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    COMM_TX_FAIL,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from acquisition.clock import Clock, SystemClock
from acquisition.motion import trapezoid_time_s
from acquisition.protocols import AxisTimeout, DeviceFault

__all__ = [
    "ADDR",
    "SIGNED_REGISTERS",
    "ERROR_NAMES",
    "HARDWARE_ERROR_NAMES",
    "MODEL_NAMES",
    "DynamixelError",
    "DynamixelCommError",
    "HardwareAlert",
    "UrlPortHandler",
    "DynamixelBus",
    "DynamixelAxis",
    "move_together",
    "read_positions",
    "to_signed",
    "to_unsigned",
    "decode_hardware_error",
]

# X-series control table addresses (e-Manual).
ADDR = {
    "model_number": 0,
    "firmware_version": 6,
    "operating_mode": 11,
    "homing_offset": 20,
    "moving_threshold": 24,
    "temperature_limit": 31,
    "max_position_limit": 48,
    "min_position_limit": 52,
    "shutdown": 63,
    "torque_enable": 64,
    "hardware_error_status": 70,
    "profile_acceleration": 108,
    "profile_velocity": 112,
    "goal_position": 116,
    "moving": 122,
    "present_position": 132,
    "present_input_voltage": 144,
    "present_temperature": 146,
}
# Registers holding two's-complement values (the SDK returns everything unsigned).
SIGNED_REGISTERS = {
    20: 4,
    100: 2,
    102: 2,
    104: 4,
    116: 4,
    124: 2,
    126: 2,
    128: 4,
    132: 4,
    136: 4,
    140: 4,
}

ERROR_NAMES = {
    1: "result fail",
    2: "instruction error",
    3: "CRC error",
    4: "data range error",
    5: "data length error",
    6: "data limit error",
    7: "access error",
}
HARDWARE_ERROR_NAMES = {
    0: "input voltage",
    2: "overheating",
    3: "motor encoder",
    4: "electrical shock",
    5: "overload",
}
MODEL_NAMES = {1020: "XM430-W350", 1060: "XL430-W250"}

_RETRYABLE = (COMM_RX_TIMEOUT, COMM_RX_CORRUPT, COMM_PORT_BUSY, COMM_TX_FAIL)
_ERR_CRC = 3
_ALERT = 0x80
TICKS_PER_REV = 4096


def to_signed(value: int, size: int) -> int:
    """Two's complement of an unsigned `size`-byte value."""
    bits = 8 * size
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >> (bits - 1) else value


def to_unsigned(value: int, size: int) -> int:
    return int(value) & ((1 << (8 * size)) - 1)


def decode_hardware_error(status: int) -> list[str]:
    """Names of the bits set in Hardware Error Status (70)."""
    names = [name for bit, name in HARDWARE_ERROR_NAMES.items() if status >> bit & 1]
    unknown = status & ~sum(1 << b for b in HARDWARE_ERROR_NAMES)
    if unknown:
        names.append(f"unknown bits 0x{unknown:02X}")
    return names


class DynamixelError(DeviceFault):
    """A servo answered with an error in its status packet (range, limit, access, ...)."""

    def __init__(self, servo_id: int, error: int, what: str) -> None:
        self.servo_id, self.error, self.what = servo_id, error, what
        self.name = ERROR_NAMES.get(error & 0x7F, f"unknown error {error & 0x7F}")
        super().__init__(f"servo {servo_id}: {what}: {self.name} (status error 0x{error:02X})")


class DynamixelCommError(DeviceFault):
    """No valid status packet after all retries (wrong ID/baud, power, cabling, noise)."""

    def __init__(self, servo_id: int | None, result: int, what: str, attempts: int) -> None:
        self.servo_id, self.result, self.what, self.attempts = servo_id, result, what, attempts
        text = PacketHandler(2.0).getTxRxResult(result) or f"result {result}"
        who = "bus" if servo_id is None else f"servo {servo_id}"
        super().__init__(
            f"{who}: {what}: {text} (SDK result {result}) after {attempts} attempt(s); "
            "check ID, baud rate, power and cabling"
        )


class HardwareAlert(DeviceFault):
    """A servo raised a hardware alert (error bit 7); `status` is register 70."""

    def __init__(self, servo_id: int, status: int, what: str, note: str = "") -> None:
        self.servo_id, self.status = servo_id, status
        self.names = decode_hardware_error(status)
        detail = ", ".join(self.names) or "no bit set in register 70"
        super().__init__(
            f"servo {servo_id}: hardware alert during {what}: {detail} "
            f"(Hardware Error Status 0x{status:02X}){note}"
        )


class UrlPortHandler(PortHandler):
    """The SDK's PortHandler, opened through `serial_for_url` (paths and URL handlers alike),
    exclusively, with the non-blocking reads (timeout=0) the SDK's busy-poll expects."""

    # Sleep this long when a poll finds no byte: the SDK busy-polls, which burns a core and,
    # in one process with a pty emulator thread, hogs the GIL the emulator needs to answer.
    # 0.1 ms is far below one byte time at 1 Mbaud (10 µs) × a status packet (≥ 11 bytes).
    poll_sleep_s = 1e-4

    def getCFlagBaud(self, baudrate: int) -> int:  # SDK name
        return baudrate if baudrate > 0 else -1

    def __init__(self, port_name: str, timeout_margin_ms: float = 0.0) -> None:
        super().__init__(port_name)
        self.timeout_margin_ms = timeout_margin_ms

    def setPacketTimeout(self, packet_length: int) -> None:  # SDK name
        super().setPacketTimeout(packet_length)
        self.packet_timeout += self.timeout_margin_ms

    def readPort(self, length: int) -> bytes:  # SDK name
        data = self.ser.read(length)
        if not data:
            time.sleep(self.poll_sleep_s)
        return data

    def setupPort(self, cflag_baud: int) -> bool:  # SDK name
        if self.is_open:
            self.closePort()
        self.ser = serial.serial_for_url(
            self.port_name,
            baudrate=self.baudrate,
            bytesize=serial.EIGHTBITS,
            timeout=0,
            exclusive=True,
        )
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True


def _set_low_latency(url: str) -> bool:
    """FTDI adapters buffer for 16 ms by default; 1 ms makes each status packet arrive ~15 ms
    sooner. Only possible for a real usb-serial tty with a writable sysfs node."""
    if "://" in url:
        return False
    try:
        tty = os.path.basename(os.path.realpath(url))
        node = f"/sys/bus/usb-serial/devices/{tty}/latency_timer"
        if os.path.exists(node) and os.access(node, os.W_OK):
            with open(node, "w") as fh:
                fh.write("1")
            return True
    except OSError:
        pass
    return False


class DynamixelBus:
    """One Dynamixel bus (port). Thread-safe: one lock serialises every transaction.

    Parameters
    ----------
    url: device path, pty path or `dxlsim://NAME`.
    baudrate: X-series ship at 57 600.
    retries: extra attempts after a timeout / corrupt packet / CRC error.
    on_alert: "stop" raises HardwareAlert; "reboot" reboots the servo, re-enables torque (if
        this bus had enabled it), re-sends the last goal, and repeats the operation once.
    clock: time line for waits (reboot settle); SystemClock on a rig, VirtualClock in sim.
    reboot_settle_s: clock time to let a rebooted servo come back before talking to it.
    timeout_margin_ms: added to the SDK's status-packet timeout (10 bit-times per byte +
        2×16 ms for the FTDI latency timer + 2 ms). A loaded host, or an emulator thread
        behind a pty, can answer later than that; a missing packet costs this much longer.
    """

    def __init__(
        self,
        url: str,
        baudrate: int = 57600,
        protocol: float = 2.0,
        retries: int = 3,
        on_alert: Literal["reboot", "stop"] = "stop",
        clock: Clock | None = None,
        *,
        reboot_settle_s: float = 0.5,
        timeout_margin_ms: float = 50.0,
    ) -> None:
        if protocol != 2.0:
            raise ValueError(f"only Dynamixel Protocol 2.0 is supported, got {protocol}")
        if on_alert not in ("reboot", "stop"):
            raise ValueError(f"on_alert must be 'reboot' or 'stop', got {on_alert!r}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0, got {retries}")
        self.url = url
        self.baudrate = baudrate
        self.retries = retries
        self.on_alert = on_alert
        self.clock: Clock = clock if clock is not None else SystemClock()
        self.reboot_settle_s = reboot_settle_s
        self.lock = threading.RLock()
        self.packet = PacketHandler(protocol)
        self.port = UrlPortHandler(url, timeout_margin_ms)
        self.stats = {"retries": 0, "reboots": 0, "alerts": 0}
        self._torque: dict[int, bool] = {}
        self._goal: dict[int, int] = {}
        try:
            ok = self.port.setBaudRate(baudrate)
        except ValueError as exc:  # serial_for_url: unknown URL scheme
            hint = ""
            if url.lower().startswith(("dxlsim://", "lightsim://")):
                hint = " (simulator URLs need `import simulator.dxl` first)"
            raise DeviceFault(f"cannot open Dynamixel bus {url!r}: {exc}{hint}") from exc
        except (serial.SerialException, OSError) as exc:
            raise DeviceFault(
                f"cannot open Dynamixel bus {url!r}: {exc} (busy, missing, or no permission?)"
            ) from exc
        if not ok:
            raise DeviceFault(f"cannot open Dynamixel bus {url!r} at {baudrate} baud")
        self.low_latency = _set_low_latency(url)

    # -- core transaction -----------------------------------------------------------------
    def _transact(
        self,
        servo_id: int | None,
        what: str,
        fn: Callable[[], tuple[Any, int, int]],
        expect_len: int | None = None,
    ) -> tuple[Any, int]:
        """Run one SDK exchange with retries; returns (data, error byte)."""
        attempts = self.retries + 1
        result = COMM_SUCCESS
        for attempt in range(attempts):
            try:
                data, result, error = fn()
            except IndexError:
                # the SDK indexes data it did not get (error status without data)
                data, result, error = None, COMM_RX_CORRUPT, 0
            finally:
                self.port.is_using = False  # never leave the SDK's port flag stuck
            if result == COMM_SUCCESS and (error & 0x7F) == _ERR_CRC:
                result = COMM_RX_CORRUPT  # the servo saw a corrupt instruction: resend
            if (
                result == COMM_SUCCESS
                and expect_len is not None
                and not (error & 0x7F)
                and (data is None or len(data) != expect_len)
            ):
                result = COMM_RX_CORRUPT
            if result == COMM_SUCCESS:
                return data, error
            if result not in _RETRYABLE:
                break
            if attempt + 1 < attempts:
                self.stats["retries"] += 1
        raise DynamixelCommError(servo_id, result, what, attempt + 1)

    def _checked(
        self,
        servo_id: int,
        what: str,
        op: Callable[[], tuple[Any, int]],
        check_alert: bool = True,
        _recovered: bool = False,
    ) -> Any:
        """Run `op` (-> data, error) and act on the error byte."""
        with self.lock:
            data, error = op()
            if error & _ALERT and check_alert:
                self._on_alert(servo_id, what, _recovered)
                return self._checked(servo_id, what, op, check_alert, _recovered=True)
            if error & 0x7F:
                raise DynamixelError(servo_id, error, what)
            return data

    def _on_alert(self, servo_id: int, what: str, recovered: bool) -> None:
        self.stats["alerts"] += 1
        status = self._read_raw(servo_id, ADDR["hardware_error_status"], 1)
        if self.on_alert == "stop":
            raise HardwareAlert(servo_id, status, what)
        if recovered:
            raise HardwareAlert(servo_id, status, what, note="; still present after reboot")
        self._recover(servo_id, what)

    def _recover(self, servo_id: int, what: str) -> None:
        """REBOOT, then restore what this bus had commanded (torque, last goal)."""
        self.reboot(servo_id)
        self.stats["reboots"] += 1
        self.clock.sleep(self.reboot_settle_s)
        status = self._read_raw(servo_id, ADDR["hardware_error_status"], 1)
        if status:  # the cause is still there (hot, jammed, bad supply): give up safely
            raise HardwareAlert(servo_id, status, what, note="; still present after reboot")
        if self._torque.get(servo_id):
            self.write(servo_id, ADDR["torque_enable"], 1, 1, check_alert=False)
            if servo_id in self._goal:
                self.write(
                    servo_id, ADDR["goal_position"], 4, self._goal[servo_id], check_alert=False
                )

    def _read_raw(self, servo_id: int, addr: int, size: int) -> int:
        data, _ = self._transact(
            servo_id,
            f"read {size} B at {addr}",
            lambda: self.packet.readTxRx(self.port, servo_id, addr, size),
            expect_len=size,
        )
        return int.from_bytes(bytes(data or b"\0" * size), "little")

    # -- public API -----------------------------------------------------------------------
    def ping(self, servo_id: int) -> int:
        """Model number of `servo_id` (1020 = XM430-W350, 1060 = XL430-W250)."""

        def op() -> tuple[Any, int]:
            return self._transact(servo_id, "ping", lambda: self.packet.ping(self.port, servo_id))

        return int(self._checked(servo_id, "ping", op, check_alert=False))

    def read_bytes(self, servo_id: int, addr: int, size: int, *, check_alert: bool = True) -> bytes:
        what = f"read {size} B at {addr}"

        def op() -> tuple[Any, int]:
            return self._transact(
                servo_id,
                what,
                lambda: self.packet.readTxRx(self.port, servo_id, addr, size),
                expect_len=size,
            )

        return bytes(self._checked(servo_id, what, op, check_alert))

    def read(
        self,
        servo_id: int,
        addr: int,
        size: int,
        *,
        signed: bool | None = None,
        check_alert: bool = True,
    ) -> int:
        """Read a register; two's complement is undone for signed registers (or `signed`)."""
        value = int.from_bytes(
            self.read_bytes(servo_id, addr, size, check_alert=check_alert), "little"
        )
        if signed if signed is not None else SIGNED_REGISTERS.get(addr) == size:
            value = to_signed(value, size)
        return value

    def write(
        self, servo_id: int, addr: int, size: int, value: int, *, check_alert: bool = True
    ) -> None:
        """Write a register (negative values are sent as two's complement)."""
        raw = to_unsigned(value, size).to_bytes(size, "little")
        what = f"write {value} ({size} B) at {addr}"

        def op() -> tuple[Any, int]:
            def call() -> tuple[Any, int, int]:
                result, error = self.packet.writeTxRx(self.port, servo_id, addr, size, list(raw))
                return None, result, error

            return self._transact(servo_id, what, call)

        self._checked(servo_id, what, op, check_alert)
        self._remember(servo_id, addr, size, value)

    def _remember(self, servo_id: int, addr: int, size: int, value: int) -> None:
        if addr == ADDR["torque_enable"] and size == 1:
            self._torque[servo_id] = bool(value)
        elif addr == ADDR["goal_position"] and size == 4:
            self._goal[servo_id] = int(value)

    def torque(self, servo_id: int, enabled: bool) -> None:
        # Turning torque off must work on a servo in alert (that is how one stops safely).
        self.write(servo_id, ADDR["torque_enable"], 1, int(bool(enabled)), check_alert=enabled)

    def sync_write(self, addr: int, size: int, values: Mapping[int, int]) -> None:
        """One SYNC WRITE packet for many servos (no status packets come back)."""
        if not values:
            return
        with self.lock:
            group = GroupSyncWrite(self.port, self.packet, addr, size)
            for sid, value in values.items():
                if not group.addParam(sid, list(to_unsigned(value, size).to_bytes(size, "little"))):
                    raise ValueError(f"duplicate servo id {sid} in sync_write")

            def call() -> tuple[Any, int, int]:
                return None, group.txPacket(), 0

            self._transact(None, f"sync write {size} B at {addr}", call)
            for sid, value in values.items():
                self._remember(sid, addr, size, value)

    def sync_read(
        self,
        addr: int,
        size: int,
        ids: Iterable[int],
        *,
        signed: bool | None = None,
        check_alert: bool = True,
    ) -> dict[int, int]:
        """One SYNC READ for many servos -> {id: value}.

        Built from the SDK's syncReadTx + readRx rather than GroupSyncRead, because
        GroupSyncRead discards each status packet's error byte (alerts would go unseen)."""
        ids = list(dict.fromkeys(ids))
        if not ids:
            return {}
        what = f"sync read {size} B at {addr}"
        is_signed = signed if signed is not None else SIGNED_REGISTERS.get(addr) == size

        def once() -> dict[int, tuple[bytes, int]]:
            state: dict[str, Any] = {"sid": None}

            def call() -> tuple[Any, int, int]:
                out: dict[int, tuple[bytes, int]] = {}
                result = self.packet.syncReadTx(self.port, addr, size, ids, len(ids), False)
                if result != COMM_SUCCESS:
                    return None, result, 0
                for sid in ids:
                    state["sid"] = sid
                    data, result, error = self.packet.readRx(self.port, sid, size)
                    if result != COMM_SUCCESS:
                        return None, result, 0
                    if not (error & 0x7F) and len(data) != size:
                        return None, COMM_RX_CORRUPT, 0
                    out[sid] = (bytes(data), error)
                return out, COMM_SUCCESS, 0

            data, _ = self._transact(None, what, call)
            return data

        with self.lock:
            for recovered in (False, True):
                replies = once()
                alerted = [sid for sid, (_, e) in replies.items() if e & _ALERT]
                if not (alerted and check_alert):
                    break
                for sid in alerted:
                    self._on_alert(sid, what, recovered)
            for sid, (_, error) in replies.items():
                if error & 0x7F:
                    raise DynamixelError(sid, error, what)
            out = {}
            for sid, (data, _) in replies.items():
                value = int.from_bytes(data, "little")
                out[sid] = to_signed(value, size) if is_signed else value
            return out

    def reboot(self, servo_id: int) -> None:
        """REBOOT: clears a tripped shutdown; torque comes back off."""

        def op() -> tuple[Any, int]:
            def call() -> tuple[Any, int, int]:
                result, error = self.packet.reboot(self.port, servo_id)
                return None, result, error

            return self._transact(servo_id, "reboot", call)

        self._checked(servo_id, "reboot", op, check_alert=False)

    def hardware_error(self, servo_id: int) -> int:
        return self.read(servo_id, ADDR["hardware_error_status"], 1, check_alert=False)

    def close(self) -> None:
        with self.lock:
            if self.port.is_open:
                self.port.closePort()

    def __enter__(self) -> DynamixelBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DynamixelAxis:
    """One rotary axis on a Dynamixel servo in position mode (implements `Axis`).

    Parameters
    ----------
    bus, servo_id, name: where the servo is and what the axis is called in messages.
    gear_ratio: servo turns per axis turn. direction: +1 or −1.
    zero_offset_rad: axis angle at servo tick 0. limits_rad: soft limits (axis angles).
    profile_velocity / profile_acceleration: written at construction if given (RAM registers,
        allowed with torque on); units 0.229 rev/min and 214.577 rev/min².
    tolerance_ticks: arrival tolerance for `wait`, in servo ticks.
    poll_s: clock time between polls in `wait`.
    """

    def __init__(
        self,
        bus: DynamixelBus,
        servo_id: int,
        name: str,
        gear_ratio: float = 1.0,
        zero_offset_rad: float = 0.0,
        direction: int = 1,
        limits_rad: tuple[float, float] = (-math.inf, math.inf),
        profile_velocity: int | None = None,
        profile_acceleration: int | None = None,
        tolerance_ticks: int = 8,
        poll_s: float = 0.05,
    ) -> None:
        if direction not in (1, -1):
            raise ValueError(f"{name}: direction must be +1 or -1, got {direction}")
        if gear_ratio <= 0:
            raise ValueError(f"{name}: gear_ratio must be > 0, got {gear_ratio}")
        lo, hi = limits_rad
        if not lo < hi:
            raise ValueError(f"{name}: limits_rad must be (lo, hi) with lo < hi, got {limits_rad}")
        self.bus, self.servo_id, self.name = bus, servo_id, name
        self.gear_ratio, self.zero_offset_rad, self.direction = (
            gear_ratio,
            zero_offset_rad,
            direction,
        )
        self.limits_rad = (float(lo), float(hi))
        self.tolerance_ticks = tolerance_ticks
        self.poll_s = poll_s
        self._goal_ticks: int | None = None
        self._last_ticks: int | None = None  # last Present Position seen (for move ETAs)
        self._eta: float | None = None  # clock time the current move should end
        try:
            self.model_number = bus.ping(servo_id)
        except DeviceFault as exc:
            raise DeviceFault(f"axis {name}: servo {servo_id} does not answer: {exc}") from exc
        if profile_acceleration is not None:
            bus.write(servo_id, ADDR["profile_acceleration"], 4, profile_acceleration)
        if profile_velocity is not None:
            bus.write(servo_id, ADDR["profile_velocity"], 4, profile_velocity)
        else:
            profile_velocity = bus.read(servo_id, ADDR["profile_velocity"], 4)
        if profile_acceleration is None:
            profile_acceleration = bus.read(servo_id, ADDR["profile_acceleration"], 4)
        self.profile_velocity, self.profile_acceleration = profile_velocity, profile_acceleration

    # -- conversions ----------------------------------------------------------------------
    def angle_from_ticks(self, ticks: float) -> float:
        return self.zero_offset_rad + self.direction * ticks * (2 * math.pi / TICKS_PER_REV) / (
            self.gear_ratio
        )

    def ticks_from_angle(self, angle_rad: float) -> int:
        return round(
            (angle_rad - self.zero_offset_rad)
            * self.direction
            * self.gear_ratio
            * TICKS_PER_REV
            / (2 * math.pi)
        )

    def check_target(self, angle_rad: float) -> int:
        lo, hi = self.limits_rad
        if not (lo <= angle_rad <= hi):  # also rejects NaN
            raise ValueError(
                f"axis {self.name}: target {math.degrees(angle_rad):.3f} deg is outside its "
                f"limits [{math.degrees(lo):.3f}, {math.degrees(hi):.3f}] deg"
            )
        return self.ticks_from_angle(angle_rad)

    def move_duration_s(self, distance_ticks: float) -> float | None:
        """Rest-to-rest time of the servo's profile over `distance_ticks` (e-Manual units:
        v = PV·0.229·4096/60 tick/s, a = PA·214.577·4096/3600 tick/s², PA = 0 → a = ∞):
        trapezoid d/v + v/a when d ≥ v²/a, else triangle 2√(d/a). None when PV = 0 (the
        servo then runs at its Velocity Limit, not known here)."""
        if not self.profile_velocity:
            return None
        v = self.profile_velocity * 0.229 * TICKS_PER_REV / 60.0
        a = (
            math.inf
            if self.profile_acceleration == 0
            else self.profile_acceleration * 214.577 * TICKS_PER_REV / 3600.0
        )
        return float(trapezoid_time_s(distance_ticks, v, a))

    def _started(self, goal_ticks: int) -> None:
        """Record a new goal and, when the start is known, when the move should be over."""
        self._eta = None
        if self._last_ticks is not None and self._goal_ticks != goal_ticks:
            duration = self.move_duration_s(goal_ticks - self._last_ticks)
            if duration is not None:
                self._eta = self.bus.clock.now() + duration
        self._goal_ticks = goal_ticks

    # -- Axis protocol --------------------------------------------------------------------
    def move_to(self, angle_rad: float) -> None:
        ticks = self.check_target(angle_rad)
        self.bus.write(self.servo_id, ADDR["goal_position"], 4, ticks)
        self._started(ticks)

    def position(self) -> float:
        self._last_ticks = self.bus.read(self.servo_id, ADDR["present_position"], 4)
        return self.angle_from_ticks(self._last_ticks)

    def _poll(self) -> tuple[bool, int]:
        # one READ of Moving(122)..Present Position(132..135)
        raw = self.bus.read_bytes(self.servo_id, ADDR["moving"], 14)
        self._last_ticks = to_signed(int.from_bytes(raw[10:14], "little"), 4)
        return bool(raw[0]), self._last_ticks

    def wait(self, timeout_s: float) -> None:
        """Sleep (on the clock) until the move's expected end, then poll Moving and Present
        Position every `poll_s` until arrived within `tolerance_ticks`, or AxisTimeout. The
        expected end comes from the profile and the last known position, so a move costs one
        or two status reads instead of one per poll."""
        clock = self.bus.clock
        t0 = clock.now()
        if self._eta is not None:
            clock.sleep(min(self._eta - t0, timeout_s))
            self._eta = None
        while True:
            moving, ticks = self._poll()
            near = self._goal_ticks is None or abs(ticks - self._goal_ticks) <= self.tolerance_ticks
            if not moving and near:
                return
            if clock.now() - t0 >= timeout_s:
                goal = (
                    f"{math.degrees(self.angle_from_ticks(self._goal_ticks)):.3f} deg"
                    if self._goal_ticks is not None
                    else "its goal"
                )
                raise AxisTimeout(
                    f"axis {self.name} (servo {self.servo_id}) did not reach {goal} within "
                    f"{timeout_s:g} s; it is at {math.degrees(self.angle_from_ticks(ticks)):.3f}"
                    f" deg{' and still moving' if moving else ''}"
                )
            clock.sleep(self.poll_s)

    def torque(self, enabled: bool) -> None:
        self.bus.torque(self.servo_id, enabled)
        self._eta = None
        if not enabled:
            self._goal_ticks = None

    def stop(self) -> None:
        """Hold where it is now: goal := present position."""
        ticks = self.bus.read(self.servo_id, ADDR["present_position"], 4, check_alert=False)
        if self.bus.read(self.servo_id, ADDR["torque_enable"], 1, check_alert=False):
            self.bus.write(self.servo_id, ADDR["goal_position"], 4, ticks, check_alert=False)
        self._goal_ticks, self._last_ticks, self._eta = ticks, ticks, None

    def status(self) -> dict[str, Any]:
        """Temperature, input voltage and Hardware Error Status, in one READ of 70..146 (gaps
        in the control table read as 0). Never triggers alert handling: it is what a safe
        stop records."""
        first = ADDR["hardware_error_status"]
        last = ADDR["present_temperature"]
        raw = self.bus.read_bytes(self.servo_id, first, last - first + 1, check_alert=False)

        def reg(addr: int, size: int) -> int:
            return int.from_bytes(raw[addr - first : addr - first + size], "little")

        hw = reg(ADDR["hardware_error_status"], 1)
        return {
            "servo_id": self.servo_id,
            "model": MODEL_NAMES.get(self.model_number, str(self.model_number)),
            "temperature_C": float(reg(ADDR["present_temperature"], 1)),
            "voltage_V": reg(ADDR["present_input_voltage"], 2) / 10.0,
            "hardware_error": hw,
            "hardware_error_names": decode_hardware_error(hw),
        }


def _by_bus(axes: Sequence[DynamixelAxis]) -> dict[int, tuple[DynamixelBus, list[int]]]:
    groups: dict[int, tuple[DynamixelBus, list[int]]] = {}
    for k, ax in enumerate(axes):
        groups.setdefault(id(ax.bus), (ax.bus, []))[1].append(k)
    return groups


def move_together(axes: Sequence[DynamixelAxis], angles_rad: Sequence[float]) -> None:
    """Start all axes at once: every target is checked first, then one SYNC WRITE per bus."""
    if len(axes) != len(angles_rad):
        raise ValueError(f"{len(axes)} axes but {len(angles_rad)} angles")
    ticks = [ax.check_target(a) for ax, a in zip(axes, angles_rad, strict=True)]
    for bus, idx in _by_bus(axes).values():
        bus.sync_write(ADDR["goal_position"], 4, {axes[k].servo_id: ticks[k] for k in idx})
        for k in idx:
            axes[k]._started(ticks[k])


def read_positions(axes: Sequence[DynamixelAxis]) -> list[float]:
    """Measured angles of `axes` (same order), one SYNC READ per bus."""
    out: list[float] = [math.nan] * len(axes)
    for bus, idx in _by_bus(axes).values():
        values = bus.sync_read(ADDR["present_position"], 4, [axes[k].servo_id for k in idx])
        for k in idx:
            axes[k]._last_ticks = values[axes[k].servo_id]
            out[k] = axes[k].angle_from_ticks(axes[k]._last_ticks)
    return out

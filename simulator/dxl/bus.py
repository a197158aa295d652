"""An emulated Dynamixel Protocol 2.0 bus: servos by ID, bytes in, status bytes out.

`EmulatedBus.handle(data)` takes whatever the host wrote (any chunking) and returns the
status packets the servos put on the wire, as `Reply` objects (bytes + wall-time delay). It
replies at once — the ROBOTIS SDK busy-polls against wall-clock timeouts, so only injected
faults ever make it time out. Transports (`transport.PtyTransport`, the `dxlsim://` pyserial
handler) move those bytes.

Instructions: PING (unicast and broadcast, replies in ID order), READ, WRITE, REG_WRITE,
ACTION, REBOOT, SYNC_READ (replies in the order of the IDs in the instruction), SYNC_WRITE,
BULK_READ, BULK_WRITE, and FAST_SYNC_READ (one shared status packet). Broadcast (FE) writes
get no reply. Status Return Level (68) is honoured: 0 = only PING replies, 1 = PING and
reads, 2 = all.

Ground truth for the simulated camera: `bus.servo(id).true_position_ticks()` (Present
Position plus any injected position offset), or `bus.true_positions_ticks()` for all.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable

import numpy as np

from acquisition.clock import Clock
from simulator.dxl import protocol as P
from simulator.dxl.faults import FaultInjector, FiredAlert, Reply, ReplyFaults, ScheduledAlert
from simulator.dxl.servo import (
    HW_ELECTRICAL_SHOCK,
    HW_ENCODER,
    HW_INPUT_VOLTAGE,
    HW_OVERHEAT,
    HW_OVERLOAD,
    Servo,
)

__all__ = ["EmulatedBus", "ALERT_BITS"]

ALERT_BITS = {
    "voltage": HW_INPUT_VOLTAGE,
    "overheat": HW_OVERHEAT,
    "encoder": HW_ENCODER,
    "electrical_shock": HW_ELECTRICAL_SHOCK,
    "overload": HW_OVERLOAD,
}


def _u16(b: bytes, i: int) -> int:
    return b[i] | (b[i + 1] << 8)


class EmulatedBus:
    """A bus of emulated X-series servos sharing one clock.

    >>> from acquisition.clock import VirtualClock
    >>> bus = EmulatedBus(VirtualClock())
    >>> _ = bus.add_servo(1, "XM430-W350")
    """

    def __init__(self, clock: Clock, rng: np.random.Generator | int | None = 0) -> None:
        self.clock = clock
        self.servos: dict[int, Servo] = {}
        self.faults = FaultInjector(rng)
        self.lock = threading.RLock()
        self._decoder = P.PacketDecoder()
        self.packets_in = 0  # instruction packets received (for scheduled faults, stats)
        self.traffic: list[tuple[str, bytes]] | None = None  # set to [] to record the wire
        self.fired_alerts: list[FiredAlert] = []  # scheduled alerts that have fired

    # -- setup ----------------------------------------------------------------------------
    def add_servo(self, dxl_id: int, model: str = "XM430-W350", **kwargs) -> Servo:
        if not 0 <= dxl_id <= P.MAX_ID:
            raise ValueError(f"servo id must be in 0..{P.MAX_ID}, got {dxl_id}")
        if dxl_id in self.servos:
            raise ValueError(f"servo id {dxl_id} is already on the bus")
        with self.lock:
            s = Servo(dxl_id, model, clock=self.clock, **kwargs)
            self.servos[dxl_id] = s
            return s

    def servo(self, dxl_id: int) -> Servo:
        return self.servos[dxl_id]

    def true_positions_ticks(self) -> dict[int, float]:
        """Physical horn positions of all servos (Present Position + injected offset)."""
        with self.lock:
            return {i: s.true_position_ticks() for i, s in self.servos.items()}

    # -- fault injection (thin front to FaultInjector + servo state) ----------------------
    def set_reply_faults(self, faults: ReplyFaults, servo_id: int | None = None) -> None:
        with self.lock:
            self.faults.configure(faults, servo_id)

    def inject_next(
        self, kind: str, servo_id: int | None = None, count: int = 1, delay_s: float = 0.1
    ) -> None:
        with self.lock:
            self.faults.inject_next(kind, servo_id, count, delay_s)

    def inject_alert(
        self,
        servo_id: int,
        kind: str | int = "overload",
        *,
        at_time_s: float | None = None,
        after_packets: int | None = None,
        persistent: bool = False,
        while_moving: bool = False,
    ) -> None:
        """Raise a hardware alert (name from ALERT_BITS or raw reg-70 bits): now, at a clock
        time, after N more instruction packets, or (`while_moving`) at the first packet that
        finds the servo mid-move (combinable with the others: then the first move after
        them). `persistent` survives REBOOT until `clear_fault(servo_id)`."""
        bits = ALERT_BITS[kind] if isinstance(kind, str) else int(kind)
        with self.lock:
            if at_time_s is None and after_packets is None and not while_moving:
                self.servos[servo_id].raise_hw_error(bits, persistent=persistent)
                return
            after = None if after_packets is None else self.packets_in + after_packets
            armed = self.clock.now() if while_moving else None
            self.faults.schedule_alert(
                ScheduledAlert(servo_id, bits, at_time_s, after, persistent, while_moving, armed)
            )

    def clear_fault(self, servo_id: int) -> None:
        with self.lock:
            self.servos[servo_id].clear_fault()

    def set_stuck(self, servo_id: int, stuck: bool = True) -> None:
        with self.lock:
            self.servos[servo_id].set_stuck(stuck)

    def set_position_offset(self, servo_id: int, ticks: float) -> None:
        """True angle = reported angle + `ticks` (a mounting error for calibration to find)."""
        with self.lock:
            self.servos[servo_id].position_offset_ticks = ticks

    def _fire_alerts(self) -> None:
        now = self.clock.now()
        keep = []
        for a in self.faults.alerts:
            servo = self.servos.get(a.servo_id)
            timed = a.at_time_s is not None or a.after_packets is not None
            due = not timed or (
                (a.at_time_s is not None and now >= a.at_time_s)
                or (a.after_packets is not None and self.packets_in >= a.after_packets)
            )
            at_s = None
            if a.while_moving and servo is not None:
                # Halfway through the first move that starts once the alert is due. The host
                # may not look during the move (with a virtual clock it sleeps through it), so
                # the alert is dated to mid-move and the horn frozen where it was then.
                mid = servo.mid_move_time(a.armed_at_s if a.armed_at_s is not None else now)
                due = due and mid is not None and now >= mid
                at_s = mid
            if due and servo is not None:
                moving, to_goal = servo.motion_state(at_s)
                servo.raise_hw_error(a.bits, persistent=a.persistent, at_s=at_s)
                t = now if at_s is None else at_s
                self.fired_alerts.append(FiredAlert(a.servo_id, a.bits, t, moving, to_goal))
            else:
                keep.append(a)
        self.faults.alerts = keep

    # -- wire -----------------------------------------------------------------------------
    def reset_input(self) -> None:
        """Forget a partial instruction (the host flushed its side)."""
        with self.lock:
            self._decoder.clear()

    def feed(self, data: bytes) -> bytes:
        """Convenience: handle `data` and return all reply bytes concatenated (delays ignored)."""
        return b"".join(r.data for r in self.handle(data))

    def handle(self, data: bytes) -> list[Reply]:
        with self.lock:
            if self.traffic is not None:
                self.traffic.append(("rx", bytes(data)))
            out: list[Reply] = []
            for pkt in self._decoder.feed(data):
                self.packets_in += 1
                self._fire_alerts()
                out.extend(self._dispatch(pkt))
            if self.traffic is not None:
                for r in out:
                    self.traffic.append(("tx", r.data))
            return out

    def _status(
        self,
        servo: Servo,
        err: int,
        data: bytes = b"",
        *,
        is_read: bool = False,
        is_ping: bool = False,
    ) -> list[Reply]:
        level = servo._get("status_return_level")  # RAM, no live refresh needed
        if not is_ping and (level == 0 or (level == 1 and not is_read)):
            return []
        error = err | servo.error_bits()
        # An error status carries no data (hence the SDK's IndexError); an alert alone does.
        pkt = P.encode_status(servo.dxl_id, error, b"" if err else data)
        reply = self.faults.apply(servo.dxl_id, pkt)
        return [] if reply is None else [reply]

    def _dispatch(self, pkt: P.Packet) -> list[Reply]:
        inst, params, did = pkt.instruction, pkt.params, pkt.dxl_id
        unicast = did in self.servos
        if not pkt.crc_ok:
            return self._status(self.servos[did], P.ERRNUM_CRC) if unicast else []
        if inst == P.INST_PING:
            if did == P.BROADCAST_ID:
                out: list[Reply] = []
                for i in sorted(self.servos):
                    out += self._ping(self.servos[i])
                return out
            return self._ping(self.servos[did]) if unicast else []
        if inst in (
            P.INST_SYNC_READ,
            P.INST_SYNC_WRITE,
            P.INST_BULK_READ,
            P.INST_BULK_WRITE,
            P.INST_FAST_SYNC_READ,
        ):
            if did != P.BROADCAST_ID:
                return self._status(self.servos[did], P.ERRNUM_INSTRUCTION) if unicast else []
            if inst == P.INST_FAST_SYNC_READ:
                return self._fast_sync_read(params)
            return self._group(inst, params)
        if inst == P.INST_ACTION:
            targets = (
                self.servos.values()
                if did == P.BROADCAST_ID
                else ([self.servos[did]] if unicast else [])
            )
            out = []
            for s in list(targets):
                err = s.action()
                if did != P.BROADCAST_ID:
                    out += self._status(s, err)
            return out
        if did == P.BROADCAST_ID:
            for s in list(self.servos.values()):
                self._unicast(s, inst, params)  # executed, never answered
            return []
        if not unicast:
            return []
        return self._unicast(self.servos[did], inst, params)

    def _ping(self, s: Servo) -> list[Reply]:
        m = s.model_number()
        return self._status(s, 0, bytes([m & 0xFF, m >> 8, s.firmware_version()]), is_ping=True)

    def _unicast(self, s: Servo, inst: int, params: bytes) -> list[Reply]:
        if inst == P.INST_READ:
            if len(params) != 4:
                return self._status(s, P.ERRNUM_DATA_LENGTH, is_read=True)
            err, data = s.read(_u16(params, 0), _u16(params, 2))
            return self._status(s, err, data, is_read=True)
        if inst in (P.INST_WRITE, P.INST_REG_WRITE):
            if len(params) < 3:
                return self._status(s, P.ERRNUM_DATA_LENGTH)
            addr, data = _u16(params, 0), bytes(params[2:])
            err = s.write(addr, data) if inst == P.INST_WRITE else s.reg_write(addr, data)
            return self._status(s, err)
        if inst == P.INST_REBOOT:
            s.reboot()  # the status reflects the rebooted device
            return self._status(s, 0)
        if inst == P.INST_CLEAR:
            return self._status(s, 0)
        return self._status(s, P.ERRNUM_INSTRUCTION)

    def _fast_sync_read(self, params: bytes) -> list[Reply]:
        """FAST SYNC READ (0x8A): the servos answer together in ONE status packet with ID FE:
        per servo [error, id, data..., crc], where each crc is the running CRC of the packet
        so far and the last one is the packet CRC. Not byte-stuffed (the SDK decodes this
        packet without unstuffing). A missing servo breaks the chain: the packet stops there
        (the host sees a partial packet)."""
        if len(params) < 5:
            return []
        addr, length = _u16(params, 0), _u16(params, 2)
        ids = list(params[4:])
        total = 1 + len(ids) * (length + 4)  # inst + records (the last "crc" is the packet's)
        if total > 0xFFFF:
            # LEN is 16 bits: no servo can form this reply, so none is sent (found by fuzzing:
            # building it raised ValueError).
            return []
        pkt = bytearray(P.HEADER) + bytes([P.BROADCAST_ID, total & 0xFF, total >> 8])
        pkt.append(P.INST_STATUS)
        complete = True
        for did in ids:
            s = self.servos.get(did)
            if s is None:
                complete = False
                break
            err, data = s.read(addr, length)
            pkt += bytes([err | s.error_bits(), did])
            pkt += data if not err else bytes(length)
            crc = P.crc16(pkt)
            pkt += bytes([crc & 0xFF, crc >> 8])
        reply = self.faults.apply(ids[0], bytes(pkt)) if complete else None
        if not complete:
            return [Reply(bytes(pkt))] if len(pkt) > 8 else []
        return [] if reply is None else [reply]

    def _group(self, inst: int, params: bytes) -> list[Reply]:
        out: list[Reply] = []
        if inst in (P.INST_SYNC_READ, P.INST_SYNC_WRITE):
            if len(params) < 4:
                return []
            addr, length = _u16(params, 0), _u16(params, 2)
            rest = params[4:]
            if inst == P.INST_SYNC_READ:
                for did in rest:  # replies in the order of the instruction's ID list
                    if did in self.servos:
                        s = self.servos[did]
                        err, data = s.read(addr, length)
                        out += self._status(s, err, data, is_read=True)
                return out
            step = 1 + length
            for k in range(0, len(rest) - step + 1, step):
                did = rest[k]
                if did in self.servos:
                    self.servos[did].write(addr, bytes(rest[k + 1 : k + step]))
            return out
        if inst == P.INST_BULK_READ:
            for k in range(0, len(params) - 4, 5):
                did, addr, length = params[k], _u16(params, k + 1), _u16(params, k + 3)
                if did in self.servos:
                    s = self.servos[did]
                    err, data = s.read(addr, length)
                    out += self._status(s, err, data, is_read=True)
            return out
        # BULK_WRITE: (id, addr, len, data...)*
        k = 0
        while k + 5 <= len(params):
            did, addr, length = params[k], _u16(params, k + 1), _u16(params, k + 3)
            data = bytes(params[k + 5 : k + 5 + length])
            if did in self.servos:
                self.servos[did].write(addr, data)
            k += 5 + length
        return out

    def ids(self) -> Iterable[int]:
        return sorted(self.servos)

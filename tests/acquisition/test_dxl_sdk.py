"""The real, unmodified `dynamixel_sdk` against the emulator, over a pseudo-terminal and over
the in-process `dxlsim://` URL; then the gonio driver (`acquisition.dynamixel`) on top.

Ground truth is independent of the emulator: SDK result/error codes as ROBOTIS defines them,
register semantics from the X-series e-Manual, and motion times recomputed here from the
e-Manual's units (0.229 rev/min, 214.577 rev/min², 4096 ticks/rev).
"""

from __future__ import annotations

import math
import time
import uuid
from types import SimpleNamespace

import pytest
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupBulkRead,
    GroupBulkWrite,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from acquisition.clock import VirtualClock
from acquisition.dynamixel import (
    DynamixelAxis,
    DynamixelBus,
    DynamixelCommError,
    DynamixelError,
    HardwareAlert,
    UrlPortHandler,
    move_together,
    read_positions,
)
from acquisition.protocols import Axis, AxisTimeout, DeviceFault
from simulator.dxl import EmulatedBus, PtyTransport, ReplyFaults, register_bus, unregister_bus
from simulator.dxl import protocol as P

# e-Manual control table addresses
TORQUE, LED, HW_ERR, PROF_ACC, PROF_VEL, GOAL, MOVING, PRESENT = 64, 65, 70, 108, 112, 116, 122, 132
OP_MODE, HOMING, MAX_LIM, MIN_LIM, MODEL, TEMP, VOLT = 11, 20, 48, 52, 0, 146, 144

TRANSPORTS = ["pty", "dxlsim"]


def _open(bus: EmulatedBus, transport: str):
    """(url, closer) for `bus` on the given transport."""
    if transport == "pty":
        t = PtyTransport(bus)
        return t.port_path, t.close
    name = f"test-{uuid.uuid4().hex[:8]}"
    register_bus(name, bus)
    return f"dxlsim://{name}", lambda: unregister_bus(name)


@pytest.fixture(params=TRANSPORTS)
def sdk(request):
    """Raw SDK session: plain PortHandler on the pty; a serial_for_url opener for dxlsim://."""
    clock = VirtualClock()
    bus = EmulatedBus(clock, rng=1)
    bus.add_servo(1, "XM430-W350")
    bus.add_servo(2, "XL430-W250")
    bus.add_servo(5, "XM430-W350", position_ticks=1000)
    url, closer = _open(bus, request.param)
    port = PortHandler(url) if request.param == "pty" else UrlPortHandler(url)
    assert port.setBaudRate(57600)
    yield SimpleNamespace(
        bus=bus, clock=clock, port=port, ph=PacketHandler(2.0), transport=request.param
    )
    port.closePort()
    closer()


# ---- raw SDK: basic instructions ------------------------------------------------------------


def test_ping_models_and_missing_id(sdk) -> None:
    ph, port = sdk.ph, sdk.port
    assert ph.ping(port, 1) == (1020, COMM_SUCCESS, 0)  # XM430-W350
    assert ph.ping(port, 2) == (1060, COMM_SUCCESS, 0)  # XL430-W250
    assert ph.ping(port, 9)[1] == COMM_RX_TIMEOUT  # nobody there


def test_broadcast_ping() -> None:
    # dxlsim only: the SDK waits out its full broadcast window (~1.4 s wall) on any transport
    bus = EmulatedBus(VirtualClock())
    for i, model in ((7, "XL430-W250"), (3, "XM430-W350")):
        bus.add_servo(i, model)
    url, closer = _open(bus, "dxlsim")
    port = UrlPortHandler(url)
    assert port.setBaudRate(57600)
    found, result = PacketHandler(2.0).broadcastPing(port)
    port.closePort()
    closer()
    assert result == COMM_SUCCESS
    assert found == {3: [1020, 48], 7: [1060, 48]}  # [model number, firmware version]


def test_read_write_round_trip(sdk) -> None:
    ph, port = sdk.ph, sdk.port
    assert ph.read2ByteTxRx(port, 2, MODEL) == (1060, COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, LED, 1) == (COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 1, LED) == (1, COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 1, PROF_VEL, 123) == (COMM_SUCCESS, 0)
    assert ph.read4ByteTxRx(port, 1, PROF_VEL) == (123, COMM_SUCCESS, 0)
    assert ph.read4ByteTxRx(port, 5, PRESENT) == (1000, COMM_SUCCESS, 0)


def test_sync_write_and_sync_read(sdk) -> None:
    ph, port = sdk.ph, sdk.port
    values = {5: 77, 1: 31, 2: 150}
    gw = GroupSyncWrite(port, ph, PROF_VEL, 4)
    for i, v in values.items():
        assert gw.addParam(i, list(v.to_bytes(4, "little")))
    assert gw.txPacket() == COMM_SUCCESS
    sdk.bus.traffic = []
    gr = GroupSyncRead(port, ph, PROF_VEL, 4)
    for i in values:
        assert gr.addParam(i)
    assert gr.txRxPacket() == COMM_SUCCESS
    for i, v in values.items():
        assert gr.isAvailable(i, PROF_VEL, 4)
        assert gr.getData(i, PROF_VEL, 4) == v
    # status packets come back in the order of the IDs in the instruction (5, 1, 2)
    replies = [d for kind, d in sdk.bus.traffic if kind == "tx"]
    assert [r[4] for r in replies] == [5, 1, 2]


def test_fast_sync_read(sdk) -> None:
    ph, port = sdk.ph, sdk.port
    for i, v in {1: 5, 2: 6, 5: 7}.items():
        assert ph.write4ByteTxRx(port, i, PROF_ACC, 1000 * v + i) == (COMM_SUCCESS, 0)
    gr = GroupSyncRead(port, ph, PROF_ACC, 4)
    for i in (2, 5, 1):
        gr.addParam(i)
    assert gr.fastSyncRead() == COMM_SUCCESS
    assert {i: gr.getData(i, PROF_ACC, 4) for i in (1, 2, 5)} == {1: 5001, 2: 6002, 5: 7005}
    gr.addParam(9)  # absent: the shared packet breaks off, the SDK sees a partial packet
    assert gr.fastSyncRead() == COMM_RX_CORRUPT


def test_sync_read_with_missing_servo_times_out(sdk) -> None:
    gr = GroupSyncRead(sdk.port, sdk.ph, PRESENT, 4)
    gr.addParam(1)
    gr.addParam(9)
    assert gr.txRxPacket() == COMM_RX_TIMEOUT


def test_bulk_read_and_bulk_write(sdk) -> None:
    ph, port = sdk.ph, sdk.port
    bw = GroupBulkWrite(port, ph)
    assert bw.addParam(1, LED, 1, [1])
    assert bw.addParam(2, PROF_ACC, 4, list((42).to_bytes(4, "little")))
    assert bw.txPacket() == COMM_SUCCESS
    br = GroupBulkRead(port, ph)
    assert br.addParam(1, LED, 1)
    assert br.addParam(2, PROF_ACC, 4)
    assert br.addParam(5, PRESENT, 4)
    assert br.txRxPacket() == COMM_SUCCESS
    assert br.getData(1, LED, 1) == 1
    assert br.getData(2, PROF_ACC, 4) == 42
    assert br.getData(5, PRESENT, 4) == 1000


def test_reg_write_then_action(sdk) -> None:
    ph, port = sdk.ph, sdk.port
    assert ph.regWriteTxRx(port, 1, LED, 1, [1]) == (COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 1, LED)[0] == 0  # registered, not yet executed
    assert ph.read1ByteTxRx(port, 1, 69)[0] == 1  # Registered Instruction flag
    ph.action(port, P.BROADCAST_ID)
    assert ph.read1ByteTxRx(port, 1, LED)[0] == 1


# ---- raw SDK: device errors -----------------------------------------------------------------


def test_eeprom_locked_while_torque_on(sdk) -> None:
    ph, port = sdk.ph, sdk.port
    assert ph.write1ByteTxRx(port, 1, OP_MODE, 4) == (COMM_SUCCESS, 0)  # torque off: allowed
    assert ph.write1ByteTxRx(port, 1, OP_MODE, 3) == (COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, OP_MODE, 4) == (COMM_SUCCESS, P.ERRNUM_ACCESS)
    assert ph.read1ByteTxRx(port, 1, OP_MODE)[0] == 3  # unchanged


def test_position_limits_range_length_and_access_errors(sdk) -> None:
    ph, port = sdk.ph, sdk.port
    assert ph.write4ByteTxRx(port, 1, MAX_LIM, 3000) == (COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 1, MIN_LIM, 1000) == (COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 1, GOAL, 3001) == (COMM_SUCCESS, P.ERRNUM_DATA_LIMIT)
    assert ph.write4ByteTxRx(port, 1, GOAL, 999) == (COMM_SUCCESS, P.ERRNUM_DATA_LIMIT)
    assert ph.read4ByteTxRx(port, 1, GOAL)[0] == 2048  # goal untouched (held position)
    assert ph.write4ByteTxRx(port, 1, PROF_ACC, 40000) == (COMM_SUCCESS, P.ERRNUM_DATA_RANGE)
    assert ph.write2ByteTxRx(port, 1, GOAL, 100) == (COMM_SUCCESS, P.ERRNUM_DATA_LENGTH)
    assert ph.write2ByteTxRx(port, 1, MODEL, 7) == (COMM_SUCCESS, P.ERRNUM_ACCESS)


def test_error_status_without_data_trips_sdk_indexerror(sdk) -> None:
    # Documents the SDK behaviour the driver must wrap: an error status carries no data, yet
    # readTxRx slices "data" after the error byte anyway — getting the 2 CRC bytes — and the
    # 4-byte helper then indexes past them.
    data, result, error = sdk.ph.readTxRx(sdk.port, 1, 200, 4)
    assert (result, error) == (COMM_SUCCESS, P.ERRNUM_ACCESS)
    assert len(data) == 2
    with pytest.raises(IndexError):
        sdk.ph.read4ByteTxRx(sdk.port, 1, 200)


def test_hardware_alert_shutdown_and_reboot(sdk) -> None:
    ph, port, bus = sdk.ph, sdk.port, sdk.bus
    assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (COMM_SUCCESS, 0)
    bus.inject_alert(1, "overload")
    # alert bit 7 on every status; the data still comes with it
    assert ph.read4ByteTxRx(port, 1, PRESENT) == (2048, COMM_SUCCESS, P.ERRBIT_ALERT)
    assert ph.read1ByteTxRx(port, 1, HW_ERR) == (1 << 5, COMM_SUCCESS, P.ERRBIT_ALERT)
    assert ph.read1ByteTxRx(port, 1, TORQUE)[0] == 0  # shutdown cleared torque
    assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (
        COMM_SUCCESS,
        P.ERRBIT_ALERT | P.ERRNUM_RESULT_FAIL,
    )
    assert ph.reboot(port, 1) == (COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 1, HW_ERR) == (0, COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, TORQUE, 1) == (COMM_SUCCESS, 0)
    assert ph.ping(port, 2) == (1060, COMM_SUCCESS, 0)  # other servos unaffected


def test_overheat_alert_persists_until_cool(sdk) -> None:
    ph, port, bus = sdk.ph, sdk.port, sdk.bus
    bus.servo(2).temperature_C = 85.0  # above the default Temperature Limit of 80 °C
    assert ph.read1ByteTxRx(port, 2, HW_ERR) == (1 << 2, COMM_SUCCESS, P.ERRBIT_ALERT)
    assert ph.read1ByteTxRx(port, 2, TEMP)[0] == 85
    ph.reboot(port, 2)
    assert ph.read1ByteTxRx(port, 2, HW_ERR)[0] == 1 << 2  # still hot: comes back
    bus.servo(2).temperature_C = 40.0
    ph.reboot(port, 2)
    assert ph.read1ByteTxRx(port, 2, HW_ERR) == (0, COMM_SUCCESS, 0)


def test_voltage_reading(sdk) -> None:
    # XM430-W350 recommended 12.0 V -> 120 in units of 0.1 V
    assert sdk.ph.read2ByteTxRx(sdk.port, 1, VOLT) == (120, COMM_SUCCESS, 0)


# ---- raw SDK: injected wire faults ----------------------------------------------------------


@pytest.mark.parametrize(
    ("kind", "expected"),
    [("drop", COMM_RX_TIMEOUT), ("truncate", COMM_RX_CORRUPT), ("bad_crc", COMM_RX_CORRUPT)],
)
def test_wire_faults_surface_as_sdk_results(sdk, kind: str, expected: int) -> None:
    ph, port = sdk.ph, sdk.port
    for _ in range(3):  # truncation length is random: try several
        sdk.bus.inject_next(kind, servo_id=1)
        assert ph.read4ByteTxRx(port, 1, PRESENT)[1] == expected
    assert ph.read4ByteTxRx(port, 1, PRESENT) == (2048, COMM_SUCCESS, 0)  # next one is fine
    assert sdk.bus.faults.counts[kind] == 3


def test_delay_fault_short_and_long(sdk) -> None:
    ph, port = sdk.ph, sdk.port
    # The SDK waits 10 bit-times per byte + 2·16 ms + 2 ms ≈ 36 ms at 57600 baud for a
    # status packet: a 2 ms delay is tolerated, a 250 ms delay is a timeout.
    sdk.bus.inject_next("delay", servo_id=1, delay_s=0.002)
    assert ph.ping(port, 1) == (1020, COMM_SUCCESS, 0)
    sdk.bus.inject_next("delay", servo_id=1, delay_s=0.25)
    assert ph.ping(port, 1)[1] == COMM_RX_TIMEOUT
    time.sleep(0.3)  # let the late packet arrive; the next transaction flushes it
    assert ph.ping(port, 1) == (1020, COMM_SUCCESS, 0)


def test_stuck_axis_and_position_offset(sdk) -> None:
    ph, port, bus = sdk.ph, sdk.port, sdk.bus
    bus.set_position_offset(1, 37)
    ph.write1ByteTxRx(port, 1, TORQUE, 1)
    bus.set_stuck(1, True)
    ph.write4ByteTxRx(port, 1, GOAL, 3000)
    sdk.clock.advance(10.0)
    assert ph.read4ByteTxRx(port, 1, PRESENT)[0] == 2048
    assert ph.read1ByteTxRx(port, 1, MOVING)[0] == 1  # still trying
    assert bus.servo(1).true_position_ticks() == 2048 + 37
    bus.set_stuck(1, False)
    sdk.clock.advance(10.0)
    assert ph.read4ByteTxRx(port, 1, PRESENT)[0] == 3000
    assert ph.read1ByteTxRx(port, 1, MOVING)[0] == 0
    assert bus.true_positions_ticks()[1] == 3000 + 37


# ---- motion model vs the e-Manual formula ---------------------------------------------------


def manual_profile(d: float, pv: int, pa: int) -> tuple[float, callable]:
    """Rest-to-rest profile from the e-Manual units, written independently of the emulator:
    returns (duration_s, x(t) in ticks travelled)."""
    v = pv * 0.229 / 60.0 * 4096.0  # tick/s
    if pa == 0:
        return d / v, lambda t: min(v * t, d)
    a = pa * 214.577 / 3600.0 * 4096.0  # tick/s²
    t_acc = v / a
    if a * t_acc**2 > d:  # accelerating to v and back would overshoot: triangle
        t_acc = math.sqrt(d / a)
        v = a * t_acc
        t_cruise = 0.0
    else:
        t_cruise = (d - a * t_acc**2) / v
    total = 2 * t_acc + t_cruise

    def x(t: float) -> float:
        if t <= 0:
            return 0.0
        if t < t_acc:
            return 0.5 * a * t * t
        if t < t_acc + t_cruise:
            return 0.5 * a * t_acc**2 + v * (t - t_acc)
        if t < total:
            r = total - t
            return d - 0.5 * a * r * r
        return d

    return total, x


@pytest.mark.parametrize(
    ("start", "goal", "pv", "pa"),
    [(1000, 3500, 50, 10), (2048, 2348, 200, 5), (3000, 500, 80, 0)],
    ids=["trapezoid", "triangle", "rectangle"],
)
def test_motion_matches_manual_trapezoid(sdk, start: int, goal: int, pv: int, pa: int) -> None:
    ph, port, clock = sdk.ph, sdk.port, sdk.clock
    ph.write4ByteTxRx(port, 5, PROF_ACC, pa)
    ph.write4ByteTxRx(port, 5, PROF_VEL, pv)
    ph.write1ByteTxRx(port, 5, TORQUE, 1)
    if start != 1000:
        ph.write4ByteTxRx(port, 5, GOAL, start)
        clock.advance(100.0)
    assert ph.read4ByteTxRx(port, 5, PRESENT)[0] == start
    total, x = manual_profile(abs(goal - start), pv, pa)
    sign = 1 if goal > start else -1
    t0 = clock.now()
    ph.write4ByteTxRx(port, 5, GOAL, goal)
    for frac in (0.1, 0.3, 0.5, 0.8, 0.97):
        clock.advance(t0 + frac * total - clock.now())
        pos = ph.read4ByteTxRx(port, 5, PRESENT)[0]
        # Present Position is an integer tick: within 0.5 tick of the exact profile (+ float
        # slack), i.e. |error| <= 1 is a strict bound.
        assert abs(pos - (start + sign * x(frac * total))) <= 1.0
        assert ph.read1ByteTxRx(port, 5, MOVING)[0] == 1
    clock.advance(t0 + total + 1e-3 - clock.now())
    assert ph.read4ByteTxRx(port, 5, PRESENT)[0] == goal
    assert ph.read1ByteTxRx(port, 5, MOVING)[0] == 0


# ---- the gonio driver -----------------------------------------------------------------------


@pytest.fixture(params=TRANSPORTS)
def drv(request):
    clock = VirtualClock()
    bus = EmulatedBus(clock, rng=7)
    bus.add_servo(1, "XM430-W350")
    bus.add_servo(2, "XL430-W250")
    url, closer = _open(bus, request.param)
    made: list[DynamixelBus] = []

    def make(**kw) -> DynamixelBus:
        kw.setdefault("clock", clock)
        b = DynamixelBus(url, **kw)
        made.append(b)
        return b

    yield SimpleNamespace(bus=bus, clock=clock, url=url, make=make, transport=request.param)
    for b in made:
        b.close()
    closer()


def test_driver_basic_ops(drv) -> None:
    dx = drv.make()
    assert dx.ping(1) == 1020 and dx.ping(2) == 1060
    dx.write(1, PROF_VEL, 4, 99)
    assert dx.read(1, PROF_VEL, 4) == 99
    dx.sync_write(PROF_ACC, 4, {1: 11, 2: 22})
    assert dx.sync_read(PROF_ACC, 4, [2, 1]) == {2: 22, 1: 11}
    dx.reboot(2)
    assert dx.read(2, TORQUE, 1) == 0


def test_driver_signed_registers(drv) -> None:
    dx = drv.make()
    dx.write(1, HOMING, 4, -3000)  # EEPROM, torque is off
    raw = drv.bus.servo(1).register("present_position")  # emulator's own view, signed
    assert raw == 2048 - 3000
    assert dx.read(1, PRESENT, 4) == -952
    assert dx.sync_read(PRESENT, 4, [1]) == {1: -952}


def test_driver_retries_recover_from_one_in_five_dropped(drv) -> None:
    drv.bus.set_reply_faults(ReplyFaults(drop_p=0.2))
    dx = drv.make(retries=5)  # P(6 drops in a row) = 0.2^6 = 6.4e-5 per operation
    for k in range(25):
        dx.write(1, PROF_VEL, 4, 10 + k)
        assert dx.read(1, PROF_VEL, 4) == 10 + k
    drops = drv.bus.faults.counts["drop"]
    assert drops > 0
    # each lost status packet cost one resend (a loaded host can add late-reply timeouts)
    assert dx.stats["retries"] >= drops


def test_driver_retries_on_corrupt_replies(drv) -> None:
    dx = drv.make(retries=3)
    drv.bus.inject_next("bad_crc", servo_id=1)
    drv.bus.inject_next("truncate", servo_id=1)
    assert dx.read(1, PRESENT, 4) == 2048
    assert dx.stats["retries"] == 2


def test_driver_gives_up_after_retries(drv) -> None:
    dx = drv.make(retries=2)
    drv.bus.inject_next("drop", servo_id=1, count=3)
    with pytest.raises(DynamixelCommError) as info:
        dx.read(1, PRESENT, 4)
    assert info.value.result == COMM_RX_TIMEOUT and info.value.attempts == 3
    assert isinstance(info.value, DeviceFault)
    assert dx.read(1, PRESENT, 4) == 2048  # the bus is usable afterwards


def test_driver_decodes_error_byte(drv) -> None:
    dx = drv.make()
    dx.torque(1, True)
    with pytest.raises(DynamixelError, match="access error") as info:
        dx.write(1, OP_MODE, 1, 4)
    assert info.value.error == P.ERRNUM_ACCESS and info.value.servo_id == 1
    with pytest.raises(DynamixelError, match="data limit error"):
        dx.write(1, GOAL, 4, 5000)
    with pytest.raises(DynamixelError, match="access error"):
        dx.read(1, 200, 4)  # the SDK's IndexError path, wrapped


def _axis(dx: DynamixelBus, sid: int = 1, **kw) -> DynamixelAxis:
    kw.setdefault("limits_rad", (0.0, 2 * math.pi))
    return DynamixelAxis(dx, sid, f"axis{sid}", profile_velocity=60, profile_acceleration=20, **kw)


def test_alert_stop_raises_device_fault(drv) -> None:
    dx = drv.make(on_alert="stop")
    ax = _axis(dx)
    ax.torque(True)
    drv.bus.inject_alert(1, "overload")
    with pytest.raises(HardwareAlert, match="overload") as info:
        ax.position()
    assert info.value.status == 1 << 5 and info.value.names == ["overload"]
    assert isinstance(info.value, DeviceFault)
    ax.torque(False)  # a safe stop still works on a servo in alert
    assert ax.status()["hardware_error_names"] == ["overload"]


def test_alert_reboot_recovers_and_finishes_move(drv) -> None:
    dx = drv.make(on_alert="reboot")
    ax = _axis(dx)
    ax.torque(True)
    ax.move_to(math.radians(300))
    drv.clock.advance(0.3)
    drv.bus.inject_alert(1, "overload")  # mid-move: shutdown, torque off
    ax.wait(timeout_s=20)
    assert dx.stats["reboots"] == 1
    assert drv.bus.servo(1).register("torque_enable") == 1
    assert drv.bus.servo(1).register("hardware_error_status") == 0
    assert abs(drv.bus.servo(1).register("present_position") - round(300 / 360 * 4096)) <= 8


def test_alert_reboot_gives_up_when_fault_persists(drv) -> None:
    dx = drv.make(on_alert="reboot")
    ax = _axis(dx)
    ax.torque(True)
    drv.bus.inject_alert(1, "overload", persistent=True)
    with pytest.raises(HardwareAlert, match="still present after reboot"):
        ax.position()


def test_scheduled_alert_fires_at_clock_time(drv) -> None:
    dx = drv.make(on_alert="stop")
    ax = _axis(dx)
    drv.bus.inject_alert(1, "overheat", at_time_s=5.0)
    ax.position()  # t = 0: fine
    drv.clock.advance(5.0)
    with pytest.raises(HardwareAlert, match="overheating"):
        ax.position()


def test_axis_conversion_gear_direction_offset(drv) -> None:
    dx = drv.make()
    ax = _axis(dx, gear_ratio=2.0, direction=-1, zero_offset_rad=3.0, limits_rad=(-1.0, 3.0))
    ax.torque(True)
    target = 1.25
    ax.move_to(target)
    # angle = zero + dir·ticks·2π/4096/gear  =>  ticks = (angle − zero)·dir·gear·4096/2π
    expect = round((target - 3.0) * -1 * 2.0 * 4096 / (2 * math.pi))
    assert drv.bus.servo(1).register("goal_position") == expect
    ax.wait(timeout_s=30)
    tick_rad = 2 * math.pi / 4096 / 2.0  # one tick on the axis side
    assert abs(ax.position() - target) <= tick_rad


def test_soft_limits_reject_before_sending(drv) -> None:
    dx = drv.make()
    ax = _axis(dx, limits_rad=(math.radians(10), math.radians(170)))
    ax.torque(True)
    with pytest.raises(ValueError, match=r"axis1.*180\.000 deg.*\[10\.000, 170\.000\] deg"):
        ax.move_to(math.pi)
    with pytest.raises(ValueError, match="axis1"):
        move_together([ax], [math.nan])
    assert drv.bus.servo(1).register("goal_position") == 2048


def test_wait_uses_virtual_time_and_matches_profile(drv) -> None:
    dx = drv.make()
    ax = _axis(dx, poll_s=0.05)
    assert isinstance(ax, Axis)
    ax.torque(True)
    t0 = drv.clock.now()
    ax.move_to(math.radians(30))
    ax.wait(timeout_s=30)
    elapsed = drv.clock.now() - t0
    d = abs(round(math.radians(30) * 4096 / (2 * math.pi)) - 2048)
    total, _ = manual_profile(d, 60, 20)
    # wait polls every poll_s of clock time, so it returns within one poll of arrival
    assert total <= elapsed + 1e-9 <= total + 0.05 + 1e-9


def test_wait_sleeps_to_expected_end_then_polls(drv) -> None:
    dx = drv.make()
    ax = _axis(dx, poll_s=0.01)
    ax.torque(True)
    ax.position()  # start position now known -> the move has an expected end
    drv.bus.traffic = []
    t0 = drv.clock.now()
    ax.move_to(math.radians(100))
    ax.wait(timeout_s=30)
    wire = b"".join(d for k, d in drv.bus.traffic if k == "rx")
    reads = [p for p in P.PacketDecoder().feed(wire) if p.instruction == P.INST_READ]
    assert 1 <= len(reads) <= 2  # not one per 10 ms poll over a ~0.8 s move
    total, _ = manual_profile(abs(round(100 / 360 * 4096) - 2048), 60, 20)
    assert total <= drv.clock.now() - t0 + 1e-9 <= total + 0.01 + 1e-9
    assert abs(drv.bus.servo(1).register("present_position") - round(100 / 360 * 4096)) == 0


def test_wait_times_out_on_stuck_axis(drv) -> None:
    dx = drv.make()
    ax = _axis(dx)
    ax.torque(True)
    drv.bus.set_stuck(1)
    ax.move_to(math.radians(90))
    t0 = drv.clock.now()
    with pytest.raises(AxisTimeout, match="axis1"):
        ax.wait(timeout_s=4.0)
    assert drv.clock.now() - t0 >= 4.0


def test_move_together_and_read_positions(drv) -> None:
    dx = drv.make()
    a1, a2 = _axis(dx, 1), _axis(dx, 2)
    for a in (a1, a2):
        a.torque(True)
    targets = [math.radians(45), math.radians(250)]
    drv.bus.traffic = []
    move_together([a1, a2], targets)
    a1.wait(30)
    a2.wait(30)
    # (checked after later transactions: on the pty the emulator thread may lag a write that
    # expects no reply; it handles bytes in order)
    wire = b"".join(d for k, d in drv.bus.traffic if k == "rx")
    insts = [p.instruction for p in P.PacketDecoder().feed(wire)]
    assert insts.count(P.INST_SYNC_WRITE) == 1  # one packet for both axes
    assert insts.count(P.INST_WRITE) == 0
    got = read_positions([a1, a2])
    for g, t in zip(got, targets, strict=True):
        assert abs(g - t) <= 2 * math.pi / 4096
    st = a2.status()
    assert st["voltage_V"] == pytest.approx(11.1) and st["temperature_C"] == 35.0
    assert st["hardware_error"] == 0


def test_open_errors_are_device_faults(drv) -> None:
    if drv.transport == "pty":
        drv.make()
        with pytest.raises(DeviceFault, match="cannot open"):
            drv.make()  # exclusive=True: the port is busy
    with pytest.raises(DeviceFault, match="cannot open"):
        DynamixelBus("dxlsim://no-such-bus", clock=drv.clock)


@pytest.mark.parametrize("policy", ["stop", "reboot"])
def test_alert_seen_through_sync_read(drv, policy: str) -> None:
    dx = drv.make(on_alert=policy)
    a1, a2 = _axis(dx, 1), _axis(dx, 2)
    for a in (a1, a2):
        a.torque(True)
    drv.bus.inject_alert(2, "overload")
    if policy == "stop":
        with pytest.raises(HardwareAlert, match="servo 2.*overload"):
            read_positions([a1, a2])
    else:
        got = read_positions([a1, a2])
        assert got == pytest.approx([math.pi, math.pi], abs=2 * math.pi / 4096)
        assert dx.stats["reboots"] == 1
        assert drv.bus.servo(2).register("torque_enable") == 1


def test_stop_holds_present_position(drv) -> None:
    dx = drv.make()
    ax = _axis(dx)
    ax.torque(True)
    ax.move_to(math.radians(300))
    drv.clock.advance(0.5)
    ax.stop()
    held = drv.bus.servo(1).register("present_position")
    assert 2048 < held < round(300 / 360 * 4096)  # stopped part-way
    drv.clock.advance(5.0)
    ax.wait(timeout_s=1.0)  # already there: the goal is where it stopped
    assert drv.bus.servo(1).register("present_position") == held

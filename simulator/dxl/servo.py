"""One emulated Dynamixel X-series servo (XM430-W350, XL430-W250) in position control mode.

Reference: ROBOTIS e-Manual, XM430-W350 / XL430-W250 "Control Table" and "Profile Velocity(112)"
(velocity-based profile). Units: position 4096 ticks/rev; Profile Velocity 0.229 rev/min per
unit; Profile Acceleration 214.577 rev/min² per unit; Present Input Voltage 0.1 V; Present
Temperature 1 °C.

Motion is a pure function of the clock: a goal written at time t0 starts a rest-to-rest
trapezoidal profile from the present position,

    v = PV · 0.229 · 4096 / 60          [tick/s]
    a = PA · 214.577 · 4096 / 3600      [tick/s²]
    trapezoid  (d ≥ v²/a):  T = d/v + v/a
    triangle   (d <  v²/a):  T = 2·√(d/a),  peak speed √(a·d)

with PA = 0 meaning infinite acceleration (rectangular velocity profile, T = d/v) and PV = 0
meaning "no limit", emulated as the Velocity Limit(44). Present Position is read from this
profile at `clock.now()`, so with a VirtualClock a 3 s move finishes after 3 s of virtual time.

Simplifications (documented, deliberate): a new goal during a move restarts the profile from
the present position at rest; writes must cover whole registers (else data length error);
Return Delay Time and Bus Watchdog are stored but have no effect; temperature and voltage are
constants unless a fault changes them.

Physical truth for the simulated camera: `true_position_ticks()` is where the horn really is,
i.e. Present Position plus any injected `position_offset_ticks` (the calibration error the
simulated camera sees but the servo does not report).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from acquisition.clock import Clock
from simulator.dxl import protocol as P

__all__ = [
    "Register",
    "CONTROL_TABLE",
    "MODELS",
    "TICKS_PER_REV",
    "RPM_PER_UNIT",
    "REV_PER_MIN2_PER_UNIT",
    "HW_INPUT_VOLTAGE",
    "HW_OVERHEAT",
    "HW_ENCODER",
    "HW_ELECTRICAL_SHOCK",
    "HW_OVERLOAD",
    "Servo",
    "profile_duration_s",
]

TICKS_PER_REV = 4096
RPM_PER_UNIT = 0.229
REV_PER_MIN2_PER_UNIT = 214.577

# Hardware Error Status (70) bits
HW_INPUT_VOLTAGE = 1 << 0
HW_OVERHEAT = 1 << 2
HW_ENCODER = 1 << 3
HW_ELECTRICAL_SHOCK = 1 << 4
HW_OVERLOAD = 1 << 5


@dataclass(frozen=True)
class Register:
    name: str
    addr: int
    size: int
    writable: bool
    default: int = 0
    lo: int | None = None  # allowed range for writes (inclusive), None = any
    hi: int | None = None
    signed: bool = False

    @property
    def eeprom(self) -> bool:
        return self.addr < 64


def _r(name, addr, size, rw, default=0, lo=None, hi=None, signed=False) -> Register:
    return Register(name, addr, size, rw == "RW", default, lo, hi, signed)


# X-series control table (protocol 2.0, firmware ≥ v42), e-Manual. Defaults are XM430-W350's;
# per-model differences are in MODELS.
CONTROL_TABLE: tuple[Register, ...] = (
    _r("model_number", 0, 2, "R"),
    _r("model_information", 2, 4, "R"),
    _r("firmware_version", 6, 1, "R", 48),
    _r("id", 7, 1, "RW", 1, 0, 252),
    _r("baud_rate", 8, 1, "RW", 1, 0, 7),
    _r("return_delay_time", 9, 1, "RW", 250, 0, 254),
    _r("drive_mode", 10, 1, "RW", 0, 0, 13),
    _r("operating_mode", 11, 1, "RW", 3, 0, 16),
    _r("secondary_id", 12, 1, "RW", 255, 0, 255),
    _r("protocol_type", 13, 1, "RW", 2, 1, 2),
    _r("homing_offset", 20, 4, "RW", 0, -1044479, 1044479, signed=True),
    _r("moving_threshold", 24, 4, "RW", 10, 0, 1023),
    _r("temperature_limit", 31, 1, "RW", 80, 0, 100),
    _r("max_voltage_limit", 32, 2, "RW", 160, 60, 160),
    _r("min_voltage_limit", 34, 2, "RW", 95, 60, 160),
    _r("pwm_limit", 36, 2, "RW", 885, 0, 885),
    _r("current_limit", 38, 2, "RW", 1193, 0, 1193),
    _r("velocity_limit", 44, 4, "RW", 200, 0, 1023),
    _r("max_position_limit", 48, 4, "RW", 4095, 0, 4095),
    _r("min_position_limit", 52, 4, "RW", 0, 0, 4095),
    _r("startup_configuration", 60, 1, "RW", 0, 0, 3),
    _r("shutdown", 63, 1, "RW", 0x34, 0, 0x3F),
    _r("torque_enable", 64, 1, "RW", 0, 0, 1),
    _r("led", 65, 1, "RW", 0, 0, 1),
    _r("status_return_level", 68, 1, "RW", 2, 0, 2),
    _r("registered_instruction", 69, 1, "R"),
    _r("hardware_error_status", 70, 1, "R"),
    _r("velocity_i_gain", 76, 2, "RW", 1920, 0, 16383),
    _r("velocity_p_gain", 78, 2, "RW", 100, 0, 16383),
    _r("position_d_gain", 80, 2, "RW", 0, 0, 16383),
    _r("position_i_gain", 82, 2, "RW", 0, 0, 16383),
    _r("position_p_gain", 84, 2, "RW", 800, 0, 16383),
    _r("feedforward_2nd_gain", 88, 2, "RW", 0, 0, 16383),
    _r("feedforward_1st_gain", 90, 2, "RW", 0, 0, 16383),
    _r("bus_watchdog", 98, 1, "RW", 0, 0, 127),
    _r("goal_pwm", 100, 2, "RW", 0, -885, 885, signed=True),
    _r("goal_current", 102, 2, "RW", 0, -1193, 1193, signed=True),
    _r("goal_velocity", 104, 4, "RW", 0, -1023, 1023, signed=True),
    _r("profile_acceleration", 108, 4, "RW", 0, 0, 32767),
    _r("profile_velocity", 112, 4, "RW", 0, 0, 32767),
    _r("goal_position", 116, 4, "RW", 0, None, None, signed=True),
    _r("realtime_tick", 120, 2, "R"),
    _r("moving", 122, 1, "R"),
    _r("moving_status", 123, 1, "R"),
    _r("present_pwm", 124, 2, "R", signed=True),
    _r("present_current", 126, 2, "R", signed=True),
    _r("present_velocity", 128, 4, "R", signed=True),
    _r("present_position", 132, 4, "R", signed=True),
    _r("velocity_trajectory", 136, 4, "R", signed=True),
    _r("position_trajectory", 140, 4, "R", signed=True),
    _r("present_input_voltage", 144, 2, "R"),
    _r("present_temperature", 146, 1, "R"),
    _r("backup_ready", 147, 1, "R"),
)
TABLE_SIZE = 148
_BY_ADDR = {r.addr: r for r in CONTROL_TABLE}
_BY_NAME = {r.name: r for r in CONTROL_TABLE}
_OWNER = {}
for _reg in CONTROL_TABLE:
    for _a in range(_reg.addr, _reg.addr + _reg.size):
        _OWNER[_a] = _reg

# Model-specific values (e-Manual): model number, voltage limits, gains, velocity limit.
MODELS: dict[str, dict[str, int]] = {
    "XM430-W350": {
        "model_number": 1020,
        "max_voltage_limit": 160,
        "min_voltage_limit": 95,
        "velocity_limit": 200,
        "position_p_gain": 800,
        "voltage_dV": 120,
    },
    "XL430-W250": {
        "model_number": 1060,
        "temperature_limit": 72,
        "max_voltage_limit": 140,
        "min_voltage_limit": 60,
        "velocity_i_gain": 1000,
        "position_d_gain": 4000,
        "velocity_limit": 265,
        "position_p_gain": 640,
        "voltage_dV": 111,
    },
}


def profile_duration_s(distance_ticks: float, v_ticks_s: float, a_ticks_s2: float) -> float:
    """Rest-to-rest time of the trapezoid/triangle profile (equations in the module doc)."""
    d = abs(distance_ticks)
    if d == 0:
        return 0.0
    if math.isinf(a_ticks_s2):
        return d / v_ticks_s
    if d >= v_ticks_s * v_ticks_s / a_ticks_s2:
        return d / v_ticks_s + v_ticks_s / a_ticks_s2
    return 2.0 * math.sqrt(d / a_ticks_s2)


class _Profile:
    """A rest-to-rest move from p0 to p1 started at t0 (ticks, seconds)."""

    def __init__(self, p0: float, p1: float, t0: float, v: float, a: float) -> None:
        self.p0, self.p1, self.t0 = p0, p1, t0
        d = abs(p1 - p0)
        self.sign = 1.0 if p1 >= p0 else -1.0
        self.d = d
        if math.isinf(a):
            self.ta, self.vpk = 0.0, v
            self.tc = d / v if v > 0 else 0.0
            self.kind = 1  # rectangle
        elif d >= v * v / a:
            self.ta, self.vpk = v / a, v
            self.tc = d / v - v / a
            self.kind = 3  # trapezoid
        else:
            self.vpk = math.sqrt(a * d)
            self.ta, self.tc = self.vpk / a, 0.0
            self.kind = 2  # triangle
        self.a = a
        self.duration = 2 * self.ta + self.tc

    def state(self, t: float) -> tuple[float, float]:
        """(position, velocity) at time t."""
        tau = t - self.t0
        if tau >= self.duration:
            return self.p1, 0.0
        if tau <= 0:
            return self.p0, 0.0
        s = self.sign
        if tau < self.ta:
            return self.p0 + s * 0.5 * self.a * tau * tau, s * self.a * tau
        d_acc = 0.5 * self.vpk * self.ta
        if tau < self.ta + self.tc:
            return self.p0 + s * (d_acc + self.vpk * (tau - self.ta)), s * self.vpk
        rem = self.duration - tau
        if self.ta > 0:
            return self.p1 - s * 0.5 * self.a * rem * rem, s * self.a * rem
        return self.p1, 0.0


class Servo:
    """An X-series servo: a control table, a motion profile and a hardware-error state.

    Parameters
    ----------
    dxl_id: bus ID (0..252).
    model: "XM430-W350" (model number 1020) or "XL430-W250" (1060).
    clock: the time line motion is evaluated on (VirtualClock in the simulator).
    position_ticks: initial horn position.
    temperature_C, voltage_V: constant readings (faults may change them).
    """

    def __init__(
        self,
        dxl_id: int,
        model: str = "XM430-W350",
        *,
        clock: Clock,
        position_ticks: int = 2048,
        temperature_C: float = 35.0,
        voltage_V: float | None = None,
    ) -> None:
        if model not in MODELS:
            raise ValueError(f"unknown model {model!r}; known: {', '.join(MODELS)}")
        self.model = model
        self.clock = clock
        self._spec = MODELS[model]
        self._mem = bytearray(TABLE_SIZE)
        self._eeprom_defaults(dxl_id)
        self._ram_defaults()
        self._pos = float(position_ticks)  # internal (pre-homing-offset) position when at rest
        self._profile: _Profile | None = None
        self.temperature_C = float(temperature_C)
        self.voltage_V = (
            float(voltage_V) if voltage_V is not None else self._spec["voltage_dV"] / 10.0
        )
        self._hw_error = 0
        self._persistent_hw_error = 0  # cleared only when the fault is lifted
        self.stuck = False  # injected: the horn does not move (e.g. jammed arm)
        self.position_offset_ticks = 0  # injected: true angle = reported + offset
        # Direction of the last commanded move (+1, −1; 0 before any): gear play makes the arm
        # lag it (simulator.world, scene [geometry] backlash_deg).
        self.last_move = 0
        self._registered: tuple[int, bytes] | None = None
        self._set("goal_position", int(round(self._pos)))

    # -- control table helpers ------------------------------------------------------------
    @property
    def dxl_id(self) -> int:
        return self._mem[7]

    def _get(self, name: str) -> int:
        r = _BY_NAME[name]
        return int.from_bytes(self._mem[r.addr : r.addr + r.size], "little", signed=r.signed)

    def _set(self, name: str, value: int) -> None:
        r = _BY_NAME[name]
        value = int(value)
        if r.signed:
            value &= (1 << (8 * r.size)) - 1
        self._mem[r.addr : r.addr + r.size] = int(value).to_bytes(r.size, "little")

    def register(self, name: str) -> int:
        """Current value of a register by name (refreshed live values included)."""
        self._refresh()
        return self._get(name)

    def _eeprom_defaults(self, dxl_id: int) -> None:
        for r in CONTROL_TABLE:
            if r.eeprom:
                self._set(r.name, self._spec.get(r.name, r.default))
        self._set("id", dxl_id)
        if self.model == "XL430-W250":
            self._set("current_limit", 0)  # XL430 has no current sensing

    def _ram_defaults(self) -> None:
        for r in CONTROL_TABLE:
            if not r.eeprom and r.name != "goal_position":
                self._set(r.name, self._spec.get(r.name, r.default))

    # -- motion ---------------------------------------------------------------------------
    def _v_ticks_s(self) -> float:
        pv = self._get("profile_velocity") or self._get("velocity_limit")
        return max(pv, 1) * RPM_PER_UNIT * TICKS_PER_REV / 60.0

    def _a_ticks_s2(self) -> float:
        pa = self._get("profile_acceleration")
        return math.inf if pa == 0 else pa * REV_PER_MIN2_PER_UNIT * TICKS_PER_REV / 3600.0

    def _state(self, t: float) -> tuple[float, float]:
        if self._profile is None:
            return self._pos, 0.0
        return self._profile.state(t)

    def _freeze(self, at_s: float | None = None) -> None:
        """Stop the horn where it is now, or was at `at_s` (torque off, shutdown, stuck)."""
        self._pos, _ = self._state(self.clock.now() if at_s is None else at_s)
        self._profile = None

    def _start_move(self, goal_internal: float) -> None:
        now = self.clock.now()
        p, _ = self._state(now)
        self._pos = p
        if goal_internal != p:
            self.last_move = 1 if goal_internal > p else -1
        if self.stuck:
            self._profile = None
            return
        self._profile = _Profile(p, goal_internal, now, self._v_ticks_s(), self._a_ticks_s2())

    def mid_move_time(self, since_s: float) -> float | None:
        """Clock time halfway through the current move, if one started at or after `since_s`
        and covers some distance; else None."""
        p = self._profile
        if p is None or p.t0 < since_s or p.duration <= 0:
            return None
        return p.t0 + 0.5 * p.duration

    def motion_state(self, at_s: float | None = None) -> tuple[bool, float]:
        """(mid-move, |goal − position| in ticks) at `at_s` (default now): mid-move means a
        profile has started and not yet arrived, so the horn is travelling."""
        now = self.clock.now() if at_s is None else at_s
        p = self._profile
        pos, _ = self._state(now)
        moving = p is not None and p.t0 < now < p.t0 + p.duration
        goal = p.p1 if p is not None else self._pos
        return moving, abs(goal - pos)

    def internal_position(self) -> float:
        return self._state(self.clock.now())[0]

    def present_position_ticks(self) -> int:
        """What the servo reports in Present Position (132)."""
        return int(round(self.internal_position())) + self._get("homing_offset")

    def true_position_ticks(self) -> float:
        """Where the horn physically is, in Present-Position ticks: what the simulated camera
        must use. Equals Present Position plus the injected `position_offset_ticks`."""
        return self.internal_position() + self._get("homing_offset") + self.position_offset_ticks

    def _refresh(self) -> None:
        """Update the live (read-only) registers from the model at clock.now()."""
        now = self.clock.now()
        pos, vel = self._state(now)
        if self._profile is not None and now >= self._profile.t0 + self._profile.duration:
            self._pos, self._profile = self._profile.p1, None
        offset = self._get("homing_offset")
        present = int(round(pos)) + offset
        self._set("present_position", present)
        self._set("present_velocity", int(round(vel * 60.0 / (RPM_PER_UNIT * TICKS_PER_REV))))
        self._set("position_trajectory", present)
        self._set("velocity_trajectory", self._get("present_velocity"))
        goal = self._get("goal_position")
        profiling = self._profile is not None
        in_pos = abs(goal - present) <= self._get("moving_threshold")
        torque = self._get("torque_enable") == 1
        moving = torque and (profiling or not in_pos)
        self._set("moving", 1 if moving else 0)
        kind = self._profile.kind if self._profile is not None else 0
        self._set("moving_status", (kind << 4) | (2 if profiling else 0) | (1 if in_pos else 0))
        self._set("realtime_tick", int(now * 1000.0) % 32768)
        self._set("present_input_voltage", int(round(self.voltage_V * 10.0)))
        self._set("present_temperature", int(round(self.temperature_C)))
        self._update_hw_error()
        self._set("hardware_error_status", self._hw_error)
        self._set("registered_instruction", 1 if self._registered else 0)

    # -- hardware errors ------------------------------------------------------------------
    def _update_hw_error(self) -> None:
        bits = self._persistent_hw_error
        if self.temperature_C > self._get("temperature_limit"):
            bits |= HW_OVERHEAT
        dv = self.voltage_V * 10.0
        if dv > self._get("max_voltage_limit") or dv < self._get("min_voltage_limit"):
            bits |= HW_INPUT_VOLTAGE
        self.raise_hw_error(bits)

    def raise_hw_error(
        self, bits: int, persistent: bool = False, at_s: float | None = None
    ) -> None:
        """Latch hardware error bits (reg 70). Bits in Shutdown (63) turn torque off until
        REBOOT, stopping the horn where it is (or was at clock time `at_s`, for an alert dated
        to the past). `persistent` bits come back after a reboot until `clear_fault`."""
        if persistent:
            self._persistent_hw_error |= bits
        new = bits & ~self._hw_error
        self._hw_error |= bits
        if new & self._get("shutdown") and self._get("torque_enable"):
            self._freeze(at_s)
            self._set("torque_enable", 0)

    def clear_fault(self) -> None:
        """Lift persistent injected faults (the cause is gone; a REBOOT still clears reg 70)."""
        self._persistent_hw_error = 0

    @property
    def shutdown_active(self) -> bool:
        return bool(self._hw_error & self._get("shutdown"))

    def error_bits(self) -> int:
        """Alert bit for the status packet's error byte."""
        self._update_hw_error()
        return P.ERRBIT_ALERT if self._hw_error else 0

    # -- instructions ---------------------------------------------------------------------
    def read(self, addr: int, length: int) -> tuple[int, bytes]:
        """(error number, data). Bytes in gaps of the table read as 0, like the real device."""
        if length < 1:
            return P.ERRNUM_DATA_LENGTH, b""
        if addr + length > TABLE_SIZE:
            return P.ERRNUM_ACCESS, b""
        self._refresh()
        return 0, bytes(self._mem[addr : addr + length])

    def check_write(self, addr: int, data: bytes) -> int:
        """Validate a write without applying it; returns the error number (0 = fine)."""
        if not data:
            return P.ERRNUM_DATA_LENGTH
        end = addr + len(data)
        a = addr
        while a < end:
            r = _OWNER.get(a)
            if r is None:
                return P.ERRNUM_ACCESS
            if r.addr != a or r.addr + r.size > end:
                return P.ERRNUM_DATA_LENGTH
            if not r.writable:
                return P.ERRNUM_ACCESS
            if r.eeprom and self._get("torque_enable"):
                return P.ERRNUM_ACCESS  # EEPROM is locked while torque is on
            v = int.from_bytes(data[a - addr : a - addr + r.size], "little", signed=r.signed)
            if r.name == "goal_position":
                lo = self._get("min_position_limit") + self._get("homing_offset")
                hi = self._get("max_position_limit") + self._get("homing_offset")
                if self._get("operating_mode") == 3 and not lo <= v <= hi:
                    return P.ERRNUM_DATA_LIMIT
            elif r.name == "profile_velocity":
                vl = self._get("velocity_limit")
                if not 0 <= v <= 32767:
                    return P.ERRNUM_DATA_RANGE
                if v > vl:
                    return P.ERRNUM_DATA_LIMIT
            elif r.lo is not None and not r.lo <= v <= r.hi:
                return P.ERRNUM_DATA_RANGE
            if r.name == "torque_enable" and v == 1 and self.shutdown_active:
                return P.ERRNUM_RESULT_FAIL  # shutdown needs a REBOOT first
            a += r.size
        return 0

    def write(self, addr: int, data: bytes) -> int:
        """Apply a write (validated first). Returns the error number (0 = written)."""
        self._refresh()
        err = self.check_write(addr, data)
        if err:
            return err
        a, end = addr, addr + len(data)
        while a < end:
            r = _OWNER[a]
            v = int.from_bytes(data[a - addr : a - addr + r.size], "little", signed=r.signed)
            self._apply(r, v)
            a += r.size
        self._refresh()
        return 0

    def _apply(self, r: Register, v: int) -> None:
        if r.name == "torque_enable":
            was = self._get("torque_enable")
            if v and not was:
                # On torque-on the servo holds where it is: goal := present position.
                self._freeze()
                self._set("goal_position", int(round(self._pos)) + self._get("homing_offset"))
            elif not v and was:
                self._freeze()
            self._set("torque_enable", v)
            return
        if r.name == "homing_offset":
            # keep the horn where it is; only the reported frame shifts
            self._set("homing_offset", v)
            return
        self._set(r.name, v)
        if r.name == "goal_position" and self._get("torque_enable"):
            self._start_move(v - self._get("homing_offset"))

    def reg_write(self, addr: int, data: bytes) -> int:
        err = self.check_write(addr, data)
        if not err:
            self._registered = (addr, bytes(data))
        return err

    def action(self) -> int:
        if self._registered is None:
            return 0
        addr, data = self._registered
        self._registered = None
        return self.write(addr, data)

    def reboot(self) -> None:
        """REBOOT: RAM back to defaults (torque off), hardware error cleared unless its cause
        persists; the horn stays where it is."""
        self._freeze()
        self._ram_defaults()
        self._hw_error = 0
        self._registered = None
        self._set("goal_position", int(round(self._pos)) + self._get("homing_offset"))
        self._refresh()

    def set_stuck(self, stuck: bool) -> None:
        """Injected jam: the horn stops where it is and ignores goals until released."""
        self._freeze()
        self.stuck = stuck
        if not stuck and self._get("torque_enable"):
            self._start_move(self._get("goal_position") - self._get("homing_offset"))

    def model_number(self) -> int:
        return self._get("model_number")

    def firmware_version(self) -> int:
        return self._get("firmware_version")

"""`gonio rig check`: what a lab looks at before the first run — every servo (model, firmware,
voltage, temperature, limits, latched errors, and its present angle against the rig file's
limits), the light controller (identity, monitor reading) and the camera (one test frame: size,
exposure, black level, clipped pixels). Nothing moves, the lamp is not switched and no servo
register is written."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rich.console import Group
from rich.table import Table

from acquisition.config import RigConfig
from gonio.plain_text import plain

__all__ = [
    "ServoCheck",
    "DeviceCheck",
    "check_rig",
    "check_light",
    "check_camera",
    "rig_check_table",
    "rig_check_report",
]


@dataclass
class ServoCheck:
    role: str
    servo_id: int
    ok: bool
    model: str = "-"
    firmware: int | None = None
    voltage_V: float | None = None
    temperature_C: float | None = None
    limits_ticks: tuple[int, int] | None = None
    hardware_error: list[str] = field(default_factory=list)
    angle_deg: float | None = None  # present position through the rig file's axis formula
    limits_deg: tuple[float, float] | None = None
    problem: str = ""


@dataclass
class DeviceCheck:
    """One non-servo device: what it said about itself, and whether that is fine."""

    device: str
    ok: bool
    facts: dict[str, str] = field(default_factory=dict)
    problem: str = ""


def _axis_angle_deg(axis, ticks: int) -> float:  # AxisConfig
    """Axis angle = zero_offset_deg + direction · (ticks / 4096 · 360°) / gear_ratio."""
    ticks = ticks - (1 << 32) if ticks >= 1 << 31 else ticks  # the register is two's complement
    return axis.zero_offset_deg + axis.direction * ticks * 360.0 / 4096 / axis.gear_ratio


def check_rig(rig: RigConfig) -> list[ServoCheck]:
    """Ping every servo of `rig` and read its model, firmware, voltage, temperature, position
    limits, hardware error status and present position. Never writes a register (no torque,
    no reboot)."""
    from acquisition.clock import get_clock
    from acquisition.dynamixel import ADDR, MODEL_NAMES, DynamixelBus, decode_hardware_error
    from acquisition.protocols import DeviceFault

    bus = DynamixelBus(
        rig.bus.url,
        baudrate=rig.bus.baudrate,
        retries=rig.bus.retries,
        on_alert="stop",
        clock=get_clock(rig.clock),
    )
    rows = []
    try:
        for a in rig.axes:
            row = ServoCheck(a.role, a.id, ok=False)
            try:
                number = bus.ping(a.id)
                row.model = MODEL_NAMES.get(number, f"model {number}")

                def reg(name: str, size: int, sid: int = a.id) -> int:
                    return bus.read(sid, ADDR[name], size, check_alert=False)

                row.firmware = reg("firmware_version", 1)
                row.voltage_V = reg("present_input_voltage", 2) / 10.0
                row.temperature_C = float(reg("present_temperature", 1))
                row.limits_ticks = (reg("min_position_limit", 4), reg("max_position_limit", 4))
                hw = reg("hardware_error_status", 1)
                row.hardware_error = decode_hardware_error(hw) if hw else []
                row.angle_deg = _axis_angle_deg(a, reg("present_position", 4))
                row.limits_deg = (a.min_deg, a.max_deg)
                notes = []
                if row.model != a.model:
                    notes.append(f"config says {a.model}")
                if hw:
                    notes.append("hardware error latched (reboot clears it once the cause is gone)")
                # Half a degree of slack: a parked arm rests on its limit, give or take a tick.
                if not a.min_deg - 0.5 <= row.angle_deg <= a.max_deg + 0.5:
                    notes.append(
                        f"at {row.angle_deg:.1f}°, outside its limits {a.min_deg:g}..{a.max_deg:g}°"
                        " (check zero_offset_deg, direction and gear_ratio)"
                    )
                row.problem = "; ".join(notes)
                row.ok = not notes
            except DeviceFault as exc:
                row.problem = str(exc)
            rows.append(row)
    finally:
        bus.close()
    return rows


def rig_check_table(rig: RigConfig, rows: list[ServoCheck]) -> Table:
    t = Table(title=plain(f"rig {rig.name}: bus {rig.bus.url} at {rig.bus.baudrate} baud"))
    cols = ("role", "id", "model", "firmware", "voltage", "temp", "angle", "limits (ticks)")
    for col in (*cols, "hw error", "status"):
        t.add_column(col)
    for r in rows:
        angle = "-"
        if r.angle_deg is not None and r.limits_deg is not None:
            angle = f"{r.angle_deg:.1f}° in {r.limits_deg[0]:g}..{r.limits_deg[1]:g}"
        cells = (
            r.role,
            str(r.servo_id),
            r.model,
            "-" if r.firmware is None else str(r.firmware),
            "-" if r.voltage_V is None else f"{r.voltage_V:.1f} V",
            "-" if r.temperature_C is None else f"{r.temperature_C:.0f} °C",
            angle,
            "-" if r.limits_ticks is None else f"{r.limits_ticks[0]}..{r.limits_ticks[1]}",
            ", ".join(r.hardware_error) or ("-" if r.firmware is None else "none"),
            "OK" if r.ok else f"FAIL: {r.problem}",
        )
        t.add_row(*map(plain, cells))  # device replies and rig names are data, not markup
    return t


def check_light(rig: RigConfig) -> DeviceCheck:
    """Identity and monitor reading of the light controller (the lamp is not switched)."""
    from acquisition.clock import get_clock
    from acquisition.protocols import DeviceFault
    from acquisition.rig import build_light

    row = DeviceCheck("light", ok=False)
    try:
        light = build_light(rig, get_clock(rig.clock))
    except DeviceFault as exc:
        row.problem = str(exc)
        return row
    try:
        if not rig.light.manual:
            row.facts["backend"] = f"{rig.light.backend} at {rig.light.url}"
        row.facts["identity"] = light.identify()
        st = light.status()
        row.facts["state"] = ("on" if st.on else "off") + f" at level {st.intensity:g}"
        row.facts["monitor"] = (
            "none (drift uncorrected)" if st.measured is None else f"{st.measured:.4f}"
        )
        row.problem = f"fault latched: {st.fault}" if st.fault else ""
        row.ok = not st.fault
    except DeviceFault as exc:
        row.problem = str(exc)
    finally:
        light.close()
    return row


def check_camera(rig: RigConfig, exposure_s: float) -> DeviceCheck:
    """One test frame through the camera backend, decoded as calibration decodes it: its size
    against the rig file's resolution, its exposure, black level and clipped pixels."""
    from acquisition.clock import get_clock
    from acquisition.protocols import DeviceFault
    from acquisition.rig import CAMERA_BACKENDS
    from calibration.decode import FrameError, decode_frame

    row = DeviceCheck("camera", ok=False)
    cam = None
    try:
        cam = CAMERA_BACKENDS[rig.camera.backend](rig, get_clock(rig.clock))
        info = cam.describe()
        row.facts["model"] = str(info.get("model") or rig.camera.model or "?")
        for key in ("sensor_px", "resolution", "pixel_format", "iso", "aperture", "image_format"):
            if info.get(key) is not None:
                value = info[key]
                text = f"{value[0]} × {value[1]} px" if isinstance(value, list) else str(value)
                row.facts[{"sensor_px": "sensor", "resolution": "device ROI"}.get(key, key)] = text
        if info.get("serial"):
            row.facts["serial"] = str(info["serial"])
        contradictions = _device_vs_rig(rig, info)
        frame = cam.capture(exposure_s)
    except (DeviceFault, KeyError, ValueError) as exc:
        row.problem = str(exc)
        return row
    finally:
        if cam is not None and hasattr(cam, "close"):
            cam.close()
    with tempfile.TemporaryDirectory(prefix="gonio-check-") as tmp:
        path = Path(tmp) / f"test{frame.suffix}"
        path.write_bytes(frame.data)
        try:
            d = decode_frame(path)
        except FrameError as exc:
            row.problem = f"test frame unreadable: {exc}"
            return row
    dn = np.asarray(d.dn)
    h, w = dn.shape[:2]
    white = rig.camera.white_level_dn
    clipped = int(np.sum(dn >= white - 0.5))
    black = float(np.mean(np.atleast_1d(np.asarray(d.black_level, dtype=float))))
    row.facts.update(
        {
            "frame": f"{w} × {h} px {frame.suffix}",
            "DN min/mean/max": f"{dn.min():g} / {dn.mean():.1f} / {dn.max():g}",
            "exposure": f"{float(frame.metadata.get('exposure_s', exposure_s)):g} s",
            "black level": f"{black:g} DN (rig file {rig.camera.black_level_dn:g})",
            "clipped": f"{clipped} of {dn.size} values ≥ white level {white:g}",
        }
    )
    if (w, h) != tuple(rig.camera.resolution):
        rw, rh = rig.camera.resolution
        row.problem = f"the frame is {w}×{h}, the rig file says {rw}×{rh}"
    if contradictions:
        row.facts["warning"] = "; ".join(contradictions)
    row.ok = not row.problem
    return row


def _device_vs_rig(rig: RigConfig, info: dict) -> list[str]:
    """Where what the camera says about itself contradicts the rig file (which calibration
    uses): resolution, bit depth, colour filter. Warnings: the rig file may be right (a
    12-bit sensor delivered in a 16-bit format), but a lab should look."""
    cam = rig.camera
    out = []
    res = info.get("resolution")
    if res is not None and tuple(res) != tuple(cam.resolution):
        out.append(f"the camera reports {res[0]}×{res[1]} px, the rig file {cam.resolution[0]}×"
                   f"{cam.resolution[1]}")  # fmt: skip
    bits = info.get("bit_depth")
    if bits is not None and int(bits) != cam.bit_depth:
        out.append(f"the camera's pixel format has {bits} bits, the rig file bit_depth is "
                   f"{cam.bit_depth}")  # fmt: skip
    cfa = info.get("color_filter")
    if cfa is not None and cfa != cam.color_filter:
        out.append(f"the camera delivers {cfa}, the rig file color_filter is {cam.color_filter}")
    return out


def rig_check_report(rig: RigConfig, servos: list[ServoCheck], devices: list[DeviceCheck]) -> Group:
    dt = Table(title="light and camera")
    for col in ("device", "what it says", "status"):
        dt.add_column(col)
    for d in devices:
        facts = "; ".join(f"{k}: {v}" for k, v in d.facts.items()) or "-"
        dt.add_row(*map(plain, (d.device, facts, "OK" if d.ok else f"FAIL: {d.problem}")))
    return Group(rig_check_table(rig, servos), dt)

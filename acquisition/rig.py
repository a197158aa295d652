"""A rig: axes, light, camera and clock, built from a rig config.

Backends are chosen by URL and registry (like pySerial's `loop://`): the bus URL goes to
`serial_for_url`, so `dxlsim://NAME` reaches the simulator's emulator once the simulator has
installed its URL handlers; camera backends are looked up by name in `CAMERA_BACKENDS`, where
the simulator registers "sim", and light backends in `LIGHT_BACKENDS` ("gonio-ascii", "scpi";
`url = "manual"` is a lamp switched by hand whatever the backend). Each real device library is
imported only by its factory, so a rig that does not use it does not need it installed. Runtime
code here never imports the simulator.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from acquisition.clock import Clock, get_clock
from acquisition.config import RigConfig
from acquisition.kinematics import Kinematics
from acquisition.protocols import Axis, Camera, DeviceFault, LightSource

__all__ = [
    "Rig",
    "CAMERA_BACKENDS",
    "LIGHT_BACKENDS",
    "register_camera_backend",
    "build_light",
    "build_rig",
    "clear_alerts",
]

CameraFactory = Callable[[RigConfig, Clock], Camera]
CAMERA_BACKENDS: dict[str, CameraFactory] = {}
LightFactory = Callable[[RigConfig, Clock], LightSource]
LIGHT_BACKENDS: dict[str, LightFactory] = {}


def register_camera_backend(name: str, factory: CameraFactory) -> None:
    CAMERA_BACKENDS[name] = factory


def _folder(config: RigConfig, clock: Clock) -> Camera:
    from acquisition.cameras import folder_camera

    return folder_camera(config, clock)


def _gphoto2(config: RigConfig, clock: Clock) -> Camera:
    from acquisition.cameras_gphoto2 import gphoto2_camera  # python-gphoto2 only here

    return gphoto2_camera(config, clock)


def _aravis(config: RigConfig, clock: Clock) -> Camera:
    from acquisition.cameras_aravis import aravis_camera  # PyGObject + Aravis only here

    return aravis_camera(config, clock)


register_camera_backend("folder", _folder)
register_camera_backend("gphoto2", _gphoto2)
register_camera_backend("aravis", _aravis)


def _gonio_ascii(config: RigConfig, clock: Clock) -> LightSource:
    from acquisition.light import SerialLight

    return SerialLight(config.light.url, clock=clock, baudrate=config.light.baudrate)


def _scpi(config: RigConfig, clock: Clock) -> LightSource:
    from acquisition.light_scpi import scpi_light  # PyVISA only here

    return scpi_light(config, clock)


LIGHT_BACKENDS["gonio-ascii"] = _gonio_ascii
LIGHT_BACKENDS["scpi"] = _scpi


def build_light(config: RigConfig, clock: Clock) -> LightSource:
    """The light source the rig file names: a hand-switched lamp (`url = "manual"`) or the
    backend's driver, opened."""
    if config.light.manual:
        from acquisition.light import ManualLight

        return ManualLight()
    return LIGHT_BACKENDS[config.light.backend](config, clock)


@dataclass
class Rig:
    config: RigConfig
    axes: dict[str, Axis]
    light: LightSource
    camera: Camera
    clock: Clock
    kinematics: Kinematics
    closers: list[Callable[[], None]] = field(default_factory=list)
    move_together: Callable[[dict[str, float]], None] | None = None
    read_positions: Callable[[], dict[str, float]] | None = None
    recovered: list[str] = field(default_factory=list)  # alerts cleared when the rig was built
    #: The side each axis last moved toward (+1 / −1; absent before its first move): a gear's
    #: play leaves the arm lagging that move by half the play, which the fit can carry
    #: (fitting.nuisance) when it knows the side. Recorded with every capture.
    approach: dict[str, int] = field(default_factory=dict)
    _last_target: dict[str, float] = field(default_factory=dict)

    def move(self, targets: dict[str, float]) -> None:
        """Start all axes toward their targets at once (sync write when the bus has it)."""
        self._note_approach(targets)
        if self.move_together is not None:
            self.move_together(targets)
        else:
            for role, angle in targets.items():
                self.axes[role].move_to(angle)

    def _note_approach(self, targets: dict[str, float]) -> None:
        """The side of this move per axis: from the last target, or before the first move from
        where the axis stands (read once; a rig that cannot say leaves the side unknown)."""
        if not self._last_target:
            try:
                self._last_target = dict(self.positions())
            except Exception:  # informational: never fail a move on it
                self._last_target = {}
        for role, target in targets.items():
            prev = self._last_target.get(role)
            if prev is not None and abs(target - prev) > 1e-9:
                self.approach[role] = 1 if target > prev else -1
            self._last_target[role] = target

    def wait(self, timeout_s: float) -> None:
        """Wait for every axis; an axis that fails does not stop the others being waited for
        (a safe stop parks whatever still moves). The first failure is raised afterwards."""
        _all_then_raise(lambda ax: ax.wait(timeout_s), self.axes.values())

    def positions(self) -> dict[str, float]:
        if self.read_positions is not None:
            return self.read_positions()
        return {role: ax.position() for role, ax in self.axes.items()}

    def torque(self, enabled: bool) -> None:
        """Torque on/off on every axis. Off is best effort per axis: a servo that does not
        answer must not leave the others powered."""
        if enabled:
            for ax in self.axes.values():
                ax.torque(True)
        else:
            _all_then_raise(lambda ax: ax.torque(False), self.axes.values())

    def device_status(self) -> dict[str, Any]:
        status: dict[str, Any] = {}
        for role, ax in self.axes.items():
            try:
                status[role] = ax.status()
            except Exception as exc:  # status is informational; never fail a capture on it
                status[role] = {"error": str(exc)}
        return status

    def close(self) -> None:
        for close in reversed(self.closers):
            try:
                close()
            except Exception:
                pass


def _all_then_raise(fn: Callable[[Any], None], items: Any) -> None:
    first: BaseException | None = None
    for item in items:
        try:
            fn(item)
        except Exception as exc:
            first = first or exc
    if first is not None:
        raise first


def clear_alerts(bus: Any, ids: list[int]) -> list[str]:
    """Reboot every servo whose Hardware Error Status (reg 70) is set, once.

    Why at rig build: a servo that tripped its shutdown (overload, overheat...) keeps the alert
    until REBOOT, and answers every later instruction with the alert bit, so a resumed run
    could not even enable torque. Starting (or resuming) a run is the operator's statement
    that the cause was removed; if the error is still latched after the reboot, the cause is
    still there and the rig refuses with the servo and the decoded error. Returns one message
    per rebooted servo (the runner records them as events).
    """
    from acquisition.dynamixel import HardwareAlert, decode_hardware_error

    notes = []
    for sid in ids:
        status = bus.hardware_error(sid)
        if not status:
            continue
        names = ", ".join(decode_hardware_error(status)) or f"0x{status:02x}"
        bus.reboot(sid)
        bus.clock.sleep(bus.reboot_settle_s)
        after = bus.hardware_error(sid)
        if after:
            raise HardwareAlert(sid, after, "reboot on rig start", note="; still present")
        notes.append(f"servo {sid}: hardware error [{names}] latched; rebooted, cleared")
    return notes


def _restoring_bus_class() -> type:
    """DynamixelBus that puts a rebooted servo's motion profile back before torque returns.

    Why: REBOOT resets every RAM register, and Profile Velocity/Acceleration (112/108) are RAM;
    the default 0 means "as fast as the Velocity Limit allows" (≈ 3× the sim rig's profile).
    DynamixelBus's on_alert="reboot" restores torque and the goal only, so the arm would race
    to its goal. Here every profile write is remembered, and replayed when torque is enabled
    again on a servo that was rebooted. (Belongs in DynamixelBus._recover; kept here until it
    moves there.)
    """
    from acquisition.dynamixel import ADDR, DynamixelBus

    profile_addrs = (ADDR["profile_acceleration"], ADDR["profile_velocity"])

    class _Bus(DynamixelBus):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            self._profiles: dict[int, dict[int, int]] = {}
            self._rebooted: set[int] = set()
            super().__init__(*args, **kwargs)

        def reboot(self, servo_id: int) -> None:
            super().reboot(servo_id)
            self._rebooted.add(servo_id)

        def write(
            self, servo_id: int, addr: int, size: int, value: int, *, check_alert: bool = True
        ) -> None:
            if addr == ADDR["torque_enable"] and value and servo_id in self._rebooted:
                self._rebooted.discard(servo_id)
                for a, v in self._profiles.get(servo_id, {}).items():
                    super().write(servo_id, a, 4, v, check_alert=False)
            super().write(servo_id, addr, size, value, check_alert=check_alert)
            if addr in profile_addrs and size == 4:
                self._profiles.setdefault(servo_id, {})[addr] = int(value)

    return _Bus


def build_rig(config: RigConfig, *, reboot_alerted: bool = True) -> Rig:
    """Open the bus, axes, light and camera named by the config.

    `reboot_alerted`: reboot servos that hold a latched hardware error (see `clear_alerts`)
    before the axes are set up; profile registers are written afterwards, so a reboot (which
    resets RAM) loses nothing.
    """
    from acquisition.dynamixel import DynamixelAxis, move_together, read_positions

    clock = get_clock(config.clock)
    bus = _restoring_bus_class()(
        config.bus.url,
        baudrate=config.bus.baudrate,
        retries=config.bus.retries,
        on_alert=config.bus.on_alert,
        clock=clock,
    )
    closers: list[Callable[[], None]] = [bus.close]
    recovered: list[str] = []
    if reboot_alerted:
        try:
            for a in config.axes:
                try:
                    bus.ping(a.id)
                except DeviceFault as exc:
                    raise DeviceFault(
                        f"axis {a.role}: servo {a.id} does not answer: {exc}"
                    ) from exc
            recovered = clear_alerts(bus, [a.id for a in config.axes])
        except Exception:
            bus.close()
            raise
    try:
        axes: dict[str, DynamixelAxis] = {}
        for a in config.axes:
            axes[a.role] = DynamixelAxis(
                bus,
                a.id,
                a.role,
                gear_ratio=a.gear_ratio,
                zero_offset_rad=math.radians(a.zero_offset_deg),
                direction=a.direction,
                limits_rad=(math.radians(a.min_deg), math.radians(a.max_deg)),
                profile_velocity=a.profile_velocity,
                profile_acceleration=a.profile_acceleration,
            )
        light = build_light(config, clock)
        closers.append(getattr(light, "close", lambda: None))
        try:
            factory = CAMERA_BACKENDS[config.camera.backend]
        except KeyError:
            raise ValueError(
                f"camera.backend {config.camera.backend!r} is not available; known: "
                f"{', '.join(sorted(CAMERA_BACKENDS)) or 'none'}"
            ) from None
        camera = factory(config, clock)
        closers.append(getattr(camera, "close", lambda: None))
    except BaseException:
        # Whatever opened so far is closed again: ports are opened exclusively, and a retry
        # (or the next resume) must find them free.
        for close in reversed(closers):
            try:
                close()
            except Exception:
                pass
        raise
    ordered = list(axes.values())
    return Rig(
        config=config,
        axes=dict(axes),
        light=light,
        camera=camera,
        clock=clock,
        kinematics=Kinematics(config),
        closers=closers,
        recovered=recovered,
        move_together=lambda targets: move_together(
            [axes[r] for r in targets], [targets[r] for r in targets]
        ),
        read_positions=lambda: dict(zip(axes, read_positions(ordered), strict=True)),
    )

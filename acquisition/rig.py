"""A rig: axes, light, camera and clock, built from a rig config.

Backends are chosen by URL and registry (like pySerial's `loop://`): the bus URL goes to
`serial_for_url`, so `dxlsim://NAME` reaches the simulator's emulator once the simulator has
installed its URL handlers; camera backends are looked up by name in `CAMERA_BACKENDS`, where
the simulator registers "sim". Runtime code here never imports the simulator.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from acquisition.clock import Clock, get_clock
from acquisition.config import RigConfig
from acquisition.kinematics import Kinematics
from acquisition.protocols import Axis, Camera, LightSource

__all__ = ["Rig", "CAMERA_BACKENDS", "register_camera_backend", "build_rig"]

CameraFactory = Callable[[RigConfig, Clock], Camera]
CAMERA_BACKENDS: dict[str, CameraFactory] = {}


def register_camera_backend(name: str, factory: CameraFactory) -> None:
    CAMERA_BACKENDS[name] = factory


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

    def move(self, targets: dict[str, float]) -> None:
        """Start all axes toward their targets at once (sync write when the bus has it)."""
        if self.move_together is not None:
            self.move_together(targets)
        else:
            for role, angle in targets.items():
                self.axes[role].move_to(angle)

    def wait(self, timeout_s: float) -> None:
        for ax in self.axes.values():
            ax.wait(timeout_s)

    def positions(self) -> dict[str, float]:
        if self.read_positions is not None:
            return self.read_positions()
        return {role: ax.position() for role, ax in self.axes.items()}

    def torque(self, enabled: bool) -> None:
        for ax in self.axes.values():
            ax.torque(enabled)

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


def build_rig(config: RigConfig) -> Rig:
    """Open the bus, axes, light and camera named by the config."""
    from acquisition.dynamixel import DynamixelAxis, DynamixelBus, move_together, read_positions
    from acquisition.light import SerialLight

    clock = get_clock(config.clock)
    bus = DynamixelBus(
        config.bus.url,
        baudrate=config.bus.baudrate,
        retries=config.bus.retries,
        on_alert=config.bus.on_alert,
        clock=clock,
    )
    closers: list[Callable[[], None]] = [bus.close]
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
    light = SerialLight(config.light.url, clock=clock)
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
    ordered = list(axes.values())
    return Rig(
        config=config,
        axes=dict(axes),
        light=light,
        camera=camera,
        clock=clock,
        kinematics=Kinematics(config),
        closers=closers,
        move_together=lambda targets: move_together(
            [axes[r] for r in targets], [targets[r] for r in targets]
        ),
        read_positions=lambda: dict(zip(axes, read_positions(ordered), strict=True)),
    )

"""The simulated rig as one object: an emulated servo bus, light controller, virtual clock and a
Mitsuba camera, registered under the names a rig config uses (`dxlsim://NAME`,
`lightsim://NAME`, clock "sim", camera backend "sim").

Physics and devices stay separate (after ophyd-async's sim devices): the bus and light are
emulators reached through the real drivers; the camera asks the emulator where the arms truly
are, so commanded-vs-actual errors (injected offsets, a stuck axis) show up in the images.
"""

from __future__ import annotations

import math

import numpy as np

from acquisition.clock import VirtualClock, register_clock
from acquisition.config import RigConfig
from acquisition.kinematics import Kinematics
from acquisition.rig import register_camera_backend
from simulator.camera import SimCamera
from simulator.dxl import EmulatedBus, register_bus
from simulator.faults import CameraFaults, FaultyCamera
from simulator.light import EmulatedLight, register_light
from simulator.render import Renderer
from simulator.scene import Scene

__all__ = ["SimWorld", "url_name"]

TICKS_PER_REV = 4096


def url_name(url: str, scheme: str) -> str | None:
    prefix = f"{scheme}://"
    if not url.startswith(prefix):
        return None
    return url[len(prefix) :].split("?", 1)[0].strip("/")


class SimWorld:
    """Build and register the simulated devices named by `rig`."""

    def __init__(self, rig: RigConfig, scene: Scene, *, renderer: Renderer | None = None) -> None:
        self.rig = rig
        self.scene = scene
        self.clock = VirtualClock()
        self.kinematics = Kinematics(rig)
        rng = np.random.default_rng(scene.seed)
        self.bus = EmulatedBus(self.clock, rng=rng)
        for ax in rig.axes:
            park = ax.park_deg if ax.park_deg is not None else max(ax.min_deg, 0.0)
            self.bus.add_servo(ax.id, ax.model, position_ticks=self._ticks(ax, math.radians(park)))
        self.light = EmulatedLight(
            self.clock, name=rig.name, rng=rng, drift_per_hour=scene.light.drift_per_hour
        )
        self._renderer = renderer
        self.camera: SimCamera | None = None
        # Camera fault knob (a capture that returns no frame): the rig gets the SimCamera
        # wrapped in a FaultyCamera that consults this; `self.camera` stays the bare device.
        self.camera_faults = CameraFaults(rng)
        if rig.clock == "sim":
            register_clock("sim", self.clock)
        if (name := url_name(rig.bus.url, "dxlsim")) is not None:
            register_bus(name, self.bus)
        if (name := url_name(rig.light.url, "lightsim")) is not None:
            register_light(name, self.light)
        if rig.camera.backend == "sim":
            register_camera_backend("sim", self._make_camera)

    # -- axis geometry (the rig's truth) -----------------------------------------------------
    @staticmethod
    def _ticks(ax, angle_rad: float) -> int:
        zero = math.radians(ax.zero_offset_deg)
        return int(
            round((angle_rad - zero) * ax.direction * ax.gear_ratio * TICKS_PER_REV / (2 * math.pi))
        )

    def true_axes_rad(self) -> dict[str, float]:
        """Physical axis angles (what the arms really are at), from the emulator's state."""
        ticks = self.bus.true_positions_ticks()
        out = {}
        for ax in self.rig.axes:
            out[ax.role] = (
                math.radians(ax.zero_offset_deg)
                + ax.direction * ticks[ax.id] * (2 * math.pi / TICKS_PER_REV) / ax.gear_ratio
            )
        return out

    def positions_m(self) -> tuple[np.ndarray, np.ndarray]:
        axes = self.true_axes_rad()
        return self.kinematics.light_position_m(axes), self.kinematics.camera_position_m(axes)

    def _make_camera(self, rig: RigConfig, clock) -> FaultyCamera:  # noqa: ANN001 - factory
        if self.camera is None:
            self.camera = SimCamera(
                self.scene,
                clock,
                self.positions_m,
                self.light.true_level,
                readout_s=rig.camera.readout_s,
                renderer=self._renderer,
            )
        return FaultyCamera(self.camera, self.camera_faults)

"""The simulated rig as one object: a lab rig whose devices happen to be emulated.

`EmulatedDevices` are the servo bus and the light controller (Protocol 2.0 and gonio-light
emulators) with their clock. `SimWorld` is what the acquiring process sees: those devices
in-process (registered as `dxlsim://NAME`, `lightsim://NAME`, clock "sim"), or — when the rig
file names serial devices — the devices of a *pretend lab* running in another process
(simulator.pretend_lab), reached through the ptys like a USB adapter, whose physical truth (true
arm angles, true lamp output) the simulated camera asks over the lab's truth socket. The camera
(camera backend "sim") renders the world's truth: the scene, completed by the rig file's
description (simulator.scene.world_scene).

Hands: a lab's calibration needs an operator (cap the lens, mount the flat source, swap the
sample for the reference target or a board). `SimWorld.hands(operator)` wraps any operator so
that a confirmed step is *performed* in the emulated world — the camera then sees a capped lens,
the flat source, the target or the board. The questions are the lab's own; only the hands are
simulated.

Physics and devices stay separate (after ophyd-async's sim devices): the bus and light are
emulators reached through the real drivers; the camera asks where the arms truly are, so
commanded-vs-actual errors show up in the images.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np

from acquisition.clock import Clock, SystemClock, VirtualClock, register_clock
from acquisition.config import RigConfig
from acquisition.operator import Operator, OperatorStep
from acquisition.rig import register_camera_backend
from plumbing.config import ConfigError
from simulator.arms import ArmPose, arm_pose
from simulator.camera import SimCamera, WorldView
from simulator.dxl import EmulatedBus, register_bus
from simulator.faults import CameraFaults, FaultyCamera
from simulator.light import EmulatedLight, register_light
from simulator.render import Renderer, check_material
from simulator.scene import DiffuseMaterial, Scene, world_scene

__all__ = ["SimWorld", "EmulatedDevices", "SimHands", "url_name", "TICKS_PER_REV"]

TICKS_PER_REV = 4096


def url_name(url: str, scheme: str) -> str | None:
    prefix = f"{scheme}://"
    if not url.startswith(prefix):
        return None
    return url[len(prefix) :].split("?", 1)[0].strip("/")


def axis_ticks(ax, angle_rad: float) -> int:  # AxisConfig
    """Servo ticks of an axis at a physical angle (the rig's truth: its stated zero offset)."""
    zero = math.radians(ax.zero_offset_deg)
    return int(
        round((angle_rad - zero) * ax.direction * ax.gear_ratio * TICKS_PER_REV / (2 * math.pi))
    )


def axes_from_ticks(rig: RigConfig, ticks: dict[int, int]) -> dict[str, float]:
    """Physical axis angles (rad) from the servos' true tick positions."""
    out = {}
    for ax in rig.axes:
        out[ax.role] = (
            math.radians(ax.zero_offset_deg)
            + ax.direction * ticks[ax.id] * (2 * math.pi / TICKS_PER_REV) / ax.gear_ratio
        )
    return out


class EmulatedDevices:
    """The servo bus and light-controller emulators of a rig, on one clock."""

    def __init__(self, rig: RigConfig, scene: Scene, clock: Clock) -> None:
        self.clock = clock
        rng = np.random.default_rng(scene.seed)
        self.bus = EmulatedBus(clock, rng=rng)
        for ax in rig.axes:
            park = ax.park_deg if ax.park_deg is not None else max(ax.min_deg, 0.0)
            self.bus.add_servo(ax.id, ax.model, position_ticks=axis_ticks(ax, math.radians(park)))
        self.light = EmulatedLight(
            clock, name=rig.name, rng=rng, drift_per_hour=scene.light.drift_per_hour
        )

    def state(self) -> dict[str, Any]:
        """What the camera needs to know of the physical world right now."""
        return {
            "ticks": {int(k): int(v) for k, v in self.bus.true_positions_ticks().items()},
            "last_move": {int(sid): int(s.last_move) for sid, s in self.bus.servos.items()},
            "light_level": float(self.light.true_level()),
            # not for the camera: so a test can see a safe stop while the lab keeps running
            "torque_enable": {
                str(sid): int(servo.register("torque_enable"))
                for sid, servo in self.bus.servos.items()
            },
        }


@dataclass
class HolderState:
    """What the camera faces: its lens (open, capped, the flat source) and what is in the
    sample holder (the sample, the reference target, a calibration board)."""

    lens: str = "open"
    holder: str = "sample"
    board: Any = None
    manual_lamp_on: bool = False
    history: list[str] = field(default_factory=list)


class SimHands:
    """An operator whose confirmed steps happen in the emulated world (see module doc)."""

    def __init__(self, inner: Operator, world: SimWorld) -> None:
        self.inner = inner
        self.world = world

    @property
    def reason(self) -> str | None:
        return getattr(self.inner, "reason", None)

    def confirm(self, step: OperatorStep) -> bool:
        if not self.inner.confirm(step):
            return False
        self.world.perform(step)
        return True


class SimWorld:
    """Build and register the simulated devices named by `rig` (see module doc)."""

    def __init__(self, rig: RigConfig, scene: Scene, *, renderer: Renderer | None = None) -> None:
        self.rig = rig
        self.scene = world_scene(scene, rig)
        self.state = HolderState()
        self.remote = None
        if url_name(rig.bus.url, "dxlsim") is not None:
            self.clock: Clock = VirtualClock() if rig.clock == "sim" else SystemClock()
            self.devices: EmulatedDevices | None = EmulatedDevices(rig, self.scene, self.clock)
            register_bus(url_name(rig.bus.url, "dxlsim"), self.devices.bus)
            if (name := url_name(rig.light.url, "lightsim")) is not None:
                register_light(name, self.devices.light)
        else:
            # Serial devices: a pretend lab serves them from another process.
            from simulator.truth_channel import TruthClient

            self.clock = SystemClock()
            self.devices = None
            self.remote = TruthClient.beside(rig.bus.url)
        self._renderer = renderer
        self.camera: SimCamera | None = None
        # Instrument errors applied so far (true_axes_rad).
        self.effect_counts: Counter[str] = Counter()
        rng = np.random.default_rng(self.scene.seed)
        # Camera fault knob (a capture that returns no frame): the rig gets the SimCamera
        # wrapped in a FaultyCamera that consults this; `self.camera` stays the bare device.
        self.camera_faults = CameraFaults(rng)
        if rig.clock == "sim":
            if self.devices is None:
                raise ConfigError(
                    'clock = "sim" needs the in-process emulators (dxlsim:// bus); a pretend '
                    'lab on serial devices runs on the wall clock: use clock = "system"'
                )
            register_clock("sim", self.clock)
        if rig.camera.backend == "sim":
            if renderer is None:
                check_material(self.scene)  # before a plan is announced or a run exists
            register_camera_backend("sim", self._make_camera)

    # -- the emulators (in-process worlds only) -------------------------------------------------
    @property
    def bus(self) -> EmulatedBus:
        if self.devices is None:
            raise AttributeError("the servo bus runs in the pretend lab's process")
        return self.devices.bus

    @property
    def light(self) -> EmulatedLight:
        if self.devices is None:
            raise AttributeError("the light controller runs in the pretend lab's process")
        return self.devices.light

    # -- physical truth ---------------------------------------------------------------------
    def _physical(self) -> dict[str, Any]:
        return self.devices.state() if self.devices is not None else self.remote.state()

    def true_axes_rad(self) -> dict[str, float]:
        """Physical axis angles (what the arms really are at): the servos' true ticks through
        the rig file's zero offsets, plus the world's instrument errors (scene [geometry]: zero
        errors, backlash, arm sag — see simulator.scene.GeometryTruth). Each error runs only
        when the scene states it (counted in `effect_counts`)."""
        physical = self._physical()
        axes = axes_from_ticks(self.rig, physical["ticks"])
        geo = self.scene.geometry
        for role, err in geo.axis_zero_error_deg.items():
            if role in axes:
                self.effect_counts["zero_error"] += 1
                axes[role] += math.radians(err)
        if geo.backlash_deg:
            self._backlash(axes, physical.get("last_move", {}))
        for role, sag in geo.compliance_deg.items():
            if role in axes:
                self.effect_counts["compliance"] += 1
                # gravity torque ∝ sin(angle from vertical); sag pulls the arm toward horizontal
                axes[role] += math.radians(sag) * math.sin(axes[role])
        return axes

    def _backlash(self, axes: dict[str, float], last_move: dict) -> None:
        """The arm lags the direction its servo last moved in by half the play (before any move
        it sits centred in its play). Directions are the emulated servos' (tick sign) times the
        axis' direction sign, i.e. of the physical angle."""
        by_role = {ax.role: ax for ax in self.rig.axes}
        for role, play in self.scene.geometry.backlash_deg.items():
            ax = by_role.get(role)
            if ax is None or role not in axes:
                continue
            self.effect_counts["backlash"] += 1
            move = int(last_move.get(ax.id, last_move.get(str(ax.id), 0))) * ax.direction
            axes[role] -= 0.5 * math.radians(play) * move

    def arm_pose(self) -> ArmPose:
        """Where the lamp is and how the camera is posed, in the sample's frame, at the arms'
        true angles (simulator.arms: the world's own forward kinematics, each axis a Mitsuba
        transform), with the scene's distance, roll and tilt errors (each counted in
        `effect_counts` when the scene states it)."""
        geo = self.scene.geometry
        for name, on in (
            ("light_distance", geo.light_distance_error_m),
            ("camera_distance", geo.camera_distance_error_m),
            ("sample_tilt", geo.sample_tilt_deg),
            ("camera_roll", geo.camera_roll_error_deg),
        ):
            if on:
                self.effect_counts[name] += 1
        return arm_pose(self.rig, self.true_axes_rad(), geo)

    def light_level(self) -> float:
        if self.rig.light.manual:
            return 1.0 if self.state.manual_lamp_on else 0.0
        return float(self._physical()["light_level"])

    # -- hands --------------------------------------------------------------------------------
    def hands(self, operator: Operator) -> SimHands:
        return SimHands(operator, self)

    def perform(self, step: OperatorStep) -> None:
        """Do a confirmed operator step in the emulated world."""
        st, a = self.state, step.action
        st.history.append(a)
        if a == "cap_lens":
            st.lens = "capped"
        elif a == "mount_flat":
            st.lens = "flat"
        elif a in ("uncap_lens", "unmount_flat"):
            st.lens = "open"
        elif a == "mount_reference":
            st.holder = "reference"
        elif a == "mount_sample":
            st.holder, st.board = "sample", None
        elif a == "mount_board":
            st.holder, st.board = "board", SimpleNamespace(**step.detail["board_fields"])
        elif a == "lamp_on":
            st.manual_lamp_on = True
        elif a == "lamp_off":
            st.manual_lamp_on = False

    # -- the camera ---------------------------------------------------------------------------
    def reference_material(self) -> Any:
        """The reference target's true BRDF: the scene's `reference_target`, else a Lambertian
        of the rig's certified albedo."""
        if self.scene.reference_target is not None:
            return self.scene.reference_target
        ref = self.rig.reference
        if ref is None or ref.type != "lambertian":
            raise ConfigError(
                "the simulated world needs [reference_target] in the scene for a reference "
                "target described by a table"
            )
        return DiffuseMaterial(reflectance=tuple(ref.albedo))

    def _view(self) -> WorldView:
        ref = self.rig.reference
        return WorldView(
            state=self.state,
            reference_material=self.reference_material if ref is not None else None,
            reference_size_m=None if ref is None else ref.size_m,
        )

    def _make_camera(self, rig: RigConfig, clock) -> FaultyCamera:  # factory
        if self.camera is None:
            self.camera = SimCamera(
                self.scene,
                clock,
                self.arm_pose,
                self.light_level,
                readout_s=rig.camera.readout_s,
                renderer=self._renderer,
                world=self._view(),
            )
        return FaultyCamera(self.camera, self.camera_faults)

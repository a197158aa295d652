"""Hardware as typing.Protocols (after ophyd-async/bluesky). Plans and the runner are written
only against these, so the same run executes on a real rig or on the simulated one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from plumbing.errors import UserError

__all__ = [
    "Axis",
    "LightSource",
    "LightStatus",
    "Camera",
    "Frame",
    "FrameLevels",
    "DeviceFault",
    "AxisTimeout",
]


class DeviceFault(UserError, RuntimeError):
    """A device reported a fault (hardware alert, no reply, ...). The runner stops safely."""


class AxisTimeout(DeviceFault):
    """An axis did not arrive within its timeout."""


@runtime_checkable
class Axis(Protocol):
    """One rotary axis. Angles are radians in the axis' own frame (after gear, offset, sign)."""

    name: str

    def move_to(self, angle_rad: float) -> None:
        """Start a move; returns at once."""

    def position(self) -> float:
        """Measured angle in radians."""

    def wait(self, timeout_s: float) -> None:
        """Block until arrived; raise AxisTimeout after timeout_s."""

    def torque(self, enabled: bool) -> None: ...

    def stop(self) -> None:
        """Stop where it is (hold position)."""

    def status(self) -> dict[str, Any]:
        """Temperature, voltage, hardware error status... for the manifest."""


@dataclass
class LightStatus:
    on: bool
    intensity: float  # relative level 0..1 as commanded
    measured: float | None = None  # monitor reading, relative, if the source has one
    fault: str | None = None


@runtime_checkable
class LightSource(Protocol):
    def on(self) -> None: ...

    def off(self) -> None: ...

    def set_intensity(self, level: float) -> None:
        """Relative level in [0, 1]."""

    def status(self) -> LightStatus: ...


@dataclass
class Frame:
    """What a camera produced, untouched: the file bytes and their suffix (".dng", ".exr",
    ".nef", ...), plus metadata the camera reported (exposure_s, gain, temperature...).

    `levels` is optional: a camera that already holds its pixels may attach them as linear
    levels (0 = black, 1 = clip level), any shape, for auto-exposure; it is never stored
    (the file bytes are the record). Without it the runner asks a `FrameLevels` decoder.
    """

    data: bytes
    suffix: str
    metadata: dict[str, Any] = field(default_factory=dict)
    levels: Any = None


# Linear levels (0 = black, 1 = the camera's clip level) of the *sample-region* pixels of a
# frame, given the measured axis angles (rad) at capture. Injected by the layer above
# (gonio.pipeline decodes with calibration.decode and projects the sample with the rig
# geometry), because acquisition may not import calibration.
FrameLevels = Callable[[Frame, dict[str, float]], Any]


@runtime_checkable
class Camera(Protocol):
    def capture(self, exposure_s: float) -> Frame: ...

    def supported_exposures(self) -> Sequence[float] | tuple[float, float]:
        """Either a list of discrete exposure times or a (min_s, max_s) range."""

    def describe(self) -> dict[str, Any]:
        """What calibration needs to know about this camera, frozen into run.toml:
        resolution [w, h], fov_deg (horizontal) or fx/fy/cx/cy in pixels, f_number,
        pixel_pitch_m, quantum_efficiency, gain_e_per_dn, black_level_dn, white_level_dn,
        wavelength_m, format."""

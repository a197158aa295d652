"""Rig kinematics: a pose (θ_i, φ_i, θ_o, φ_o) ↔ axis targets, and the constraints that make a
pose impossible (arm limits, light–camera occlusion).

Preset "two-arm": two spherical arms centred on the sample. The light arm carries the source at
`light_distance_m`, the camera arm the camera at `camera_distance_m`; each arm has an elevation
axis (θ from the sample normal) and an azimuth axis (φ from +x toward +y).

The camera's orientation is forward kinematics of its arm (`Kinematics.camera_rotation`): at
the arms' zero it looks down the normal, its image right along +y and image down along +x (the
rig's zero mount), turned about its optical axis by the rig file's `camera_roll_deg`; the
elevation axis turns it about the arm's horizontal axis, the azimuth axis about the normal:

    R = R_z(φ) · R_y(θ) · R₀ · R_roll(ρ)          (columns: image right, image down, forward)

so the image turns with the arm's azimuth at θ = 0 as a real camera does: there is no pole.
Away from the normal, with ρ = 0, this is the camera whose image keeps the horizon level.

Preset "inplane": both arms swing in the lab's x–z plane. The light arm is at lab azimuth 0
with elevation `light_theta` ≥ 0; the camera arm has a signed elevation `camera_theta`:
positive is across the normal from the light (lab azimuth π, the specular side), negative on
the light's side (lab azimuth 0). An optional turntable `sample_azimuth` = α turns the sample
about its normal by α, so a lab azimuth φ_L is the sample-frame azimuth φ_L − α. Such a rig
reaches exactly the poses with Δφ = φ_o − φ_i ∈ {0, π} (or θ_i = 0 / θ_o = 0), and, without a
turntable, only φ_i = 0. Its camera: R = R_z(−α) · R_y(−c) · R₀ · R_roll(ρ), so a camera whose
image is upright on one side of the normal is upside down on the other, as on a real arm that
swings through the normal (`camera_roll_deg = 180` makes the specular side upright).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from acquisition.config import RigConfig
from brdfdata.directions import spherical_to_vector
from plumbing.errors import UserError

__all__ = ["Pose", "Unreachable", "Kinematics", "ZERO_MOUNT", "axis_rotation"]

TWO_PI = 2.0 * math.pi

#: R₀: the camera at the arms' zero (module docstring), columns image right, image down and
#: forward in the sample frame.
ZERO_MOUNT = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def axis_rotation(axis: str, angle_rad: float) -> np.ndarray:
    """The right-handed rotation by `angle_rad` about the frame's "x", "y" or "z" axis."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    if axis == "x":
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    if axis == "y":
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Pose:
    """Directions in the sample frame, radians."""

    theta_i: float
    phi_i: float
    theta_o: float
    phi_o: float

    @classmethod
    def from_deg(cls, ti: float, pi: float, to: float, po: float) -> Pose:
        return cls(*(math.radians(a) for a in (ti, pi, to, po)))

    def deg(self) -> tuple[float, float, float, float]:
        return tuple(math.degrees(a) for a in (self.theta_i, self.phi_i, self.theta_o, self.phi_o))

    @property
    def wi(self) -> np.ndarray:
        return spherical_to_vector(self.theta_i, self.phi_i)

    @property
    def wo(self) -> np.ndarray:
        return spherical_to_vector(self.theta_o, self.phi_o)


class Unreachable(UserError, ValueError):
    """The rig cannot take this pose; the message says why in one line."""


class Kinematics:
    def __init__(self, rig: RigConfig) -> None:
        self.rig = rig
        self.geometry = rig.geometry
        self.limits = {a.role: (math.radians(a.min_deg), math.radians(a.max_deg)) for a in rig.axes}

    # -- pose → axes -------------------------------------------------------------------------
    def _fit_angle(self, role: str, angle: float, periodic: bool) -> float:
        lo, hi = self.limits[role]
        if periodic:
            # Azimuth is periodic: pick the representative 2πk + angle that lies in the limits.
            k = math.ceil((lo - angle) / TWO_PI - 1e-12)
            candidate = angle + k * TWO_PI
            if candidate <= hi + 1e-12:
                return min(max(candidate, lo), hi)
        elif lo - 1e-12 <= angle <= hi + 1e-12:
            return min(max(angle, lo), hi)
        raise Unreachable(
            f"axis {role} cannot reach {math.degrees(angle):.2f} deg "
            f"(limits {math.degrees(lo):.1f}..{math.degrees(hi):.1f} deg)"
        )

    def check(self, pose: Pose) -> None:
        """Raise Unreachable with the reason, or return None."""
        self.targets(pose)

    def targets(self, pose: Pose) -> dict[str, float]:
        """Axis targets in radians for a pose, or Unreachable."""
        self._check_common(pose)
        if self.geometry.preset == "inplane":
            return self._inplane_targets(pose)
        return {
            "light_theta": self._fit_angle("light_theta", pose.theta_i, periodic=False),
            "light_phi": self._fit_angle("light_phi", pose.phi_i, periodic=True),
            "camera_theta": self._fit_angle("camera_theta", pose.theta_o, periodic=False),
            "camera_phi": self._fit_angle("camera_phi", pose.phi_o, periodic=True),
        }

    def _inplane_targets(self, pose: Pose) -> dict[str, float]:
        eps = 1e-9
        if pose.theta_i <= eps:  # the light on the normal: turn the sample to the camera
            alpha, sign = math.pi - pose.phi_o, 1.0
        else:
            alpha = -pose.phi_i
            dphi = (pose.phi_o - pose.phi_i) % TWO_PI
            if pose.theta_o <= eps or abs(dphi - math.pi) <= 1e-7:
                sign = 1.0
            elif min(dphi, TWO_PI - dphi) <= 1e-7:
                sign = -1.0
            else:
                raise Unreachable(
                    f"an in-plane rig measures only Δφ = 0 or 180 deg "
                    f"(got Δφ = {math.degrees(dphi):.2f} deg)"
                )
        out = {
            "light_theta": self._fit_angle("light_theta", pose.theta_i, periodic=False),
            "camera_theta": self._fit_angle("camera_theta", sign * pose.theta_o, periodic=False),
        }
        if "sample_azimuth" in self.limits:
            out["sample_azimuth"] = self._fit_angle("sample_azimuth", alpha, periodic=True)
        elif abs(math.remainder(alpha, TWO_PI)) > 1e-9:
            raise Unreachable(
                f"φ_i = {math.degrees(pose.phi_i):.2f} deg needs a turntable "
                "(no sample_azimuth axis)"
            )
        return out

    def _check_common(self, pose: Pose) -> None:
        g = self.geometry
        max_theta = math.radians(g.max_theta_deg)
        for label, theta in (("theta_i", pose.theta_i), ("theta_o", pose.theta_o)):
            if not 0.0 <= theta <= max_theta + 1e-12:
                raise Unreachable(
                    f"{label} = {math.degrees(theta):.2f} deg is outside 0..{g.max_theta_deg} deg"
                )
        sep = math.degrees(separation_rad(pose))
        # 1e-9 deg of slack: a grid pose exactly at the limit (e.g. 15° vs 10° on the same
        # side) must not be rejected by rounding in the vector arithmetic.
        if sep < g.min_separation_deg - 1e-9:
            raise Unreachable(
                f"light and camera {sep:.2f} deg apart, closer than min_separation_deg = "
                f"{g.min_separation_deg} (the light would occlude the camera)"
            )

    # -- axes → pose and positions -------------------------------------------------------------
    def pose(self, axes_rad: dict[str, float]) -> Pose:
        if self.geometry.preset == "inplane":
            alpha = axes_rad.get("sample_azimuth", 0.0)
            cam = axes_rad["camera_theta"]
            phi_lab = math.pi if cam >= 0 else 0.0
            return Pose(
                axes_rad["light_theta"],
                (-alpha) % TWO_PI,
                abs(cam),
                (phi_lab - alpha) % TWO_PI,
            )
        return Pose(
            axes_rad["light_theta"],
            axes_rad["light_phi"] % TWO_PI,
            axes_rad["camera_theta"],
            axes_rad["camera_phi"] % TWO_PI,
        )

    def light_position_m(self, axes_rad: dict[str, float]) -> np.ndarray:
        p = self.pose(axes_rad)
        return self.geometry.light_distance_m * spherical_to_vector(p.theta_i, p.phi_i)

    def camera_position_m(self, axes_rad: dict[str, float]) -> np.ndarray:
        p = self.pose(axes_rad)
        return self.geometry.camera_distance_m * spherical_to_vector(p.theta_o, p.phi_o)

    def camera_rotation(self, axes_rad: dict[str, float], roll_rad: float = 0.0) -> np.ndarray:
        """Camera → sample rotation (3×3, columns: image right, image down, forward; OpenCV's
        camera axes) at the axes' angles: the forward kinematics of the module docstring, the
        rig file's `camera_roll_deg` plus `roll_rad` (what `gonio calibrate-rig` measured)."""
        roll = math.radians(self.geometry.camera_roll_deg) + roll_rad
        mount = ZERO_MOUNT @ axis_rotation("z", roll)
        if self.geometry.preset == "inplane":
            arm = axis_rotation("z", -axes_rad.get("sample_azimuth", 0.0)) @ axis_rotation(
                "y", -axes_rad["camera_theta"]
            )
        else:
            arm = axis_rotation("z", axes_rad["camera_phi"]) @ axis_rotation(
                "y", axes_rad["camera_theta"]
            )
        return arm @ mount


def separation_rad(pose: Pose) -> float:
    """Angle between the light and camera directions of a pose.

    atan2(|wi × wo|, wi · wo): accurate for both tiny and near-π angles (arccos of a dot
    product is not). Scalar arithmetic, since it runs once per planned pose: for 3-vectors
    numpy's cross and norm cost ~100 µs a call, most of a 10⁵-pose plan's build time.
    """
    st_i, st_o = math.sin(pose.theta_i), math.sin(pose.theta_o)
    a = (st_i * math.cos(pose.phi_i), st_i * math.sin(pose.phi_i), math.cos(pose.theta_i))
    b = (st_o * math.cos(pose.phi_o), st_o * math.sin(pose.phi_o), math.cos(pose.theta_o))
    cross = (
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    )
    return math.atan2(math.hypot(*cross), a[0] * b[0] + a[1] * b[1] + a[2] * b[2])

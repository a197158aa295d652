"""The simulated rig's arms as Mitsuba transforms: where the lamp truly is and how the camera is
truly posed, in the sample's frame, at the arms' true angles.

Each axis is one Mitsuba rotation (``mi.ScalarTransform4f().rotate``), composed the way the arms
are built: the azimuth axis carries the elevation axis, which carries the arm, at whose end the
camera sits on its mount. The camera at the arms' zero (its mount) is what the rig describes:
above the sample looking down the normal, image top toward −x (Mitsuba's ``look_at`` from
(0, 0, d) toward the centre with up = −x), then turned about its optical axis by the rig file's
``camera_roll_deg`` and the world's own error of it (scene [geometry] ``camera_roll_error_deg``).

This is the world's forward kinematics, written here and not imported from the lab's
(`acquisition.kinematics`), so that each checks the other: where the lab's rule for the camera's
orientation is wrong, calibrated directions disagree with the directions rendered here
(tests/simulator/test_arms.py, tests/calibration/test_camera_pose.py).

Frames: Mitsuba's camera frame has columns (left, up, forward); OpenCV's is (right, down,
forward) = (−left, −up, forward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from acquisition.config import RigConfig
from simulator.scene import GeometryTruth

__all__ = ["ArmPose", "arm_pose"]


@dataclass(frozen=True)
class ArmPose:
    """The lamp's position (3,) and the camera's to_world (4×4, Mitsuba's camera frame: columns
    left, up, forward, origin), metres, sample frame."""

    light_m: np.ndarray
    camera_to_world: np.ndarray

    @property
    def camera_m(self) -> np.ndarray:
        return self.camera_to_world[:3, 3].copy()


def _mi():
    import mitsuba as mi

    from simulator.variant import ensure_variant

    if mi.variant() is None:
        ensure_variant()
    return mi


def arm_pose(rig: RigConfig, axes_rad: dict[str, float], truth: GeometryTruth) -> ArmPose:
    """The arms at their true angles `axes_rad` (the servos' ticks through the rig file's zero
    offsets, plus the world's errors: simulator.world.SimWorld.true_axes_rad); the world's
    lamp- and camera-distance errors, the camera's roll error and the sample's tilt from
    `truth`."""
    mi = _mi()
    t4 = mi.ScalarTransform4f

    def rot(axis: tuple[float, float, float], angle_rad: float):
        return t4().rotate(list(axis), math.degrees(angle_rad))

    geo = rig.geometry
    z, y = (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)
    if geo.preset == "inplane":
        # The sample turns by α on its turntable, so the lab turns by −α in the sample's frame;
        # the light arm swings at lab azimuth 0, the camera arm's signed angle c swings it
        # toward −x for c > 0 (the specular side).
        turn = rot(z, -axes_rad.get("sample_azimuth", 0.0))
        light_arm = turn @ rot(y, axes_rad["light_theta"])
        camera_arm = turn @ rot(y, -axes_rad["camera_theta"])
    else:
        light_arm = rot(z, axes_rad["light_phi"]) @ rot(y, axes_rad["light_theta"])
        camera_arm = rot(z, axes_rad["camera_phi"]) @ rot(y, axes_rad["camera_theta"])
    d_light = geo.light_distance_m + truth.light_distance_error_m
    d_camera = geo.camera_distance_m + truth.camera_distance_error_m
    mount = t4().look_at(origin=[0.0, 0.0, 0.0], target=[0.0, 0.0, -1.0], up=[-1.0, 0.0, 0.0])
    roll = math.radians(geo.camera_roll_deg + truth.camera_roll_error_deg)
    camera = camera_arm @ t4().translate([0.0, 0.0, d_camera]) @ mount @ rot(z, roll)
    light = light_arm @ t4().translate([0.0, 0.0, d_light])
    if truth.sample_tilt_deg:
        # The sample's frame: a point p of it sits at R_τ p in the rig's, R_τ = R_y(τ_y) R_x(τ_x),
        # so the arms seen from it are turned by R_τᵀ = R_x(−τ_x) R_y(−τ_y).
        tx = math.radians(truth.sample_tilt_deg.get("x", 0.0))
        ty = math.radians(truth.sample_tilt_deg.get("y", 0.0))
        untilt = rot((1.0, 0.0, 0.0), -tx) @ rot(y, -ty)
        camera, light = untilt @ camera, untilt @ light
    light_m = np.asarray(light.matrix, dtype=np.float64)[:3, 3]
    return ArmPose(light_m, np.asarray(camera.matrix, dtype=np.float64))

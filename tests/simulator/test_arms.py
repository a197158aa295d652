"""The world's arms (simulator.arms: one Mitsuba rotation per axis) against the lab's forward
kinematics (acquisition.kinematics.Kinematics.camera_rotation, numpy): two implementations of
one rig, each the other's check. Neither is the truth alone; where they agree to the
float32 rounding of Mitsuba's scalar transforms (~1e-7) for every preset, azimuth and roll, a
wrong axis order, sign or mount in either one would show as an error of order one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from acquisition.config import load_rig
from acquisition.kinematics import Kinematics
from simulator.arms import arm_pose
from simulator.render import world_to_camera_cv
from simulator.scene import GeometryTruth
from tests.support.paths import REPO

#: Mitsuba's scalar transforms are float32: a rotation's entries are good to ~1e-7.
FLOAT32 = 1e-6


def _cv(to_world: np.ndarray) -> np.ndarray:
    """Camera → world rotation in OpenCV's axes (right, down, forward) from Mitsuba's (left,
    up, forward) columns."""
    return np.stack([-to_world[:3, 0], -to_world[:3, 1], to_world[:3, 2]], axis=1)


def _rig(preset: str, roll_deg: float):
    rig = load_rig(
        REPO / "configs" / "rigs" / ("inplane.toml" if preset == "inplane" else "sim.toml")
    )
    geo = rig.geometry.model_copy(update={"camera_roll_deg": roll_deg})
    return rig.model_copy(update={"geometry": geo})


@pytest.mark.parametrize("preset", ["two-arm", "inplane"])
@pytest.mark.parametrize("roll_deg", [0.0, 37.0, -90.0])
def test_the_worlds_arms_and_the_labs_kinematics_pose_the_camera_alike(preset, roll_deg) -> None:
    rig = _rig(preset, roll_deg)
    kin = Kinematics(rig)
    rng = np.random.default_rng(7)
    for _ in range(20):
        if preset == "inplane":
            axes = {
                "light_theta": rng.uniform(0.0, 1.4),
                "camera_theta": rng.uniform(-1.4, 1.4),
                "sample_azimuth": rng.uniform(-math.pi, math.pi),
            }
        else:
            axes = {
                "light_theta": rng.uniform(0.0, 1.4),
                "light_phi": rng.uniform(0.0, 2 * math.pi),
                "camera_theta": rng.uniform(0.0, 1.4) * rng.choice([0.0, 1.0]),  # poles too
                "camera_phi": rng.uniform(0.0, 2 * math.pi),
            }
        pose = arm_pose(rig, axes, GeometryTruth())
        assert np.abs(_cv(pose.camera_to_world) - kin.camera_rotation(axes)).max() < FLOAT32
        assert np.abs(pose.camera_m - kin.camera_position_m(axes)).max() < FLOAT32
        assert np.abs(pose.light_m - kin.light_position_m(axes)).max() < FLOAT32


def test_away_from_the_normal_the_unrolled_camera_keeps_the_horizon_level() -> None:
    """With no roll, an oblique camera's image right is horizontal and its image up leans
    toward +z: the look-at camera (simulator.render's free-standing one) to float32."""
    rig = _rig("two-arm", 0.0)
    for theta, phi in ((0.3, 0.0), (0.9, 2.0), (1.3, 4.5)):
        axes = {"light_theta": 0.5, "light_phi": 0.0, "camera_theta": theta, "camera_phi": phi}
        pose = arm_pose(rig, axes, GeometryTruth())
        look = world_to_camera_cv(pose.camera_m)[0].T
        assert np.abs(_cv(pose.camera_to_world) - look).max() < FLOAT32


def test_at_the_normal_the_image_turns_with_the_arms_azimuth() -> None:
    """θ_o = 0: the camera's image right is R_z(φ)·(+y): it turns with the arm, where a
    look-at rule would hold it still. Two azimuths 45° apart give images turned 45°."""
    rig = _rig("two-arm", 0.0)
    rights = []
    for phi_deg in (180.0, 135.0):
        axes = {"light_theta": 0.5, "light_phi": 0.0, "camera_theta": 0.0,
                "camera_phi": math.radians(phi_deg)}  # fmt: skip
        right = _cv(arm_pose(rig, axes, GeometryTruth()).camera_to_world)[:, 0]
        phi = math.radians(phi_deg)
        assert np.abs(right - [-math.sin(phi), math.cos(phi), 0.0]).max() < FLOAT32
        rights.append(right)
    assert math.degrees(math.acos(np.clip(rights[0] @ rights[1], -1, 1))) == pytest.approx(45.0)


def test_the_worlds_roll_error_is_what_the_lab_does_not_know() -> None:
    """The scene's camera_roll_error_deg turns the world's camera about its optical axis; the
    lab's kinematics, told only the rig file's roll, is off by exactly that turn."""
    rig = _rig("two-arm", 10.0)
    axes = {"light_theta": 0.5, "light_phi": 0.0, "camera_theta": 0.4, "camera_phi": 1.0}
    world = _cv(arm_pose(rig, axes, GeometryTruth(camera_roll_error_deg=2.0)).camera_to_world)
    lab = Kinematics(rig).camera_rotation(axes)
    turn = lab.T @ world  # about the optical axis (z) only
    assert abs(turn[2, 2] - 1.0) < FLOAT32
    assert math.degrees(math.atan2(turn[1, 0], turn[0, 0])) == pytest.approx(2.0, abs=1e-4)
    assert np.abs(Kinematics(rig).camera_rotation(axes, math.radians(2.0)) - world).max() < FLOAT32

"""Recover injected camera-arm zero offsets and sample-plane tilt from synthetic board images.

The images come from simulator.board.render_board_views (exact back-projection through a
pinhole + Brown-Conrady lens, independent of OpenCV's projection); the camera poses come from
the *true* (offset) arm angles and a camera turned on its arm, with a tilted, slightly shifted
board, built here with scipy's rotations (the camera: azimuth about z, elevation about y, the
mount looking down with image right along +y, then its roll about the optical axis — the rig's
stated convention, written again here rather than taken from acquisition.kinematics). The fit
sees only the commanded angles and the images. Truth = the injected values.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from acquisition.config import load_rig
from acquisition.kinematics import Kinematics
from calibration.arm_offsets import (
    arm_offsets_from_images,
    board_in_sample,
    camera_centre_in_board,
    fit_arm_offsets,
)
from calibration.camera_model import board_pose, parse_board
from simulator.board import render_board_views
from tests.support.paths import REPO

BOARD = parse_board("charuco:8x6:0.02:0.015:DICT_5X5_100")
# A 640×480 camera, 26° horizontal field: the 16×12 cm board fills about half of it at 0.5 m.
INTR = {"fx": 1400.0, "fy": 1400.0, "cx": 319.5, "cy": 239.5, "dist": [-0.05, 0.02, 0, 0, 0]}
SIZE = (640, 480)
TRUE = {  # degrees
    "camera_theta": 0.35,
    "camera_phi": -0.6,
    "tilt_x": 0.25,
    "tilt_y": -0.15,
    "camera_roll": 1.2,
}
#: The camera at the arms' zero: image right +y, image down +x, forward −z (columns).
MOUNT = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
SHIFT_M = (0.0015, -0.001)
COMMANDED_DEG = [(t, p) for t in (15.0, 35.0, 55.0) for p in (0.0, 90.0, 180.0, -90.0)]


def _axes(theta_deg: float, phi_deg: float) -> dict[str, float]:
    return {
        "light_theta": 0.0,
        "light_phi": 0.0,
        "camera_theta": math.radians(theta_deg),
        "camera_phi": math.radians(phi_deg),
    }


def _true_board_pose(kin: Kinematics, commanded: dict[str, float]):
    true = dict(commanded)
    true["camera_theta"] += math.radians(TRUE["camera_theta"])
    true["camera_phi"] += math.radians(TRUE["camera_phi"])
    c_s = kin.camera_position_m(true)
    arm = Rotation.from_euler("z", true["camera_phi"]) * Rotation.from_euler(
        "y", true["camera_theta"]
    )
    roll = Rotation.from_euler("z", TRUE["camera_roll"], degrees=True).as_matrix()
    r_cam = arm.as_matrix() @ MOUNT @ roll  # camera → sample (columns: camera axes)
    # Board → sample: face up (board z into the board = −z), centred, then the holder's tilt.
    tilt = Rotation.from_euler("xy", [TRUE["tilt_x"], TRUE["tilt_y"]], degrees=True).as_matrix()
    flip = np.diag([1.0, -1.0, -1.0])
    centre = np.array([BOARD.cols * BOARD.square_m / 2, BOARD.rows * BOARD.square_m / 2, 0.0])
    r_bs = tilt @ flip
    t_bs = tilt @ (-flip @ centre + np.array([*SHIFT_M, 0.0]))
    r = r_cam.T @ r_bs
    t = r_cam.T @ (t_bs - c_s)
    return Rotation.from_matrix(r).as_rotvec(), t


@pytest.fixture(scope="module")
def views():
    kin = Kinematics(load_rig(REPO / "configs" / "rigs" / "sim.toml"))
    commanded = [_axes(t, p) for t, p in COMMANDED_DEG]
    poses = [_true_board_pose(kin, a) for a in commanded]
    intr = (INTR["fx"], INTR["fy"], INTR["cx"], INTR["cy"], *SIZE)
    images = render_board_views(BOARD, intr, INTR["dist"], poses, np.random.default_rng(5))
    return kin, commanded, images


def test_offsets_and_tilt_recovered_within_a_tenth_of_a_degree(views) -> None:
    kin, commanded, images = views
    fit = arm_offsets_from_images(images, commanded, BOARD, INTR, kin)
    got = fit.deg()
    for name, truth in TRUE.items():
        # 0.1° = 0.87 mm of camera travel at 0.5 m; solvePnP centres are good to ~0.3 mm. The
        # roll: the board's orientation in the image, ~0.02° a view, 12 views.
        assert abs(got[name] - truth) <= 0.1, (name, got[name], truth)
    # Measured: every angle here sits 1–2 of its σ low for any noise seed (−0.011° for the
    # roll): the corner detector's bias on these rendered boards, which no σ from scatter sees.
    assert np.allclose(fit.board_shift_m, SHIFT_M, atol=5e-4)
    assert fit.rms_m < 1e-3


def test_nominal_kinematics_do_not_explain_the_images(views) -> None:
    """The check can fail: with zero offsets and no tilt the camera centres seen by solvePnP
    miss the nominal ones by several mm, ~10× the fitted residual."""
    kin, commanded, images = views
    poses = [board_pose(img, BOARD, INTR) for img in images]
    fit = fit_arm_offsets(kin, commanded, poses, BOARD)
    r_bs, t_bs = board_in_sample(BOARD)
    nominal = np.array([r_bs.T @ (kin.camera_position_m(a) - t_bs) for a in commanded])
    seen = np.array([camera_centre_in_board(r, t) for r, t in poses])
    rms_nominal = float(np.sqrt(np.mean(np.sum((seen - nominal) ** 2, axis=1))))
    assert rms_nominal > 10 * fit.rms_m, (rms_nominal, fit.rms_m)
    assert all(s < 0.03 for k, s in fit.sigma_rad.items() if not k.startswith("shift"))

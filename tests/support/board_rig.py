"""The simulated rig set up to see a ChArUco board, as `gonio calibrate-rig` needs it."""

from __future__ import annotations

from acquisition.config import load_rig
from calibration.camera_model import parse_board
from tests.support.paths import REPO

__all__ = ["BOARD", "board_rig"]

BOARD = parse_board("charuco:8x6:0.02:0.015:DICT_5X5_100")


def board_rig():
    """The sim rig with a camera that can see the board: 640 × 480 px of 5 µm behind a 7 mm
    lens (f_x = 1400 px), no intrinsics file (nominal pinhole)."""
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    cam = rig.camera.model_copy(update={"resolution": (640, 480), "focal_length_m": 0.007})
    cal = rig.calibration.model_copy(update={"intrinsics": None})
    return rig.model_copy(update={"camera": cam, "calibration": cal})

"""Geometric calibration of the rig: camera-arm zero offsets and sample-plane tilt from board views.

A calibration board (ChArUco) lies in the sample holder, its centre on the sample centre, its x
axis along the holder's reference direction +x, its printed face up. The camera arm is driven to
several commanded angles (θ_k, φ_k); at each, one image gives the board pose in the camera frame
by solvePnP (`calibration.camera_model.board_pose`), X_c = R_k X_b + t_k, hence the camera
centre in the board frame c_b,k = −R_kᵀ t_k.

Model (rig kinematics, `acquisition.kinematics`): the arm really sits at (θ_k + δθ, φ_k + δφ)
(δ = zero offsets: the encoder zero is not the geometric zero), so the camera centre in the
sample frame is c_s = d · (sin θ cos φ, sin θ sin φ, cos θ) (d = camera arm radius). The board
frame is the sample frame tilted by τ (the holder is not perpendicular to the arms' common axis)
and shifted in-plane by s (the board is not exactly centred):

    X_s = R_τ (B X_b + b₀ + (s_x, s_y, 0)),   R_τ = R_y(τ_y) R_x(τ_x),
    B = diag(1, −1, −1)   (OpenCV board: y along rows, z *into* the board → face up is −z_b),
    b₀ = −B · (board centre in board coordinates).

Least squares over (δθ, δφ, τ_x, τ_y, s_x, s_y) on the camera centres c_b,k (metres; solvePnP's
centres are good to ~0.1-0.3 mm at 0.5 m, i.e. ~0.02-0.03°). A rotation of the board about the
normal is indistinguishable from δφ; it is fixed at zero because the board *defines* +x.

Then the camera's roll on its arm, δρ (the part of its mount the rig file's `camera_roll_deg`
did not state): the camera centres do not see it, the board's orientation in the image does.
With the arm's forward kinematics at the fitted offsets (`Kinematics.camera_rotation`), each
view's measured camera → board rotation R_kᵀ differs from the predicted one by a turn about the
optical axis, ρ_k = δρ + noise; δρ is their mean and its σ their sd / √n (a separate step: the
roll enters no centre, and its noise is the board's in-image orientation, not the centres').
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from acquisition.kinematics import Kinematics

__all__ = [
    "ArmOffsets",
    "tilt_rotation",
    "board_in_sample",
    "camera_centre_in_board",
    "fit_arm_offsets",
    "arm_offsets_from_images",
]

_FLIP = np.diag([1.0, -1.0, -1.0])


def tilt_rotation(tilt_x_rad: float, tilt_y_rad: float) -> np.ndarray:
    """R_τ = R_y(τ_y) R_x(τ_x): the sample plane's normal tipped toward −y by τ_x, +x by τ_y."""
    cx, sx = np.cos(tilt_x_rad), np.sin(tilt_x_rad)
    cy, sy = np.cos(tilt_y_rad), np.sin(tilt_y_rad)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    return ry @ rx


def _board_centre(board) -> np.ndarray:
    """Centre of the squares in board coordinates (ChArUco origin: outer top-left corner)."""
    if board.kind == "charuco":
        return np.array([board.cols * board.square_m / 2.0, board.rows * board.square_m / 2.0, 0])
    # chessboard: origin at the first inner corner
    return np.array(
        [(board.cols - 1) * board.square_m / 2, (board.rows - 1) * board.square_m / 2, 0]
    )


def board_in_sample(
    board, tilt_x_rad: float = 0.0, tilt_y_rad: float = 0.0, shift_m=(0.0, 0.0)
) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with X_s = R X_b + t for a board centred (up to `shift_m`) on a tilted sample."""
    r_t = tilt_rotation(tilt_x_rad, tilt_y_rad)
    b0 = -_FLIP @ _board_centre(board) + np.array([shift_m[0], shift_m[1], 0.0])
    return r_t @ _FLIP, r_t @ b0


def camera_centre_in_board(rvec, tvec) -> np.ndarray:
    """c_b = −Rᵀ t for a board pose X_c = R X_b + t (OpenCV rvec/tvec)."""
    import cv2

    rot, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return -rot.T @ np.asarray(tvec, dtype=np.float64).reshape(3)


@dataclass(frozen=True)
class ArmOffsets:
    camera_theta_rad: float  # add to the commanded camera θ to get the true one
    camera_phi_rad: float
    tilt_x_rad: float
    tilt_y_rad: float
    board_shift_m: tuple[float, float]
    rms_m: float  # RMS camera-centre residual
    sigma_rad: dict[str, float]  # 1-σ from the fit's covariance (residual-scaled)
    n_views: int
    camera_roll_rad: float = 0.0  # add to the rig file's camera_roll_deg (module docstring)

    def deg(self) -> dict[str, float]:
        return {
            "camera_theta": float(np.degrees(self.camera_theta_rad)),
            "camera_phi": float(np.degrees(self.camera_phi_rad)),
            "tilt_x": float(np.degrees(self.tilt_x_rad)),
            "tilt_y": float(np.degrees(self.tilt_y_rad)),
            "camera_roll": float(np.degrees(self.camera_roll_rad)),
        }


_NAMES = ("camera_theta", "camera_phi", "tilt_x", "tilt_y", "shift_x", "shift_y")


def _true_axes(p, a: Mapping[str, float]) -> dict[str, float]:
    true = dict(a)
    true["camera_theta"] = a["camera_theta"] + p[0]
    true["camera_phi"] = a["camera_phi"] + p[1]
    return true


def _predict(p, kin: Kinematics, axes: Sequence[Mapping[str, float]], board) -> np.ndarray:
    r_bs, t_bs = board_in_sample(board, p[2], p[3], (p[4], p[5]))
    return np.asarray([r_bs.T @ (kin.camera_position_m(_true_axes(p, a)) - t_bs) for a in axes])


def _view_rolls(p, kin: Kinematics, axes, board_poses, board) -> np.ndarray:
    """ρ_k: each view's turn about the optical axis from the predicted camera → board rotation
    (the arms at the fitted offsets, no roll beyond the rig file's) to the measured one."""
    import cv2

    r_bs, _ = board_in_sample(board, p[2], p[3], (p[4], p[5]))
    out = []
    for a, (rvec, _tvec) in zip(axes, board_poses, strict=True):
        rot, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
        predicted = r_bs.T @ kin.camera_rotation(_true_axes(p, a))
        d = predicted.T @ rot.T  # camera(predicted) ← camera(measured)
        out.append(np.arctan2(d[1, 0] - d[0, 1], d[0, 0] + d[1, 1]))
    return np.asarray(out)


def fit_arm_offsets(
    kin: Kinematics,
    commanded_axes: Sequence[Mapping[str, float]],
    board_poses: Sequence[tuple[np.ndarray, np.ndarray]],
    board,
) -> ArmOffsets:
    """Fit zero offsets and tilt from board poses (rvec, tvec) seen at commanded axis angles
    (radians, the rig's axis roles). Needs ≥ 3 views at different azimuths."""
    if len(commanded_axes) != len(board_poses) or len(board_poses) < 3:
        raise ValueError("need ≥ 3 views, one board pose per commanded axis set")
    measured = np.asarray([camera_centre_in_board(r, t) for r, t in board_poses])

    def resid(p):
        return (_predict(p, kin, commanded_axes, board) - measured).ravel()

    sol = least_squares(resid, np.zeros(6), x_scale=[1e-3] * 4 + [1e-3] * 2, method="lm")
    r = sol.fun
    dof = max(r.size - sol.x.size, 1)
    s2 = float(r @ r) / dof
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2
        sig = np.sqrt(np.diag(cov))
    except np.linalg.LinAlgError:
        sig = np.full(6, np.inf)
    p = sol.x
    rolls = _view_rolls(p, kin, commanded_axes, board_poses, board)
    roll = float(np.mean(rolls))
    sig = np.append(sig, _roll_sigma(p, cov if np.isfinite(sig).all() else None, rolls,
                                     lambda q: _view_rolls(q, kin, commanded_axes, board_poses,
                                                           board).mean()))  # fmt: skip
    return ArmOffsets(
        float(p[0]),
        float(p[1]),
        float(p[2]),
        float(p[3]),
        (float(p[4]), float(p[5])),
        float(np.sqrt(np.mean(r.reshape(-1, 3) ** 2) * 3)),
        {n: float(s) for n, s in zip((*_NAMES, "camera_roll"), sig, strict=True)},
        len(board_poses),
        roll,
    )


def _roll_sigma(p, cov, rolls: np.ndarray, mean_roll) -> float:
    """σ of the mean roll: the views' scatter / √n, with the offsets' and tilt's own
    uncertainty carried through (the predicted orientation moves with them: g Σ gᵀ, g by
    central differences of 1e-6 rad / 1 µm)."""
    var = float(np.var(rolls, ddof=1)) / len(rolls)
    if cov is None:
        return float("inf")
    h = 1e-6
    g = np.array([(mean_roll(p + h * e) - mean_roll(p - h * e)) / (2 * h) for e in np.eye(len(p))])
    return float(np.sqrt(var + g @ cov @ g))


def arm_offsets_from_images(
    images: Sequence[np.ndarray],
    commanded_axes: Sequence[Mapping[str, float]],
    board,
    intrinsics: Mapping,
    kin: Kinematics,
) -> ArmOffsets:
    """Detect the board in each image (solvePnP with `intrinsics`: fx, fy, cx, cy, dist) and
    fit the offsets."""
    from calibration.camera_model import board_pose

    poses = [board_pose(img, board, intrinsics) for img in images]
    return fit_arm_offsets(kin, commanded_axes, poses, board)

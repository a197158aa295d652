"""`gonio calibrate-rig`: the camera arm's zero offsets and the sample plane's tilt, measured on
the rig itself from views of a calibration board, written as the file the rig file's
`[calibration] arm_offsets` points at (then `gonio calibrate` uses it: true axis angle =
measured + offset, directions in the tilted sample's frame; calibration.geometry.RigGeometry).

Procedure (as a lab does it): the operator puts the board in the holder (centred, x along +x);
the light arm goes overhead and the camera arm through a grid of elevations × azimuths; at each
view the camera takes frames on an exposure ladder until the board's bright squares sit well
inside the range; the board's pose in each view comes from solvePnP with the camera's
intrinsics (calibration.camera_model.board_pose), and the offsets and tilt from the least-squares
fit of the camera centres (calibration.arm_offsets.fit_arm_offsets). The raw frames are kept
beside the output (`<out>.frames/`), the board goes back for the sample, and the rig is left
safe (parked, light and torque off).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.config import ARM_OFFSETS_SCHEMA, RigConfig
from acquisition.description import camera_description
from acquisition.kinematics import Pose
from acquisition.operator import Operator, ask, step
from acquisition.plans import park_targets
from gonio.errors import UserError
from plumbing.atomic import atomic_write_bytes

__all__ = ["RigCalibrationPlan", "calibrate_rig"]


@dataclass(frozen=True)
class RigCalibrationPlan:
    """The board views: camera elevations × azimuths (deg), light overhead."""

    theta_deg: tuple[float, ...] = (15.0, 35.0, 55.0)
    phi_deg: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0)
    exposure_start_s: float = 0.002
    exposure_ratio: float = 2.0
    max_frames: int = 12
    # The brightest board pixels (99th percentile) should land in this band of the clip level:
    # bright enough for sub-pixel corners, below saturation so edges keep their shape.
    target_band: tuple[float, float] = (0.35, 0.85)


@dataclass
class _View:
    axes_rad: dict[str, float]
    exposure_s: float
    frame: Path
    pose: tuple[np.ndarray, np.ndarray] | None = None
    note: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def _gray8(path: Path, black: float, white: float) -> tuple[np.ndarray, float]:
    """A frame as 8-bit grey for the board detector, and its 99th-percentile level (0..1 of
    the clip). A mosaic is binned 2×2 to superpixels' full resolution kept by repeating."""
    from calibration.decode import decode_frame

    d = decode_frame(path)
    dn = np.asarray(d.dn, dtype=np.float64)
    if dn.ndim == 3:
        dn = dn.mean(axis=2)
    level = (dn - black) / (white - black)
    p99 = float(np.percentile(level, 99))
    img = np.clip(level / max(p99, 1e-9), 0, 1) * 255.0
    return np.rint(img).astype(np.uint8), p99


def _capture_view(rig_dev, plan: RigCalibrationPlan, desc: dict, frames_dir: Path, k: int):
    """Frames on an exposure ladder until the board's bright pixels are in the target band;
    every frame is kept. Returns (path, exposure, gray image) of the chosen one."""
    t = plan.exposure_start_s
    lo, hi = plan.target_band
    best = None
    for j in range(plan.max_frames):
        frame = rig_dev.camera.capture(t)
        path = frames_dir / f"view{k:02d}_{j:02d}{frame.suffix}"
        atomic_write_bytes(path, frame.data)
        gray, p99 = _gray8(path, desc["black_level_dn"], desc["white_level_dn"])
        best = (path, t, gray)
        if p99 > hi:
            t /= plan.exposure_ratio * 1.5  # overshoot: back off more than one step
        elif p99 < lo:
            t *= plan.exposure_ratio
        else:
            return best
        t = min(max(t, desc["exposure_range_s"][0]), desc["exposure_range_s"][1])
    return best


def calibrate_rig(
    rig_cfg: RigConfig,
    rig_dev,  # acquisition.rig.Rig, built by the caller
    board,  # calibration.camera_model.BoardSpec
    out: Path,
    operator: Operator,
    plan: RigCalibrationPlan | None = None,
) -> dict[str, Any]:
    """Drive the board views, fit, write `out` (refusing to overwrite); returns its content."""
    from calibration.arm_offsets import fit_arm_offsets
    from calibration.camera_model import CalibrationInputError, board_pose

    plan = plan or RigCalibrationPlan()
    if rig_cfg.geometry.preset != "two-arm":
        raise UserError("calibrate-rig needs the two-arm preset (camera elevation and azimuth)")
    out = Path(out)
    if out.exists():
        raise UserError(f"{out}: exists; choose a new --out file (earlier calibrations are kept)")
    frames_dir = out.with_name(out.name + ".frames")
    if frames_dir.exists():
        raise UserError(f"{frames_dir}: exists; choose a new --out file")
    desc = camera_description(rig_cfg)
    intr = {k: desc[k] for k in ("fx", "fy", "cx", "cy", "dist")}
    kin = rig_dev.kinematics
    targets = []
    for th in plan.theta_deg:
        for ph in plan.phi_deg:
            targets.append(kin.targets(Pose.from_deg(0.0, 0.0, th, ph)))  # Unreachable: 1 line
    fields = {k: getattr(board, k) for k in ("kind", "cols", "rows", "square_m")}
    fields.update(marker_m=board.marker_m, dictionary=board.dictionary)
    ask(operator, step("mount_board", board=str(board), board_fields=fields))
    frames_dir.mkdir(parents=True)
    views: list[_View] = []
    try:
        rig_dev.torque(True)
        rig_dev.light.set_intensity(rig_cfg.light.level)
        if rig_cfg.light.manual:
            ask(operator, step("lamp_on", warmup_s=rig_cfg.light.warmup_s))
        rig_dev.light.on()
        for k, tgt in enumerate(targets):
            rig_dev.move(tgt)
            rig_dev.wait(rig_cfg.move_timeout_s)
            rig_dev.clock.sleep(rig_cfg.settle_s)
            measured = rig_dev.positions()
            path, t, gray = _capture_view(rig_dev, plan, desc, frames_dir, k)
            view = _View(measured, t, path)
            try:
                view.pose = board_pose(gray, board, intr)
            except CalibrationInputError as exc:
                view.note = str(exc)
            views.append(view)
        rig_dev.move(park_targets(rig_cfg))
        rig_dev.wait(rig_cfg.move_timeout_s)
    finally:
        for action in (rig_dev.light.off, lambda: rig_dev.torque(False)):
            try:
                action()
            except Exception:  # best effort: the next steps still run
                pass
    ask(operator, step("mount_sample", mark=rig_cfg.sample.orientation_mark))
    good = [v for v in views if v.pose is not None]
    if len(good) < 3:
        raise UserError(
            f"the board was found in {len(good)} of {len(views)} views (need ≥ 3); check "
            f"--board, lighting and focus (frames kept in {frames_dir})"
        )
    fit = fit_arm_offsets(kin, [v.axes_rad for v in good], [v.pose for v in good], board)
    doc = _document(fit, rig_cfg, board, views, frames_dir)
    atomic_write_bytes(out, (json.dumps(doc, indent=2) + "\n").encode())
    return doc


def _document(fit, rig_cfg: RigConfig, board, views: list[_View], frames_dir: Path) -> dict:
    deg = fit.deg()
    sig = {k: math.degrees(v) for k, v in fit.sigma_rad.items() if not k.startswith("shift")}
    return {
        "schema": ARM_OFFSETS_SCHEMA,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "rig": rig_cfg.name,
        "board": str(board),
        "offsets_deg": {"camera_theta": deg["camera_theta"], "camera_phi": deg["camera_phi"]},
        "tilt_deg": {"x": deg["tilt_x"], "y": deg["tilt_y"]},
        "camera_roll_deg": deg["camera_roll"],
        "sigma_deg": sig,
        "board_shift_m": list(fit.board_shift_m),
        "rms_m": fit.rms_m,
        "n_views": fit.n_views,
        "views": [
            {
                "axes_deg": {k: math.degrees(v) for k, v in v.axes_rad.items()},
                "exposure_s": v.exposure_s,
                "frame": str(v.frame.relative_to(frames_dir.parent)),
                "used": v.pose is not None,
                "note": v.note,
            }
            for v in views
        ],
    }

"""What a run records about the instrument: the camera, the sample and the geometric
calibration, resolved from the rig file (docs/design.md §1: calibration uses only this and what the
run recorded).

`camera_description` is the `[camera]` table of run.toml: the lab's description of its camera
with the pinhole intrinsics resolved — from the `[calibration] intrinsics` file when there is
one (what `gonio calibrate-camera --json` measured), else nominal from the datasheet,
f_x = f_y = focal length / pixel pitch with the principal point at the image centre
((W − 1)/2, (H − 1)/2 in OpenCV's pixel-centre convention).
"""

from __future__ import annotations

from typing import Any

from acquisition.config import RigConfig, load_arm_offsets, load_intrinsics

__all__ = ["camera_description", "sample_description", "arm_offsets_description"]


def camera_description(rig: RigConfig) -> dict[str, Any]:
    """The camera as calibration needs it (keys of calibration.geometry.Intrinsics and
    calibration.radiometry.CameraRadiometry), plus what the lab stated for the record."""
    cam = rig.camera
    w, h = cam.resolution
    if rig.calibration.intrinsics is not None:
        intr = load_intrinsics(rig.calibration.intrinsics, cam.resolution)
        source = f"file {rig.calibration.intrinsics}"
    else:
        fx = float(cam.nominal_fx_px)
        intr = {"fx": fx, "fy": fx, "cx": (w - 1) / 2.0, "cy": (h - 1) / 2.0, "dist": [0.0] * 5}
        source = "nominal: focal_length_m / pixel_pitch_m, principal point at the centre"
    d: dict[str, Any] = {
        "backend": cam.backend,
        "model": cam.model,
        "resolution": [int(w), int(h)],
        **intr,
        "intrinsics_source": source,
        "f_number": cam.f_number,
        "pixel_pitch_m": cam.pixel_pitch_m,
        "wavelength_m": cam.wavelength_m,
        "gain_e_per_dn": cam.gain_e_per_dn,
        "black_level_dn": cam.black_level_dn,
        "white_level_dn": cam.white_level_dn,
        "read_noise_e": cam.read_noise_e,
        "color_filter": cam.color_filter,
        "bit_depth": cam.bit_depth,
        "exposure_range_s": [cam.exposure_min_s, cam.exposure_max_s],
    }
    if cam.focal_length_m is not None:
        d["focal_length_m"] = cam.focal_length_m
    if cam.quantum_efficiency is not None:
        d["quantum_efficiency"] = cam.quantum_efficiency
    return d


def sample_description(rig: RigConfig) -> dict[str, Any]:
    return rig.sample.model_dump(mode="json")


def arm_offsets_description(rig: RigConfig) -> dict[str, Any] | None:
    """The `[calibration] arm_offsets` file's content (validated), or None."""
    if rig.calibration.arm_offsets is None:
        return None
    return load_arm_offsets(rig.calibration.arm_offsets)

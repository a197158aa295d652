"""Per-pixel geometry: where each pixel looks on the sample, and its own ω_i, ω_o.

The light and camera are at finite distance, so the directions differ across the image; using
one (θ, φ) per image would blur the BRDF. Each pixel ray (pinhole model, OpenCV convention:
pixel (u, v) centre at integer coordinates, ray ∝ ((u − c_x)/f_x, (v − c_y)/f_y, 1)) is cut
with the sample plane z = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acquisition.kinematics import look_at_rotation

__all__ = ["Intrinsics", "PixelGeometry", "pixel_geometry", "project_points"]


@dataclass(frozen=True)
class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_description(cls, d: dict) -> Intrinsics:
        """From a camera description (run.toml [camera]): explicit fx/fy/cx/cy, or a
        horizontal field of view with the principal point at the image centre."""
        w, h = (int(x) for x in d["resolution"])
        if "fx" in d:
            return cls(w, h, float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]))
        fx = (w / 2.0) / np.tan(np.radians(float(d["fov_deg"])) / 2.0)
        return cls(w, h, fx, fx, (w - 1) / 2.0, (h - 1) / 2.0)


@dataclass
class PixelGeometry:
    """Arrays of shape (H, W) / (H, W, 3), for pixel centres at (u·step + offset)."""

    point_m: np.ndarray  # surface point hit by the ray (z = 0)
    wi: np.ndarray  # unit, toward the light
    wo: np.ndarray  # unit, toward the camera
    light_distance_m: np.ndarray
    on_sample: np.ndarray  # bool: the ray hits the sample (inside its edge margin)


def pixel_geometry(
    intr: Intrinsics,
    camera_pos_m: np.ndarray,
    light_pos_m: np.ndarray,
    sample_size_m: float,
    *,
    step: int = 1,
    offset: float = 0.0,
    margin_m: float = 0.0,
) -> PixelGeometry:
    """Geometry for pixel centres u = offset + step·k (k = 0..W/step−1), same for v.

    With a 2×2 Bayer superpixel, step = 2 and offset = 0.5 put the ray through the centre of
    the four photosites.
    """
    cam = np.asarray(camera_pos_m, dtype=np.float64)
    light = np.asarray(light_pos_m, dtype=np.float64)
    us = offset + step * np.arange(intr.width // step)
    vs = offset + step * np.arange(intr.height // step)
    uu, vv = np.meshgrid(us, vs)
    d_cam = np.stack(
        [(uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy, np.ones_like(uu)], axis=-1
    )
    rot = look_at_rotation(cam)
    d = d_cam @ rot.T
    dz = d[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dz < 0, -cam[2] / dz, np.nan)
    p = cam + t[..., None] * d
    p[..., 2] = 0.0
    half = sample_size_m / 2.0 - margin_m
    on = np.isfinite(t) & (np.abs(p[..., 0]) < half) & (np.abs(p[..., 1]) < half)
    to_light = light - p
    r = np.linalg.norm(to_light, axis=-1)
    wi = to_light / r[..., None]
    to_cam = cam - p
    wo = to_cam / np.linalg.norm(to_cam, axis=-1, keepdims=True)
    on &= (wi[..., 2] > 0) & (wo[..., 2] > 0)
    return PixelGeometry(p, wi, wo, r, on)


def project_points(intr: Intrinsics, camera_pos_m: np.ndarray, points_m: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) = (u, v) of world points (N, 3) seen by the camera at
    ``camera_pos_m`` looking at the origin (pinhole, OpenCV convention as in `pixel_geometry`):
    x_cam = Rᵀ(X − C), u = f_x x/z + c_x, v = f_y y/z + c_y."""
    cam = np.asarray(camera_pos_m, dtype=np.float64)
    rot = look_at_rotation(cam)
    pc = (np.atleast_2d(np.asarray(points_m, dtype=np.float64)) - cam) @ rot
    return np.stack(
        [intr.fx * pc[:, 0] / pc[:, 2] + intr.cx, intr.fy * pc[:, 1] / pc[:, 2] + intr.cy], axis=-1
    )

"""Per-pixel geometry: where each pixel looks on the sample, and its own ω_i, ω_o.

The light and camera are at finite distance, so the directions differ across the image; using
one (θ, φ) per image would blur the BRDF. Each pixel ray (OpenCV camera model: pixel (u, v)
centre at integer coordinates; the pinhole ray ∝ (x, y, 1) with (x, y) the *undistorted*
normalised coordinates of (u, v) — ((u − c_x)/f_x, (v − c_y)/f_y) when the Brown–Conrady
coefficients are zero, else cv2.undistortPoints) is cut with the sample plane z = 0.

`RigGeometry` puts the light and camera in the *sample's* frame from the measured axis angles,
the rig's kinematics and its geometric calibration (`gonio calibrate-rig`: arm zero offsets δ,
true angle = measured + δ; the sample plane's tilt R_τ = R_y(τ_y) R_x(τ_x), a point of the
sample frame sits at R_τ·p in the rig frame — calibration.arm_offsets; the camera's roll on its
arm). The camera's orientation is its arm's forward kinematics (`Kinematics.camera_rotation`,
roll included), in the sample frame R_τᵀ·R_arm: the image turns with the arm, at θ_o = 0 too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from acquisition.kinematics import Kinematics
from plumbing.numba_policy import dispatch

__all__ = [
    "Intrinsics",
    "RigGeometry",
    "PixelGeometry",
    "PixelGrid",
    "pixel_geometry",
    "project_points",
]


@dataclass(frozen=True)
class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @classmethod
    def from_description(cls, d: dict) -> Intrinsics:
        """From a camera description (run.toml [camera], acquisition.description): explicit
        fx/fy/cx/cy (and OpenCV dist k1, k2, p1, p2, k3), or — runs written before schema 2 —
        a horizontal field of view with the principal point at the image centre."""
        w, h = (int(x) for x in d["resolution"])
        if "fx" in d:
            dist = tuple((list(map(float, d.get("dist") or [])) + [0.0] * 5)[:5])
            return cls(w, h, float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]), dist)
        fx = (w / 2.0) / np.tan(np.radians(float(d["fov_deg"])) / 2.0)
        return cls(w, h, fx, fx, (w - 1) / 2.0, (h - 1) / 2.0)

    @property
    def distorted(self) -> bool:
        return any(self.dist)

    def normalised(self, uu: np.ndarray, vv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates (x, y) of pixel positions (u, v)."""
        if not self.distorted:
            return (uu - self.cx) / self.fx, (vv - self.cy) / self.fy
        import cv2

        pts = np.stack([uu.ravel(), vv.ravel()], axis=-1).astype(np.float64).reshape(-1, 1, 2)
        k = np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])
        # Iterative inversion of Brown–Conrady (20 iterations; checked against projectPoints).
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)
        und = cv2.undistortPoints(pts, k, np.asarray(self.dist), None, None, None, crit)
        und = und.reshape(-1, 2)
        return und[:, 0].reshape(uu.shape), und[:, 1].reshape(uu.shape)


@dataclass(frozen=True)
class RigGeometry:
    """Light and camera in the sample's frame from measured axis angles (see module doc)."""

    kinematics: Kinematics
    offsets_rad: dict[str, float]
    tilt: np.ndarray  # R_τ (3×3)
    roll_rad: float = 0.0  # the camera's roll beyond the rig file's (calibrate-rig)

    @classmethod
    def of_run(cls, kinematics: Kinematics, arm_offsets: dict | None) -> RigGeometry:
        """From the run's frozen arm-offsets record (run.toml [arm_offsets]) or none."""
        if not arm_offsets:
            return cls(kinematics, {}, np.eye(3))
        from calibration.arm_offsets import tilt_rotation

        offs = {k: float(np.radians(v)) for k, v in arm_offsets["offsets_deg"].items()}
        t = arm_offsets["tilt_deg"]
        return cls(
            kinematics,
            offs,
            tilt_rotation(np.radians(t["x"]), np.radians(t["y"])),
            float(np.radians(arm_offsets.get("camera_roll_deg", 0.0))),
        )

    def true_axes(self, measured: dict[str, float]) -> dict[str, float]:
        return {k: float(v) + self.offsets_rad.get(k, 0.0) for k, v in measured.items()}

    def positions(self, measured: dict[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(camera position, light position, camera→sample rotation), sample frame."""
        axes = self.true_axes(measured)
        cam = self.kinematics.camera_position_m(axes)
        light = self.kinematics.light_position_m(axes)
        rot = self.tilt.T @ self.kinematics.camera_rotation(axes, self.roll_rad)
        return self.tilt.T @ cam, self.tilt.T @ light, rot


@dataclass
class PixelGeometry:
    """Arrays of shape (H, W) / (H, W, 3), for pixel centres at (u·step + offset)."""

    point_m: np.ndarray  # surface point hit by the ray (z = 0)
    wi: np.ndarray  # unit, toward the light
    wo: np.ndarray  # unit, toward the camera
    light_distance_m: np.ndarray
    on_sample: np.ndarray  # bool: the ray hits the sample (inside its edge margin)


@dataclass(frozen=True)
class PixelGrid:
    """Which pixel centres a geometry is computed for: u = x0 + offset + step·k within the
    `window` (x0, y0, x1, y1) of the frame (x0, y0 multiples of `step`; None: the whole frame),
    the same for v. A 2×2 Bayer superpixel has step 2 and offset 0.5: the ray goes through
    the centre of its four photosites. A window gives the whole frame's values at its pixels."""

    step: int = 1
    offset: float = 0.0
    window: tuple[int, int, int, int] | None = None


def pixel_geometry(
    intr: Intrinsics,
    camera_pos_m: np.ndarray,
    light_pos_m: np.ndarray,
    sample_size_m: float,
    *,
    grid: PixelGrid = PixelGrid(),
    margin_m: float = 0.0,
    rotation: np.ndarray,
    mask_only: bool = False,
) -> PixelGeometry:
    """Geometry for the pixel centres of `grid` (default: every pixel of the frame).

    `rotation`: camera → sample frame (columns: camera axes), from the arm's kinematics
    (`RigGeometry.positions`). `mask_only`: only
    `on_sample` is filled (the other arrays are 1 × 1 placeholders).
    """
    cam = np.asarray(camera_pos_m, dtype=np.float64)
    light = np.asarray(light_pos_m, dtype=np.float64)
    step, offset = grid.step, grid.offset
    x0, y0, x1, y1 = (0, 0, intr.width, intr.height) if grid.window is None else grid.window
    us = x0 + offset + step * np.arange((x1 - x0) // step)
    vs = y0 + offset + step * np.arange((y1 - y0) // step)
    if intr.distorted:
        uu, vv = np.meshgrid(us, vs)
        x, y = intr.normalised(uu, vv)
    else:  # one value per column and per row, broadcast (no (H, W) arrays to build)
        xs, ys = intr.normalised(us, vs)
        x = np.broadcast_to(xs[None, :], (vs.size, us.size))
        y = np.broadcast_to(ys[:, None], (vs.size, us.size))
    rot = np.asarray(rotation, dtype=np.float64)
    h, w = x.shape
    shape3 = (h, w, 3) if not mask_only else (1, 1, 3)
    geo = PixelGeometry(
        np.empty(shape3), np.empty(shape3), np.empty(shape3),
        np.empty((h, w) if not mask_only else (1, 1)), np.empty((h, w), bool),
    )  # fmt: skip
    half = sample_size_m / 2.0 - margin_m
    arrays = (geo.point_m, geo.wi, geo.wo, geo.light_distance_m, geo.on_sample)
    rays = (x, y, rot, cam, light, half, mask_only)
    # Threads for large frames when they pay (the fitting kernels' policy: plumbing.numba_policy).
    dispatch("pixel_geometry", _rays_par, _rays_ser, h * w, rays, arrays)
    return geo


@numba.njit(cache=True, nogil=True)
def _ray_row(r, rays, out):
    """Row r of the pixels: the ray d = R·(x, y, 1) from the camera cut with z = 0 at
    p = C + t·d (t = −C_z/d_z, none when d_z ≥ 0), ω_i = (L − p)/|L − p|, ω_o = (C − p)/|C − p|,
    and on the sample when |p_x|, |p_y| < `half` and both directions are above the surface.
    `rays` = (x, y, R, C, L, half, mask_only); `out` = (point, ω_i, ω_o, distance to the light,
    on-sample mask), only the mask written with `mask_only`."""
    x, y, rot, cam, light, half, mask_only = rays
    point, wi, wo, dist, on = out
    w = x.shape[1]
    for c in range(w):
        xn, yn = x[r, c], y[r, c]
        d0 = xn * rot[0, 0] + yn * rot[0, 1] + rot[0, 2]
        d1 = xn * rot[1, 0] + yn * rot[1, 1] + rot[1, 2]
        d2 = xn * rot[2, 0] + yn * rot[2, 1] + rot[2, 2]
        t = -cam[2] / d2 if d2 < 0 else np.nan
        p0 = cam[0] + t * d0
        p1 = cam[1] + t * d1
        l0, l1, l2 = light[0] - p0, light[1] - p1, light[2]
        if mask_only:
            # ω_i,z > 0 and ω_o,z > 0 are L_z > 0 and C_z > 0 where p is finite (|L − p| and
            # |C − p| are then finite and > 0, for lamp and camera at finite positions): the
            # same mask without two roots and divisions
            on[r, c] = (
                np.isfinite(t) and abs(p0) < half and abs(p1) < half and l2 > 0 and cam[2] > 0
            )
            continue
        rl = np.sqrt(l0 * l0 + l1 * l1 + l2 * l2)
        v0, v1, v2 = cam[0] - p0, cam[1] - p1, cam[2]
        rv = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        wiz, woz = l2 / rl, v2 / rv
        on[r, c] = np.isfinite(t) and abs(p0) < half and abs(p1) < half and wiz > 0 and woz > 0
        point[r, c, 0], point[r, c, 1], point[r, c, 2] = p0, p1, 0.0
        wi[r, c, 0], wi[r, c, 1], wi[r, c, 2] = l0 / rl, l1 / rl, wiz
        wo[r, c, 0], wo[r, c, 1], wo[r, c, 2] = v0 / rv, v1 / rv, woz
        dist[r, c] = rl


@numba.njit(cache=True, parallel=True, nogil=True)
def _rays_par(rays, out):
    """`_ray_row` for every row, rows in parallel (each pixel's arithmetic is its own)."""
    for r in numba.prange(rays[0].shape[0]):
        _ray_row(np.int64(r), rays, out)  # int64 as the serial twin's: one compiled helper


@numba.njit(cache=True, nogil=True)
def _rays_ser(rays, out):
    for r in range(rays[0].shape[0]):
        _ray_row(r, rays, out)


def project_points(
    intr: Intrinsics,
    camera_pos_m: np.ndarray,
    points_m: np.ndarray,
    rotation: np.ndarray,
) -> np.ndarray:
    """Pixel coordinates (N, 2) = (u, v) of world points (N, 3) seen by the camera at
    ``camera_pos_m`` turned by ``rotation`` (OpenCV convention as in `pixel_geometry`):
    x_cam = Rᵀ(X − C), then u = f_x x'/z + c_x, v = f_y y'/z + c_y with (x', y') distorted by
    Brown–Conrady when the intrinsics have distortion (cv2.projectPoints)."""
    cam = np.asarray(camera_pos_m, dtype=np.float64)
    rot = np.asarray(rotation, dtype=np.float64)
    pc = (np.atleast_2d(np.asarray(points_m, dtype=np.float64)) - cam) @ rot
    if intr.distorted:
        import cv2

        k = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])
        uv, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), k, np.asarray(intr.dist))
        return uv.reshape(-1, 2)
    return np.stack(
        [intr.fx * pc[:, 0] / pc[:, 2] + intr.cx, intr.fy * pc[:, 1] / pc[:, 2] + intr.cy], axis=-1
    )

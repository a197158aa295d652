"""Per-pixel geometry (calibration.geometry.pixel_geometry, a compiled ray cast) against the
inverse mapping, the camera projection (`project_points`: world → pixel, an independent formula,
cv2.projectPoints with distortion): every on-sample pixel's surface point projects back onto that
pixel, its ω_i and ω_o point at the light and the camera, and a window of the frame gives the
whole frame's values there.

Tolerances: the ray cast and the projection are each a few float64 operations on coordinates of
~0.5 m (≤ 1e-15 relative); back at the pixel that is ≤ 1e-9 px for focal lengths ≤ 10⁵ px (the
undistorted case, asserted at 1e-6 px). With distortion, cv2.undistortPoints inverts Brown–Conrady
by 20 fixed-point iterations to an ε of 1e-9 in normalised coordinates, ≈ 1e-5 px at f ≈ 10⁴ px:
asserted at 1e-3 px.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.geometry import Intrinsics, PixelGrid, pixel_geometry, project_points
from simulator.render import world_to_camera_cv

SIZE_M = 0.05
CAM_M = np.array([0.21, -0.12, 0.43])  # θ_o ≈ 31°: an oblique view, a trapezoidal footprint
LIGHT_M = np.array([-0.3, 0.05, 0.35])


def _camera_rotation() -> np.ndarray:
    """Camera → sample rotation of a camera at CAM_M looking at the centre (the simulator's
    pinhole: any orientation serves, these tests are about the rays through it)."""
    return world_to_camera_cv(CAM_M)[0].T


def _intrinsics(distorted: bool) -> Intrinsics:
    dist = (-0.12, 0.05, 1e-3, -5e-4, 0.0) if distorted else (0.0,) * 5
    return Intrinsics(640, 480, 1450.0, 1452.0, 321.3, 238.9, dist)


@pytest.mark.parametrize("distorted", [False, True])
@pytest.mark.parametrize("step, offset", [(1, 0.0), (2, 0.5)])
def test_on_sample_pixels_project_back_onto_themselves(distorted, step, offset) -> None:
    intr = _intrinsics(distorted)
    rot = _camera_rotation()
    grid = PixelGrid(step, offset)
    geo = pixel_geometry(intr, CAM_M, LIGHT_M, SIZE_M, grid=grid, rotation=rot)
    on = geo.on_sample
    assert 1000 < on.sum() < on.size  # the footprint is in view and does not fill the frame
    vs, us = np.nonzero(on)
    uv = project_points(intr, CAM_M, geo.point_m[on], rot)
    tol_px = 1e-3 if distorted else 1e-6
    np.testing.assert_allclose(uv[:, 0], offset + step * us, atol=tol_px, rtol=0)
    np.testing.assert_allclose(uv[:, 1], offset + step * vs, atol=tol_px, rtol=0)
    p = geo.point_m[on]
    assert np.all(p[:, 2] == 0) and np.all(np.abs(p[:, :2]) < SIZE_M / 2)
    to_light = LIGHT_M - p
    r = np.linalg.norm(to_light, axis=1)
    np.testing.assert_allclose(geo.light_distance_m[on], r, rtol=1e-14)
    np.testing.assert_allclose(geo.wi[on], to_light / r[:, None], rtol=0, atol=1e-14)
    to_cam = CAM_M - p
    want_wo = to_cam / np.linalg.norm(to_cam, axis=1)[:, None]
    np.testing.assert_allclose(geo.wo[on], want_wo, rtol=0, atol=1e-14)


@pytest.mark.parametrize("distorted", [False, True])
def test_pixels_off_the_sample_are_off(distorted) -> None:
    """A pixel is on the sample exactly when the pixel's ray lands inside the square: the
    neighbours of the footprint's edge pixels, one pixel out, land outside it (or miss)."""
    intr = _intrinsics(distorted)
    rot = _camera_rotation()
    geo = pixel_geometry(intr, CAM_M, LIGHT_M, SIZE_M, rotation=rot)
    on = geo.on_sample
    ring = np.zeros_like(on)
    ring[1:, :] |= on[:-1, :]
    ring[:-1, :] |= on[1:, :]
    ring[:, 1:] |= on[:, :-1]
    ring[:, :-1] |= on[:, 1:]
    ring &= ~on
    assert ring.sum() > 100
    full = pixel_geometry(intr, CAM_M, LIGHT_M, 10 * SIZE_M, rotation=rot)  # same rays
    assert np.all(np.abs(full.point_m[ring][:, :2]).max(axis=1) >= SIZE_M / 2)


def test_a_window_gives_the_whole_frames_values() -> None:
    intr = _intrinsics(False)
    rot = _camera_rotation()
    whole = pixel_geometry(intr, CAM_M, LIGHT_M, SIZE_M, grid=PixelGrid(2, 0.5), rotation=rot)
    x0, y0, x1, y1 = 96, 64, 400, 352
    grid = PixelGrid(2, 0.5, (x0, y0, x1, y1))
    part = pixel_geometry(intr, CAM_M, LIGHT_M, SIZE_M, grid=grid, rotation=rot)
    sl = (slice(y0 // 2, y1 // 2), slice(x0 // 2, x1 // 2))
    for name in ("point_m", "wi", "wo", "light_distance_m", "on_sample"):
        np.testing.assert_array_equal(getattr(part, name), getattr(whole, name)[sl])
    mask = pixel_geometry(
        intr, CAM_M, LIGHT_M, SIZE_M, grid=PixelGrid(2, 0.5), rotation=rot, mask_only=True
    )
    np.testing.assert_array_equal(mask.on_sample, whole.on_sample)


@pytest.mark.parametrize("light_z_m", [0.35, 0.0, -0.05])
def test_the_mask_alone_is_the_whole_geometrys_mask(light_z_m) -> None:
    """`mask_only` decides "above the surface" from the light's and camera's heights instead
    of the normalised directions: the same pixels, whether the lamp is above, level with or
    below the sample's plane (then no pixel is lit)."""
    intr = _intrinsics(True)
    rot = _camera_rotation()
    light = np.array([LIGHT_M[0], LIGHT_M[1], light_z_m])
    whole = pixel_geometry(intr, CAM_M, light, SIZE_M, rotation=rot)
    mask = pixel_geometry(intr, CAM_M, light, SIZE_M, rotation=rot, mask_only=True)
    assert whole.on_sample.any() == (light_z_m > 0)
    np.testing.assert_array_equal(mask.on_sample, whole.on_sample)

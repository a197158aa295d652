"""Synthetic images of a calibration board (ChArUco or chessboard) seen by a distorting camera.

Each output pixel is traced backwards through the exact camera model: the pixel (u, v) is
un-distorted to normalised coordinates (x, y) by inverting the Brown–Conrady model (OpenCV
convention, Zhang 2000; see `distort_normalised`), the ray (x, y, 1) is carried into the board
frame and cut with the board plane z_b = 0, and the board texture is sampled there. Pixels are
supersampled (SS×SS per output pixel, box-averaged) so edges carry the right area coverage,
then mildly blurred and given read noise. The ground truth of every image is the intrinsics,
distortion and pose it was rendered with — nothing here calls OpenCV's projection or
calibration code.

Board frames (match OpenCV's detectors): ChArUco — origin at the outer top-left corner of the
squares, x along columns, y along rows, z into the board. Chessboard — origin at the first
inner corner, same axes. Poses are OpenCV's (rvec, tvec): X_c = R(rvec) X_b + tvec.

The board argument is any object with `kind` ("charuco" | "chessboard"), `cols`, `rows`,
`square_m`, and for ChArUco `marker_m` and `dictionary` (OpenCV name) — e.g.
`calibration.camera_model.BoardSpec` (not imported: simulator and calibration are independent).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

__all__ = [
    "board_texture",
    "distort_normalised",
    "render_board_views",
    "rotation_from_rvec",
    "undistort_normalised",
]

# Board texture resolution and supersampling: a 3×3 supersample of the output keeps the
# box-filtered edge position exact to ≈ 1/(2·3²) of a pixel's area; 160 texels per square keeps
# the texture finer than the supersampled pixels for squares up to ~50 output px.
TEXELS_PER_SQUARE = 160
SUPERSAMPLE = 3
BLACK_DN, WHITE_DN, BACKGROUND_DN = 30.0, 220.0, 110.0


def rotation_from_rvec(rvec: Sequence[float]) -> np.ndarray:
    """Rodrigues' formula R = I + sin θ K + (1 − cos θ) K², θ = |rvec|, K = [k]× for k = rvec/θ."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * kx + (1.0 - np.cos(theta)) * (kx @ kx)


def _dist5(dist: Sequence[float]) -> tuple[float, float, float, float, float]:
    d = [float(v) for v in dist] + [0.0] * 5
    return d[0], d[1], d[2], d[3], d[4]


def distort_normalised(
    x: np.ndarray, y: np.ndarray, dist: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """Brown–Conrady distortion of normalised coordinates (OpenCV docs, calib3d):
    x_d = x(1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²),
    y_d = y(1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2y²) + 2 p2 x y, r² = x² + y²."""
    k1, k2, p1, p2, k3 = _dist5(dist)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def undistort_normalised(
    xd: np.ndarray, yd: np.ndarray, dist: Sequence[float], *, tol: float = 1e-12
) -> tuple[np.ndarray, np.ndarray]:
    """Invert `distort_normalised` by Newton's method (2×2 Jacobian per point).

    Raises RuntimeError if the forward model does not reproduce (xd, yd) to `tol` — the
    distortion is then not invertible over the image (too strong for the field of view).
    """
    k1, k2, p1, p2, k3 = _dist5(dist)
    x = np.array(xd, dtype=np.float64)
    y = np.array(yd, dtype=np.float64)
    for _ in range(50):
        fx_, fy_ = distort_normalised(x, y, dist)
        ex, ey = fx_ - xd, fy_ - yd
        if max(np.abs(ex).max(initial=0.0), np.abs(ey).max(initial=0.0)) < tol:
            break
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r²
        j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        j21 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        det = j11 * j22 - j12 * j21
        x = x - (j22 * ex - j12 * ey) / det
        y = y - (-j21 * ex + j11 * ey) / det
    else:
        raise RuntimeError("distortion could not be inverted over the image")
    return x, y


def board_texture(board: Any) -> tuple[np.ndarray, float, float]:
    """The board as a float32 image with a one-square white quiet zone around the pattern.

    Returns (texture, texels_per_m, origin_texel): board point (X, Y) in metres sits at texel
    coordinates (origin_texel + X·texels_per_m, origin_texel + Y·texels_per_m), texel centres
    at integers.
    """
    n = TEXELS_PER_SQUARE
    per_m = n / float(board.square_m)
    if board.kind == "charuco":
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
        cv_board = cv2.aruco.CharucoBoard(
            (board.cols, board.rows), board.square_m, board.marker_m, dictionary
        )
        pattern = cv_board.generateImage((board.cols * n, board.rows * n), marginSize=0)
        pattern_origin_m = 0.0  # board origin = outer corner of the squares
    elif board.kind == "chessboard":
        # (cols+1)×(rows+1) squares give cols×rows inner corners; top-left square black.
        i, j = np.meshgrid(np.arange(board.cols + 1), np.arange(board.rows + 1))
        cells = np.where((i + j) % 2 == 0, 0, 255).astype(np.uint8)
        pattern = np.kron(cells, np.ones((n, n), np.uint8))
        pattern_origin_m = -float(board.square_m)  # first inner corner is one square in
    else:
        raise ValueError(f"unknown board kind {board.kind!r}")
    pattern = pattern.astype(np.float32) / 255.0
    texture = cv2.copyMakeBorder(pattern, n, n, n, n, cv2.BORDER_CONSTANT, value=1.0)
    texture = (BLACK_DN + (WHITE_DN - BLACK_DN) * texture).astype(np.float32)
    # A texel k covers [k − ½, k + ½]; the pattern's outer edge is the texel boundary at n − ½.
    origin_texel = n - 0.5 - pattern_origin_m * per_m
    return texture, per_m, origin_texel


def render_board_views(
    board: Any,
    intrinsics: Sequence[float],
    dist: Sequence[float],
    poses: Sequence[tuple[Sequence[float], Sequence[float]]],
    rng: np.random.Generator,
    *,
    blur_sigma_px: float = 0.5,
    noise_dn: float = 1.5,
) -> list[np.ndarray]:
    """8-bit grayscale images of `board` from each pose (rvec, tvec), board → camera.

    intrinsics = (fx, fy, cx, cy, width, height) in pixels; dist = (k1, k2, p1, p2, k3), any
    trailing terms may be omitted. Each image: exact back-projection of a 3×3 supersample
    (see module docstring), box-averaged, Gaussian blur `blur_sigma_px` (lens), additive
    Gaussian read noise `noise_dn` (DN), rounded and clipped to 0…255.
    """
    fx, fy, cx, cy, w, h = (float(v) for v in intrinsics)
    w, h = int(w), int(h)
    ss = SUPERSAMPLE
    # Sub-pixel sample positions: supersample pixel k maps to output coordinate (k + ½)/ss − ½,
    # so the ss×ss samples of output pixel u sit symmetrically around u.
    us = (np.arange(w * ss) + 0.5) / ss - 0.5
    vs = (np.arange(h * ss) + 0.5) / ss - 0.5
    uu, vv = np.meshgrid(us, vs)
    x, y = undistort_normalised((uu - cx) / fx, (vv - cy) / fy, dist)
    rays = np.stack([x, y, np.ones_like(x)], axis=-1)  # camera frame, pose-independent
    del uu, vv, x, y

    texture, per_m, origin = board_texture(board)
    images = []
    for rvec, tvec in poses:
        rot = rotation_from_rvec(rvec)
        t = np.asarray(tvec, dtype=np.float64).reshape(3)
        centre_b = -rot.T @ t  # camera centre in the board frame
        d_b = rays @ rot  # = (Rᵀ d)ᵀ for each ray
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -centre_b[2] / d_b[..., 2]
        hit = np.isfinite(s) & (s > 0)  # plane in front of the camera
        px = np.where(hit, centre_b[0] + s * d_b[..., 0], np.nan)
        py = np.where(hit, centre_b[1] + s * d_b[..., 1], np.nan)
        map_x = np.nan_to_num(origin + px * per_m, nan=-1e6).astype(np.float32)
        map_y = np.nan_to_num(origin + py * per_m, nan=-1e6).astype(np.float32)
        hi = cv2.remap(
            texture,
            map_x,
            map_y,
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=BACKGROUND_DN,
        )
        img = cv2.resize(hi, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64)
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
        if noise_dn > 0:
            img = img + rng.normal(0.0, noise_dn, img.shape)
        images.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return images

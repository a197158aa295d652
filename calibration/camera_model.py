"""Camera intrinsics and lens distortion from images of a ChArUco board or a plain chessboard.

Model (OpenCV pinhole + Brown–Conrady, Zhang 2000 "A flexible new technique for camera
calibration", IEEE TPAMI 22(11)): a board point X_b (metres) goes to the camera frame as
X_c = R X_b + t, to normalised coordinates (x, y) = (X_c/Z_c, Y_c/Z_c), is distorted with
r² = x² + y²,

    x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)
    y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2y²) + 2 p2 x y

and lands on pixel (u, v) = (fx x_d + cx, fy y_d + cy), pixel centres at integer coordinates.
`cv2.calibrateCamera` minimises the squared reprojection error over all views; the RMS it
returns (pixels) is sqrt(Σ‖u_obs − u_model‖² / N_points).

OpenCV 5 keeps only the class API for ChArUco (docs/design.md §7):
`aruco.CharucoDetector.detectBoard` then `board.matchImagePoints`; detection needs 8-bit input, so
16-bit and float images are scaled to 8 bits first.
"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from plumbing.atomic import atomic_write_bytes
from plumbing.errors import UserError
from plumbing.inputs import FRAME_MAX_BYTES, read_input_bytes

__all__ = [
    "BoardSpec",
    "BoardSpecError",
    "CalibrationInputError",
    "CalibrationResult",
    "RESULT_KEYS",
    "SUBPIX_HALF_WINDOW",
    "board_pose",
    "calibrate_images",
    "detect_board",
    "format_result",
    "load_gray8",
    "parse_board",
    "to_gray8",
    "write_result_json",
]

#: The keys of the `--json` output, exactly (issue 6 item 3).
RESULT_KEYS = ("fx", "fy", "cx", "cy", "dist", "rms_px", "views_used")

_EXPECTED = (
    "expected charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (COLSxROWS counts squares, "
    "e.g. charuco:8x6:0.03:0.022:DICT_5X5_100) or chessboard:COLSxROWS:SQUARE_M "
    "(COLSxROWS counts inner corners, e.g. chessboard:9x6:0.025)"
)

# A ChArUco view with fewer interpolated corners than this is not used: 6 points are the
# fewest from which OpenCV's planar initialisation (homography, 4+) and the per-view pose
# (6 dof) are comfortably over-determined.
MIN_CHARUCO_CORNERS = 6
# Zhang's method needs ≥ 3 views of a plane to solve for a general camera matrix without
# assumptions (each view gives two constraints on the 5 entries of B = K⁻ᵀK⁻¹ plus distortion).
MIN_VIEWS = 3
# cornerSubPix half-window (px) for chessboards, OpenCV's calibration-sample default. It must
# stay below the corner spacing in the image: on OpenCV's left*.jpg (squares ≈ 25–30 px) a
# half-window of 5 gives RMS 0.196 px instead of 0.393 px, and fx 0.6 % lower.
SUBPIX_HALF_WINDOW = 11


class BoardSpecError(UserError, ValueError):
    """A `--board` string that cannot be parsed; the message is one line."""


class CalibrationInputError(UserError, ValueError):
    """Calibration images that cannot give a calibration; the message is one line."""


@dataclass(frozen=True)
class BoardSpec:
    """A calibration target.

    kind: "charuco" or "chessboard". For ChArUco, (cols, rows) count *squares*; for a
    chessboard they count *inner corners*. Lengths in metres. `dictionary` is the canonical
    OpenCV name (e.g. "DICT_5X5_100"), None for a chessboard.
    """

    kind: str
    cols: int
    rows: int
    square_m: float
    marker_m: float | None = None
    dictionary: str | None = None

    def __str__(self) -> str:
        if self.kind == "charuco":
            name = (self.dictionary or "").removeprefix("DICT_")
            return f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:{name}"
        return f"chessboard:{self.cols}x{self.rows}:{self.square_m:g}"

    @property
    def inner_corners(self) -> tuple[int, int]:
        """(cols, rows) of the inner chessboard corners, the points that are measured."""
        if self.kind == "charuco":
            return self.cols - 1, self.rows - 1
        return self.cols, self.rows

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object (ChArUco only). Board frame: origin at the outer top-left
        corner of the squares, x along the columns, y along the rows, z into the board."""
        if self.kind != "charuco":
            raise TypeError("charuco_board() needs a charuco board spec")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.cols, self.rows), self.square_m, self.marker_m, dictionary
        )

    def chessboard_object_points(self) -> np.ndarray:
        """(N, 3) float32 inner-corner positions in the order `findChessboardCorners` returns
        them (row by row): corner (i, j) at (i·s, j·s, 0), origin at the first inner corner."""
        i, j = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        pts = np.zeros((self.cols * self.rows, 3), np.float32)
        pts[:, 0] = i.ravel() * self.square_m
        pts[:, 1] = j.ravel() * self.square_m
        return pts


# OpenCV's predefined dictionaries by upper-case name (the module exports e.g. both
# DICT_APRILTAG_36h11 and DICT_APRILTAG_36H11).
_DICTIONARIES = {
    n.upper(): getattr(cv2.aruco, n)
    for n in dir(cv2.aruco)
    if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int)
}

_DIMS = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def _bad(spec: str, reason: str) -> BoardSpecError:
    return BoardSpecError(f"bad board spec {spec!r}: {reason}; {_EXPECTED}")


def _positive_length(spec: str, text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise _bad(spec, f"{what} {text!r} is not a number") from None
    if not np.isfinite(value) or value <= 0:
        raise _bad(spec, f"{what} must be a positive length in metres, got {text!r}")
    return value


def parse_board(spec: str) -> BoardSpec:
    """Parse "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT" or "chessboard:COLSxROWS:SQUARE_M".

    DICT is an OpenCV predefined dictionary, with or without the "DICT_" prefix
    (DICT_5X5_100 or 5X5_100). Raises `BoardSpecError` with a one-line message.
    """
    if not isinstance(spec, str):
        raise BoardSpecError(f"bad board spec {spec!r}: not a string; {_EXPECTED}")
    parts = spec.strip().split(":")
    kind = parts[0].strip().lower()
    if kind not in ("charuco", "chessboard"):
        raise _bad(spec, f"unknown board kind {parts[0]!r}")
    n_fields = 5 if kind == "charuco" else 3
    if len(parts) != n_fields:
        raise _bad(spec, f"{kind} takes {n_fields} ':'-separated fields, got {len(parts)}")
    m = _DIMS.match(parts[1])
    if m is None:
        raise _bad(spec, f"COLSxROWS {parts[1]!r} is not two integers joined by 'x'")
    cols, rows = int(m.group(1)), int(m.group(2))
    square_m = _positive_length(spec, parts[2], "SQUARE_M")
    if kind == "chessboard":
        # findChessboardCorners asserts both pattern dimensions are > 2.
        if cols < 3 or rows < 3:
            raise _bad(spec, f"a chessboard needs at least 3x3 inner corners, got {cols}x{rows}")
        return BoardSpec("chessboard", cols, rows, square_m)

    if cols < 3 or rows < 3:
        raise _bad(spec, f"a ChArUco board needs at least 3x3 squares, got {cols}x{rows}")
    marker_m = _positive_length(spec, parts[3], "MARKER_M")
    if marker_m >= square_m:
        raise _bad(spec, f"MARKER_M {marker_m:g} must be smaller than SQUARE_M {square_m:g}")
    name = parts[4].strip().upper()
    if not name.startswith("DICT_"):
        name = "DICT_" + name
    dict_id = _DICTIONARIES.get(name)
    if dict_id is None:
        raise _bad(spec, f"unknown ArUco dictionary {parts[4].strip()!r}")
    n_markers = cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0]
    # White squares carry the markers: ⌊cols·rows/2⌋ of them, each needing its own id.
    needed = (cols * rows) // 2
    if needed > n_markers:
        raise _bad(spec, f"{cols}x{rows} squares need {needed} markers but {name} has {n_markers}")
    canonical = next(n for n in dir(cv2.aruco) if n.upper() == name)
    return BoardSpec("charuco", cols, rows, square_m, marker_m, canonical)


def load_gray8(path: Path | str) -> np.ndarray | None:
    """Read an image (JPEG, PNG, TIFF, …) as 8-bit grayscale; None if it cannot be read.

    16-bit and float images are scaled by their maximum into 0…255: corner detection looks at
    contrast only, and OpenCV's ArUco detector rejects anything but 8-bit.
    """
    # imdecode on the bytes rather than imread: a missing file is an OSError here instead of
    # an OpenCV log line on stderr, and both end as "unreadable". Read through plumbing.inputs:
    # a FIFO among the images waited forever for a writer, a device never ended.
    try:
        data = np.frombuffer(read_input_bytes(path, "image", FRAME_MAX_BYTES), dtype=np.uint8)
    except OSError:
        return None
    if data.size == 0:
        return None
    try:  # OpenCV refuses an image whose header declares more than 2³⁰ pixels (cv2.error)
        img = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    except cv2.error:
        return None
    if img is None or img.size == 0:
        return None
    return to_gray8(img)


def to_gray8(img: np.ndarray) -> np.ndarray:
    """Any 2-D or BGR(A) array → 8-bit grayscale (non-8-bit input scaled by its maximum)."""
    img = np.asarray(img)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[..., 0]
        else:
            code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            img = cv2.cvtColor(img, code)
    if img.dtype == np.uint8:
        return img
    work = np.nan_to_num(img.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    work -= min(work.min(), 0.0)
    peak = work.max()
    if peak > 0:
        work *= 255.0 / peak
    return np.clip(np.rint(work), 0, 255).astype(np.uint8)


def detect_board(
    gray: np.ndarray, board: BoardSpec, *, subpix_half_window: int = SUBPIX_HALF_WINDOW
) -> tuple[np.ndarray, np.ndarray] | None:
    """Find the board in an 8-bit image.

    Returns (object_points (N, 3) float32 metres, image_points (N, 2) float32 pixels), or None
    when the board is not found (chessboard: not every inner corner; ChArUco: fewer than
    `MIN_CHARUCO_CORNERS` corners, or all on one line).
    """
    gray = to_gray8(gray)
    if board.kind == "chessboard":
        size = (board.cols, board.rows)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, size, flags=flags)
        if not found:
            return None
        # Same refinement as OpenCV's calibration sample (half-window 11 px, stop after 30
        # iterations or a 0.1 px step), the procedure behind the published calibration of
        # OpenCV's own chessboard set, so our figures are comparable with it.
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.1)
        win = (subpix_half_window, subpix_half_window)
        corners = cv2.cornerSubPix(gray, corners, win, (-1, -1), criteria)
        return board.chessboard_object_points(), corners.reshape(-1, 2).astype(np.float32)

    cv_board = board.charuco_board()
    detector = cv2.aruco.CharucoDetector(
        cv_board, cv2.aruco.CharucoParameters(), cv2.aruco.DetectorParameters()
    )
    corners, ids, _marker_corners, _marker_ids = detector.detectBoard(gray)
    if corners is None or ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    if cv_board.checkCharucoCornersCollinear(ids):
        return None
    obj, img = cv_board.matchImagePoints(corners, ids)
    return obj.reshape(-1, 3).astype(np.float32), img.reshape(-1, 2).astype(np.float32)


class CalibrationResult(dict):
    """The calibration as a plain dict with exactly `RESULT_KEYS` (what `--json` writes), plus
    attributes that stay out of the JSON: `skipped` [(file name, reason)], `image_size` (w, h),
    and the OpenCV matrices `camera_matrix` (3×3) and `dist_coeffs` (5,)."""

    skipped: list[tuple[str, str]]
    image_size: tuple[int, int]

    @property
    def camera_matrix(self) -> np.ndarray:
        return _camera_matrix(self)

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self["dist"], dtype=np.float64)


def _camera_matrix(intr: Mapping) -> np.ndarray:
    return np.array(
        [[intr["fx"], 0.0, intr["cx"]], [0.0, intr["fy"], intr["cy"]], [0.0, 0.0, 1.0]],
        dtype=np.float64,
    )


def calibrate_images(
    paths: Sequence[Path | str],
    board: BoardSpec,
    fix_aspect: bool = False,
    *,
    subpix_half_window: int = SUBPIX_HALF_WINDOW,
) -> CalibrationResult:
    """Calibrate intrinsics + distortion (k1, k2, p1, p2, k3) from images of `board`.

    Unreadable images, images of another size than the first readable one, and views where the
    board is not found are skipped with one counted warning; fewer than 3 usable views raise
    `CalibrationInputError`. `fix_aspect` holds fx/fy = 1 (cv2.CALIB_FIX_ASPECT_RATIO);
    `subpix_half_window` is the chessboard corner-refinement half-window in pixels.
    Returns a `CalibrationResult` (a dict with exactly `RESULT_KEYS`).
    """
    object_points: list[np.ndarray] = []
    image_points: list[np.ndarray] = []
    used: list[str] = []
    skipped: list[tuple[str, str]] = []
    size: tuple[int, int] | None = None
    for p in paths:
        p = Path(p)
        gray = load_gray8(p)
        if gray is None:
            skipped.append((p.name, "unreadable image"))
            continue
        h, w = gray.shape
        if size is None:
            size = (w, h)
        elif (w, h) != size:
            skipped.append((p.name, f"size {w}x{h} differs from {size[0]}x{size[1]}"))
            continue
        found = detect_board(gray, board, subpix_half_window=subpix_half_window)
        if found is None:
            skipped.append((p.name, "board not found"))
            continue
        object_points.append(found[0])
        image_points.append(found[1])
        used.append(p.name)

    if skipped:
        detail = ", ".join(f"{name} ({why})" for name, why in skipped)
        warnings.warn(
            f"skipped {len(skipped)} of {len(paths)} images: {detail}", UserWarning, stacklevel=2
        )
    if len(used) < MIN_VIEWS:
        raise CalibrationInputError(
            f"only {len(used)} of {len(paths)} images are usable views of {board} "
            f"(readable, board found); calibration needs at least {MIN_VIEWS}"
        )

    flags = cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect else 0
    # With FIX_ASPECT_RATIO and no intrinsic guess OpenCV keeps only the ratio fx/fy of the
    # matrix passed in: identity → square pixels.
    k0 = np.eye(3, dtype=np.float64)
    rms, k, dist, _rvecs, _tvecs = cv2.calibrateCamera(
        object_points, image_points, size, k0, None, flags=flags
    )
    dist = np.asarray(dist, dtype=np.float64).ravel()[:5]
    result = CalibrationResult(
        fx=float(k[0, 0]),
        fy=float(k[1, 1]),
        cx=float(k[0, 2]),
        cy=float(k[1, 2]),
        dist=[float(d) for d in dist],
        rms_px=float(rms),
        views_used=used,
    )
    result.skipped = skipped
    result.image_size = size
    return result


def board_pose(
    image: np.ndarray | Path | str, board: BoardSpec, intrinsics: Mapping
) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the board in the camera frame, X_c = R(rvec) X_b + tvec, by `cv2.solvePnP`.

    `intrinsics` holds fx, fy, cx, cy and optionally dist (k1, k2, p1, p2, k3), e.g. a
    `calibrate_images` result. Returns (rvec (3,) Rodrigues radians, tvec (3,) metres).
    A chessboard's pose is defined only up to the 180° turn `findChessboardCorners` may pick
    for a symmetric pattern; ChArUco has no such ambiguity.
    """
    if isinstance(image, (str, Path)):
        gray = load_gray8(image)
        if gray is None:
            raise CalibrationInputError(f"cannot read image {str(image)!r}")
    else:
        gray = to_gray8(image)
    found = detect_board(gray, board)
    if found is None:
        raise CalibrationInputError(f"board {board} not found in the image")
    obj, img = found
    k = _camera_matrix(intrinsics)
    dist = np.asarray(intrinsics.get("dist", np.zeros(5)), dtype=np.float64)
    # Planar target: OpenCV initialises from the homography, then Levenberg–Marquardt.
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationInputError("solvePnP found no pose for the detected board")
    return rvec.ravel(), tvec.ravel()


def write_result_json(result: Mapping, path: Path | str) -> None:
    """Write exactly `RESULT_KEYS` as JSON; via a temporary file and an atomic rename, so an
    interrupted write never leaves a half-written file behind."""
    path = Path(path)
    payload = {key: result[key] for key in RESULT_KEYS}
    atomic_write_bytes(path, (json.dumps(payload, indent=2) + "\n").encode())


def format_result(result: Mapping) -> str:
    """Human-readable text of a calibration result (what `gonio calibrate-camera` prints)."""
    k1, k2, p1, p2, k3 = (list(result["dist"]) + [0.0] * 5)[:5]
    lines = [
        "camera intrinsics",
        f"  fx       {result['fx']:12.4f} px",
        f"  fy       {result['fy']:12.4f} px",
        f"  cx       {result['cx']:12.4f} px",
        f"  cy       {result['cy']:12.4f} px",
        "distortion (OpenCV k1, k2, p1, p2, k3)",
        f"  k1       {k1:12.6f}",
        f"  k2       {k2:12.6f}",
        f"  p1       {p1:12.6f}",
        f"  p2       {p2:12.6f}",
        f"  k3       {k3:12.6f}",
        f"RMS reprojection error {result['rms_px']:.4f} px",
        f"views used ({len(result['views_used'])}): " + ", ".join(result["views_used"]),
    ]
    skipped = getattr(result, "skipped", None)
    if skipped:
        lines.append(f"skipped ({len(skipped)}): " + ", ".join(f"{n} ({r})" for n, r in skipped))
    return "\n".join(lines)

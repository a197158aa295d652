"""One pose's frames → merged, flat-corrected colour planes with their per-pixel geometry.

Per pose: decode every bracket, subtract the master dark of that exposure (or the nominal
black level when the run has no dark frames), convert to electrons, merge brackets
(noise-optimal HDR, calibration.hdr) per photosite, divide by the flat field (vignetting ×
PRNU, when the run has flat frames), and form colour channels (RGGB → 2×2 superpixels, greens
summed), each with the geometry of its own photosites (calibration.geometry). Also the image
segmentation of the sample (calibration.segmentation) around its projected footprint.

`RunCalibration` holds what every pose of a run shares: the camera's radiometry and intrinsics,
the rig's geometry (with its geometric calibration), the sample size, darks and flat, and the
reduction options — built once per run by calibration.reduce.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calibration.darks import DarkLibrary
from calibration.flatfield import FlatField
from calibration.geometry import (
    Intrinsics,
    PixelGeometry,
    PixelGrid,
    RigGeometry,
    pixel_geometry,
)
from calibration.geometry import project_points as _project
from calibration.hdr import RawBrackets, merge_frames_local
from calibration.linearity import Linearity, linearise_dn
from calibration.radiometry import CameraRadiometry
from calibration.segmentation import segment_sample
from plumbing.errors import UserError

__all__ = [
    "PlaneError",
    "RunCalibration",
    "Plane",
    "pose_planes",
    "footprint_window",
    "Window",
    "block_all",
    "bracket_noise_e",
    "bracket_zero_dn",
]


class PlaneError(UserError, ValueError):
    """Frames of a pose that cannot be combined (shapes differ, an unsupported mosaic)."""


@dataclass(frozen=True)
class RunCalibration:
    """What the reduction of every pose of one run uses (see module doc). `options` is a
    calibration.reduce.ReduceOptions."""

    run_dir: Path
    radiometry: CameraRadiometry
    intrinsics: Intrinsics
    geometry: RigGeometry
    sample_size_m: float
    darks: DarkLibrary | None
    flat: FlatField | None
    options: Any
    #: The camera's response measured from the brackets (calibration.linearity), or None.
    linearity: Linearity | None = None


def _pointing_margin_m(cal: RunCalibration, cam_pos_m: np.ndarray) -> float:
    """How far inside the sample's edge a pixel must see to stay on the sample when the camera
    arm points off by the angle errors the rig file states (its zero, play and sag; the fit
    carries them, fitting.nuisance, but the footprint moves with them) or sits further than
    stated: 2σ of the footprint's shift, r·σ/cos θ_o along the view ⊕ the edge's R·σ_d/r (a
    pixel straddling the edge reads up to half of f — 25σ low on the realistic rig at
    θ_o = 60°). 0 when the rig states none."""
    geo = cal.geometry.kinematics.geometry
    parts = [
        (geo.axis_zero_sigma_deg or {}).get("camera_theta"),
        None if geo.backlash_deg is None else 0.5 * geo.backlash_deg,
        geo.arm_sag_deg,
    ]
    sigma = math.radians(math.hypot(*(p for p in parts if p is not None)) if any(
        p is not None for p in parts) else 0.0)  # fmt: skip
    r = float(np.linalg.norm(cam_pos_m))
    cos_o = max(abs(float(cam_pos_m[2])) / r, 0.2) if r > 0 else 1.0
    # A pupil further than stated sees the sample smaller: its edge moves in by half the
    # side times σ_d/r (the fit carries the distance, fitting.nuisance, not the footprint).
    sigma_d = geo.camera_distance_sigma_m or 0.0
    edge = 0.5 * cal.sample_size_m * sigma_d / r if r > 0 else 0.0
    return 2.0 * math.hypot(r * sigma / cos_o, edge)


@dataclass
class Plane:
    """One colour channel of a pose at channel resolution, with its per-pixel geometry."""

    name: str
    flux: np.ndarray  # e/s per channel value (flat-corrected)
    var: np.ndarray
    all_sat: np.ndarray
    geo: PixelGeometry  # on_sample includes the edge margin (and whole superpixels)
    offset: float
    step: int
    sites: int
    # The frame's photosite (x, y) at the plane's corner: planes cover the window around the
    # sample's footprint (`footprint_window`), pixel u of the plane is x0 + offset + step·u.
    origin: tuple[int, int] = (0, 0)


def block_all(a: np.ndarray, b: int) -> np.ndarray:
    """True for each b × b block of the first two axes whose elements all are (a trailing
    partial block is dropped): the b² strided views ANDed into one, each element read once in
    contiguous runs (a reduction over the axes of a reshaped array was 3–10× slower)."""
    h, w = a.shape[0] // b * b, a.shape[1] // b * b
    out = a[0:h:b, 0:w:b].copy()
    for i in range(b):
        for j in range(b):
            if i or j:
                out &= a[i:h:b, j:w:b]
    return out


def _channels_of(flux, var, sat, channels: str, cfa_pattern: str | None):
    """Per-channel planes of merged flux, variance and all-saturated masks, plus the pixel step
    and per-channel offsets for geometry (Bayer → 2×2 superpixels) and photosites per channel
    value. In an RGGB tile the R site sits at (0, 0), B at (1, 1) and the two greens' centroid
    at (0.5, 0.5): each channel's rays go through its own photosites (a 0.5 px shift is 0.06°
    here, which would bias a steep specular lobe by ~0.5%)."""
    if channels == "CFA":
        pattern = str(cfa_pattern).upper()
        if pattern != "RGGB":
            raise PlaneError(f"CFA pattern {pattern} not supported yet (RGGB only)")

        def split(a, combine):
            r, g1, g2, b = a[0::2, 0::2], a[0::2, 1::2], a[1::2, 0::2], a[1::2, 1::2]
            return [r, combine(g1, g2), b]

        # Two green photosites are summed (not averaged) so the electron count stays Poisson.
        return (
            ["R", "G", "B"],
            split(flux, np.add),
            split(var, np.add),
            split(sat, np.logical_or),
            2,
            [0.0, 0.5, 1.0],
            [1, 2, 1],
        )
    if flux.ndim == 2:
        return ["Y"], [flux], [var], [sat], 1, [0.0], [1]
    n = flux.shape[2]
    return (
        ["R", "G", "B"][:n],
        [flux[..., c] for c in range(n)],
        [var[..., c] for c in range(n)],
        [sat[..., c] for c in range(n)],
        1,
        [0.0] * n,
        [1] * n,
    )


@dataclass(frozen=True)
class Window:
    """A rectangle of the frame, photosites x0 ≤ x < x1, y0 ≤ y < y1."""

    x0: int
    y0: int
    x1: int
    y1: int

    @classmethod
    def whole(cls, shape: tuple[int, ...]) -> Window:
        return cls(0, 0, int(shape[1]), int(shape[0]))

    def of(self, a: np.ndarray) -> np.ndarray:
        """The window of a frame-shaped array (H, W) or (H, W, C): a view, not a copy."""
        return a[self.y0 : self.y1, self.x0 : self.x1]

    @property
    def bounds(self) -> tuple[int, int, int, int]:
        return self.x0, self.y0, self.x1, self.y1


#: Points per side of the sample square projected to bound its image (a distorted side bows).
_SIDE_POINTS = 33


def footprint_window(
    cal: RunCalibration,
    camera: tuple[np.ndarray, np.ndarray],
    size_m: float,
    step: int,
    shape: tuple[int, ...],
) -> Window | None:
    """The part of a frame (`shape`) a pose's reduction needs: the bounding box of the image of
    the square of side `size_m` (its sides projected through the camera model, distortion
    included), widened by what looks beyond it — the segmentation's edge search (its band, the
    ±1 px step and the bilinear neighbour, in colour-plane pixels of `step` photosites) and the
    HDR merge's same-colour neighbours (2 photosites) — and aligned to whole regions of
    `step` × bin_px photosites, so every plane, region and block is the whole frame's. Pixels
    outside it cannot be on the sample or in its search band, so the samples are the whole
    frame's. None (use the whole frame) when the square is not wholly in front of the camera
    or the window would be empty or the whole frame."""
    cam_pos, rot = camera
    half = size_m / 2.0
    corners = np.array([[-half, -half], [half, -half], [half, half], [-half, half], [-half, -half]])
    s = np.linspace(0.0, 1.0, _SIDE_POINTS)[:, None]
    sides = zip(corners[:-1], corners[1:], strict=True)
    edges = np.concatenate([a + s * (b - a) for a, b in sides])
    points = np.column_stack([edges, np.zeros(len(edges))])
    if np.any((points - cam_pos) @ rot[:, 2] <= 0):  # behind the camera: no bounded image
        return None
    uv = _project(cal.intrinsics, cam_pos, points, rot)
    if not np.all(np.isfinite(uv)):
        return None
    pad = (math.ceil(cal.options.segment_band_px) + 4) * step + 2
    align = step * max(1, int(cal.options.bin_px))
    h, w = int(shape[0]), int(shape[1])
    x0 = max(0, (math.floor(uv[:, 0].min()) - pad) // align * align)
    y0 = max(0, (math.floor(uv[:, 1].min()) - pad) // align * align)
    x1 = min(w, -(-(math.ceil(uv[:, 0].max()) + pad + 1) // align) * align)
    y1 = min(h, -(-(math.ceil(uv[:, 1].max()) + pad + 1) // align) * align)
    if x1 <= x0 or y1 <= y0 or (x0, y0, x1, y1) == (0, 0, w, h):
        return None
    return Window(x0, y0, x1, y1)


def merge_pose(cal: RunCalibration, decoded, exposures, on_sample=None, window=None):
    """Dark-subtract, convert to electrons, HDR-merge and flat-correct at full resolution,
    within `window` (a `Window` of the frames; None: the whole frame).

    Returns flux (e/s per photosite or pixel, flat-corrected), its variance and the
    all-brackets-saturated mask, in the frames' own layout.
    """
    radiometry, flat = cal.radiometry, cal.flat
    k = radiometry.gain_e_per_dn
    shape = decoded[0].dn.shape
    cut = Window.whole(shape) if window is None else window
    dn, noise_sd = [], []
    for d, t in zip(decoded, exposures, strict=True):
        if d.dn.shape != shape:
            raise PlaneError(f"{d.path}: frame shape {d.dn.shape} differs from {shape}")
        dn.append(cut.of(d.dn))
        noise_sd.append(bracket_noise_e(cal, t))
    # Electrons (DN − dark or black)·gain; a bracket is saturated at the camera's clip level
    # (full well, which can sit far below the ADC's white level) and clips at (white − dark)·gain.
    # Weights, variance and the choice of brackets come from the neighbours' flux, never the
    # pixel's own noisy value (calibration.hdr.merge_brackets_local, whose maths
    # merge_frames_local computes without whole-frame temporaries: own-value weights and
    # saturation tests bias the flux and any σ-weighted fit by O(1/N_electrons)).
    # Off-sample neighbours (holder, background) do not enter the local estimate.
    offsets = _offsets(cal, exposures, cut, (len(dn), *dn[0].shape))
    lin = cal.linearity
    if lin is not None and lin.corrected:
        # The bend comes out before the merge: each bracket's zero moves up by what the
        # response added (y_m − y), so (DN − offset) is the linear signal; the saturation test
        # still reads the raw DN.
        y = np.stack(dn).astype(np.float64) - offsets
        offsets = offsets + (y - linearise_dn(y, lin.beta, lin.clip_dn))
    brackets = RawBrackets(
        np.stack(dn),
        offsets,
        list(exposures),
        np.asarray(noise_sd),
        k,
        radiometry.white_level_dn,
    )
    field = None
    if flat is not None:
        if flat.gain.shape != shape:
            raise PlaneError(f"flat field shape {flat.gain.shape} ≠ frame {shape}")
        field = (cut.of(flat.gain), cut.of(flat.rel_var))
    flux, var, all_sat = merge_frames_local(
        brackets,
        valid=on_sample,
        cfa=decoded[0].channels == "CFA",
        flat=field,  # divided out in the merge's own pass
    )
    return flux, var, all_sat


def bracket_noise_e(cal: RunCalibration, exposure_s: float) -> float:
    """A bracket's signal-independent noise σ (e⁻): with darks, the frame's own (measured) dark
    noise plus that of the master subtracted from it; else the read noise and the ADC's step."""
    k = cal.radiometry.gain_e_per_dn
    if cal.darks is not None:
        dark = cal.darks.for_exposure(exposure_s)  # CalibrationFrameError names the exposure
        return k * math.sqrt(dark.temporal_var_dn2 + dark.master_var_dn2)
    return math.sqrt(cal.radiometry.read_noise_e**2 + k**2 / 12.0)


def bracket_zero_dn(cal: RunCalibration, exposure_s: float):
    """What a bracket reads at zero signal: its master dark (frame-shaped), else the black
    level (a scalar)."""
    if cal.darks is not None:
        return cal.darks.for_exposure(exposure_s).dn
    return float(cal.radiometry.black_level_dn)


def _offsets(cal: RunCalibration, exposures, cut: Window, shape: tuple[int, ...]) -> np.ndarray:
    """What each bracket reads at zero signal, (B, …) in the window: the black level broadcast
    without darks; with them one view of the darks' stack when the brackets' masters lie in it
    in order (a stacked copy cost ~0.1 GB a 5 MP pose), else a stack of their windows."""
    darks = cal.darks
    if darks is None:
        return np.broadcast_to(float(cal.radiometry.black_level_dn), shape)
    stacked = darks.stacked(list(exposures))
    if stacked is not None:
        return stacked[:, cut.y0 : cut.y1, cut.x0 : cut.x1]
    return np.stack([cut.of(darks.for_exposure(t).dn) for t in exposures])


def pose_planes(
    cal: RunCalibration,
    decoded,
    exposures,
    axes_measured: dict[str, float],
    size_m: float | None = None,
    *,
    crop: bool = True,
) -> tuple[list[Plane], np.ndarray | None]:
    """Merge a pose's brackets and split it into colour planes with their geometry; also the
    image segmentation of the flat square of side `size_m` (the sample's by default; the
    reference target's for its captures) — bool at channel resolution, None if disabled.
    With `crop` (default) only the window around the square's image is processed
    (`footprint_window`: the same samples, a fraction of the work on a large sensor)."""
    opts, intr = cal.options, cal.intrinsics
    size_m = cal.sample_size_m if size_m is None else size_m
    cam_pos, light_pos, rot = cal.geometry.positions(axes_measured)
    first = decoded[0]
    cfa = first.channels == "CFA"
    window = (
        footprint_window(cal, (cam_pos, rot), size_m, 2 if cfa else 1, first.dn.shape)
        if crop
        else None
    )
    window = window or Window.whole(first.dn.shape)

    def geometry(step: int = 1, offset: float = 0.0, mask_only: bool = False) -> PixelGeometry:
        return pixel_geometry(
            intr,
            cam_pos,
            light_pos,
            size_m,
            grid=PixelGrid(step, offset, window.bounds),
            margin_m=max(opts.margin_m, _pointing_margin_m(cal, cam_pos)),
            rotation=rot,
            mask_only=mask_only,
        )

    # Where each full-resolution pixel (photosite) lands on the sample, edge margin included.
    on_full = geometry(mask_only=True).on_sample
    flux_all, var_all, sat_all = merge_pose(
        cal, decoded, exposures, on_sample=on_full, window=window
    )
    names, fluxes, variances, sats, step, offsets, sites = _channels_of(
        flux_all, var_all, sat_all, first.channels, first.cfa_pattern
    )
    origin = (window.x0, window.y0)
    geos: dict[float, PixelGeometry] = {}
    # A superpixel is on the sample only if every photosite of it is: at grazing views one
    # photosite spans more than the edge margin, so the centroid's test is not enough.
    sites_on = block_all(on_full, step) if step > 1 else None
    planes = []
    for c, name in enumerate(names):
        if offsets[c] not in geos:
            geos[offsets[c]] = geometry(step, offsets[c])
        geo = geos[offsets[c]]
        if sites_on is not None:
            geo = PixelGeometry(
                geo.point_m, geo.wi, geo.wo, geo.light_distance_m, geo.on_sample & sites_on
            )
        planes.append(
            Plane(name, fluxes[c], variances[c], sats[c], geo, offsets[c], step, sites[c], origin)
        )
    seg = None
    if opts.segment:
        seg = _segment(cal, fluxes, variances, sats, (cam_pos, rot), size_m, step, origin)
    return planes, seg


def _segment(cal: RunCalibration, fluxes, variances, sats, camera, size_m, step, origin):
    """The image of all colours together (a superpixel per value for a mosaic) segmented
    around the square's projected corners, in that image's pixel coordinates (the planes'
    window, whose corner is the frame's photosite `origin`)."""
    cam_pos, rot = camera
    half = size_m / 2.0
    corners_m = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]])
    uv = _project(cal.intrinsics, cam_pos, corners_m, rot) - np.asarray(origin, dtype=np.float64)
    corners = (uv - (step - 1) / 2.0) / step
    image = _total(fluxes)
    noise = np.sqrt(_total(variances))
    # A pixel saturated in every bracket is bright whatever its merged value says.
    sat_any = _total(sats)
    finite = np.isfinite(image) & ~sat_any
    image = np.where(sat_any, image[finite].max() if finite.any() else 0.0, image)
    if not np.all(np.isfinite(corners)):
        return None
    return segment_sample(image, corners, noise_sd=noise, band_px=cal.options.segment_band_px).mask


def _total(planes):
    """The planes' element-wise sum (logical or for masks) in order, accumulated in place: the
    value np.sum(planes, axis=0) gives, without stacking the strided colour planes first (its
    sum starts from +0, so −0 becomes +0: the `+ 0.0`)."""
    first = planes[0]
    total = first + 0.0 if first.dtype.kind == "f" else np.array(first, copy=True)
    for plane in planes[1:]:
        total += plane
    return total

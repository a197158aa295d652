"""Reduce a run directory to BRDF samples (`samples.parquet`, DESIGN §4).

Per pose: decode every bracket (untouched frames from `frames/`), subtract the master dark of
that exposure (or the nominal black level when the run has no dark frames), convert to
electrons, merge brackets (noise-optimal HDR) per photosite, divide by the flat field
(vignetting × PRNU, when the run has flat frames), form colour channels (RGGB → 2×2
superpixels, greens summed), convert to radiance with the camera irradiance equation, divide by
the surface irradiance at each pixel's own surface point, and bin pixels into square regions
(σ of the mean from the noise model, including the dark and flat uncertainties).

Radiometry (``ReduceOptions.radiometry``): "certified" divides by the light's certified intensity
(rig config) and trusts the camera irradiance equation; "reference" replaces both by the effective
intensity measured on a reference target (calibration.reference), whose own σ is added in
quadrature to every sample's σ (it is a correlated systematic; also reported in the metadata);
"auto" (default) uses the reference captures when the run has them, else the certified intensity.
Without either the result is relative and flagged so (``gonio.absolute`` = "false").

Segmentation (``ReduceOptions.segment``): per pose the sample is segmented in the image
(calibration.segmentation) around its geometric footprint; footprint pixels the image puts on the
holder or background (a mis-estimated pose, an occluding rim) are kept but flagged MASKED.

Calibration frames live raw in `RUN/calibration/` (`calibration.darks`, `calibration.flatfield`).
Bad input: a frame listed in the manifest but missing → CalibrationError naming the first; a
frame that exists but cannot be decoded (truncated RAW, EXR without colour channels) → that
capture is skipped with a printed warning and counted in the Parquet metadata
(`gonio.skipped_captures`); nothing decodable at all → CalibrationError.
"""

from __future__ import annotations

import json
import math
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.config import RigConfig
from acquisition.kinematics import Kinematics
from acquisition.store import RunStore
from calibration.darks import CalibrationFrameError, load_darks
from calibration.decode import FrameError, decode_frame
from calibration.flatfield import load_flat
from calibration.geometry import Intrinsics, pixel_geometry, project_points
from calibration.hdr import merge_brackets_local
from calibration.radiometry import CameraRadiometry, surface_irradiance
from calibration.reference import (
    ReferenceScale,
    combine_scales,
    load_reference_target,
    pixel_scale,
    reference_entries,
)
from calibration.segmentation import segment_sample
from fitting.directions import vector_to_spherical
from fitting.samples import Flags, SampleTable, write_samples

__all__ = ["ReduceOptions", "CalibrationError", "reduce_run"]

CALIBRATION_VERSION = "1"


class CalibrationError(RuntimeError):
    """A run cannot be reduced; one-line message."""


@dataclass(frozen=True)
class ReduceOptions:
    bin_px: int = 4  # square regions of bin_px × bin_px (super)pixels; 1 = per pixel
    # "mean": a region's value is the mean of its pixels (uses every photon, but averaging a
    # curved lobe over the region's spread of directions broadens it slightly: a 0.5° region
    # biases a Beckmann m = 0.2 by ≈ +2e-4 relative). "center": one pixel per region, with its
    # own exact directions (no averaging bias, fewer photons per sample).
    mode: str = "mean"
    margin_m: float = 0.001  # stay this far inside the sample edge
    min_snr: float = 3.0  # below this a sample is flagged dark
    # Scale the certified intensity by the light monitor's reading recorded with each capture
    # (relative to the commanded level), so lamp drift during a long run does not become a
    # drift of the BRDF. Without a monitor reading the certified value is used as is.
    light_monitor: bool = True
    # "auto": the reference-target scale if the run has reference captures, else the certified
    # intensity; "certified" / "reference" force one (reference without captures is an error).
    radiometry: str = "auto"
    # Segment the sample in each image and flag footprint pixels off it as MASKED.
    segment: bool = True
    segment_band_px: float = 4.0  # largest footprint error (image pixels) the image can correct


def _channels_of(flux, var, sat, channels: str, cfa_pattern: str | None):
    """Per-channel planes of merged flux, variance and all-saturated masks, plus the pixel step
    and per-channel offsets for geometry (Bayer → 2×2 superpixels) and photosites per channel
    value. In an RGGB tile the R site sits at (0, 0), B at (1, 1) and the two greens' centroid
    at (0.5, 0.5): each channel's rays go through its own photosites (a 0.5 px shift is 0.06°
    here, which would bias a steep specular lobe by ~0.5%)."""
    if channels == "CFA":
        pattern = str(cfa_pattern).upper()
        if pattern != "RGGB":
            raise CalibrationError(f"CFA pattern {pattern} not supported yet (RGGB only)")

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


def _block_mean(a: np.ndarray, b: int) -> np.ndarray:
    h, w = a.shape[0] // b * b, a.shape[1] // b * b
    a = a[:h, :w]
    return a.reshape(h // b, b, w // b, b, *a.shape[2:]).mean(axis=(1, 3))


def _block_all(a: np.ndarray, b: int) -> np.ndarray:
    h, w = a.shape[0] // b * b, a.shape[1] // b * b
    return a[:h, :w].reshape(h // b, b, w // b, b).all(axis=(1, 3))


def _block_any(a: np.ndarray, b: int) -> np.ndarray:
    h, w = a.shape[0] // b * b, a.shape[1] // b * b
    return a[:h, :w].reshape(h // b, b, w // b, b).any(axis=(1, 3))


def reduce_run(
    run_dir: str | Path,
    options: ReduceOptions | None = None,
    *,
    out: str | Path | None = None,
    progress: bool = False,
) -> SampleTable:
    """Reduce `run_dir` and write `samples.parquet` into it (or to `out`)."""
    run_dir = Path(run_dir)
    store = RunStore.open(run_dir)
    try:
        return _reduce_open_run(store, run_dir, options or ReduceOptions(), out, progress)
    finally:
        store.close()  # a long-lived process (study, report) must not leak SQLite handles


def _reduce_open_run(
    store: RunStore,
    run_dir: Path,
    options: ReduceOptions,
    out: str | Path | None,
    progress: bool,
) -> SampleTable:
    cfg = store.run_config()
    try:
        rig = RigConfig.model_validate(cfg["rig"])
        camera = cfg["camera"]
        sample_size_m = float(cfg["sample"]["size_m"])
    except KeyError as exc:
        raise CalibrationError(f"{run_dir}/run.toml: missing section {exc.args[0]!r}") from None
    radiometry = CameraRadiometry.from_description(camera)
    intr = Intrinsics.from_description(camera)
    kin = Kinematics(rig)
    absolute = rig.light.intensity_W_sr is not None
    intensity = (
        np.asarray(rig.light.intensity_W_sr, dtype=np.float64) * rig.light.level
        if absolute
        else np.ones(3)
    )

    by_pose: dict[int, list] = defaultdict(list)
    for rec in store.captures("done"):
        by_pose[rec.pose_index].append(rec)
    if not by_pose:
        raise CalibrationError(f"{run_dir}: the run has no completed captures")
    missing = [
        r.frame_path
        for recs in by_pose.values()
        for r in recs
        if not (run_dir / r.frame_path).exists()
    ]
    if missing:
        raise CalibrationError(
            f"{run_dir}: {len(missing)} frame(s) listed in the manifest are missing, "
            f"first {missing[0]}"
        )

    try:
        darks = load_darks(run_dir)
        flat = load_flat(run_dir, darks, radiometry, intr)
    except (CalibrationFrameError, FrameError) as exc:
        raise CalibrationError(f"{run_dir}: {exc}") from None

    if options.radiometry not in ("auto", "certified", "reference"):
        raise CalibrationError(
            f"radiometry must be 'auto', 'certified' or 'reference' (got {options.radiometry!r})"
        )
    try:
        refs = reference_entries(run_dir)
    except CalibrationFrameError as exc:
        raise CalibrationError(f"{run_dir}: {exc}") from None
    method = options.radiometry
    if method == "auto":
        method = "reference" if refs else "certified"
    ref_scale: ReferenceScale | None = None
    ref_rel = np.zeros(3)
    if method == "reference":
        if not refs:
            raise CalibrationError(
                f"{run_dir}: --radiometry reference but the run has no reference-target captures"
            )
        try:
            ref_scale = _reference_scale(
                run_dir,
                refs,
                radiometry,
                intr,
                kin,
                sample_size_m,
                options,
                darks,
                flat,
                rig.light.level,
            )
        except (CalibrationFrameError, FrameError) as exc:
            raise CalibrationError(f"{run_dir}: reference target: {exc}") from None
        absolute = True
        intensity = ref_scale.k
        ref_rel = ref_scale.sigma / ref_scale.k

    cols: dict[str, list[np.ndarray]] = defaultdict(list)
    skipped: list[dict] = []
    iterator = sorted(by_pose.items())
    bar = None
    if progress:
        from rich.progress import Progress

        bar = Progress(transient=True)
        bar.start()
        task = bar.add_task("calibrating", total=len(iterator))
    try:
        for _pose_index, recs in iterator:
            good, decoded = _decode_pose(recs, run_dir, skipped)
            if good:
                _reduce_pose(
                    good,
                    decoded,
                    radiometry,
                    intr,
                    kin,
                    intensity
                    * (_monitor_factor(good, rig.light.level) if options.light_monitor else 1.0),
                    sample_size_m,
                    options,
                    cols,
                    darks,
                    flat,
                    ref_rel,
                )
            if bar is not None:
                bar.advance(task)
    finally:
        if bar is not None:
            bar.stop()
    if not cols:
        # One line, no warnings before it: the error names the first frame that failed.
        if skipped and len(skipped) == sum(len(r) for r in by_pose.values()):
            raise CalibrationError(f"{run_dir}: no frame could be decoded ({skipped[0]['reason']})")
        raise CalibrationError(f"{run_dir}: no pixel of any frame falls on the sample")
    if skipped:
        # Warned only once the reduction has succeeded (the frames are counted in the Parquet
        # metadata too); a handful are named, then the count.
        for rec in skipped[:5]:
            msg = f"warning: skipping capture {rec['capture_id']}: {rec['reason']}"
            print(msg, file=sys.stderr)
        print(
            f"warning: {len(skipped)} capture(s) skipped (unreadable frames), "
            f"first {skipped[0]['frame']}",
            file=sys.stderr,
        )
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    table = SampleTable(
        theta_i=cat["theta_i"],
        phi_i=cat["phi_i"],
        theta_o=cat["theta_o"],
        phi_o=cat["phi_o"],
        channel=cat["channel"],
        f=cat["f"],
        sigma=cat["sigma"],
        flags=cat["flags"].astype(np.int32),
        extra={
            "capture_id": cat["capture_id"].astype(np.int64),
            "pixel_x": cat["pixel_x"].astype(np.int32),
            "pixel_y": cat["pixel_y"].astype(np.int32),
        },
        metadata={
            "gonio.absolute": "true" if absolute else "false",
            "gonio.calibration": json.dumps(
                {
                    "version": CALIBRATION_VERSION,
                    "run": str(run_dir.name),
                    "bin_px": options.bin_px,
                    "radiometry": method,
                    "method": (
                        "reference target: k = L_ref/(f_ref cos(theta_i)/r^2), "
                        "f = L/(k cos(theta_i)/r^2); sigma includes sigma_k in quadrature"
                        if method == "reference"
                        else "camera irradiance equation, point source E = I cos(theta_i)/r^2"
                    ),
                    "intensity_W_sr": np.asarray(intensity).tolist() if absolute else None,
                    "reference": None if ref_scale is None else ref_scale.describe(),
                    "segment": options.segment,
                    "mode": options.mode,
                    "dark": (
                        None
                        if darks is None
                        else {f"{t:g}": m.n_frames for t, m in sorted(darks.masters.items())}
                    ),
                    "flat": None if flat is None else {"frames": flat.n_frames},
                }
            ),
            "gonio.skipped_captures": json.dumps({"count": len(skipped), "captures": skipped}),
        },
    )
    write_samples(Path(out) if out is not None else run_dir / "samples.parquet", table)
    return table


def _decode_pose(recs, run_dir, skipped):
    """Decode a pose's brackets; a frame that cannot be decoded is skipped and recorded."""
    good, decoded = [], []
    for r in recs:
        try:
            decoded.append(decode_frame(run_dir / r.frame_path))
            good.append(r)
        except FrameError as exc:
            skipped.append({"capture_id": int(r.id), "frame": r.frame_path, "reason": str(exc)})
    return good, decoded


def _merge_pose(decoded, exposures, radiometry, darks, flat, on_sample=None):
    """Dark-subtract, convert to electrons, HDR-merge and flat-correct at full resolution.

    Returns flux (e/s per photosite or pixel, flat-corrected), its variance and the
    all-brackets-saturated mask, in the frames' own layout.
    """
    k = radiometry.gain_e_per_dn
    electrons, sats, noise_sd, clip_e = [], [], [], []
    white = radiometry.white_level_dn
    shape = decoded[0].dn.shape
    for d, t in zip(decoded, exposures, strict=True):
        dn = np.asarray(d.dn, dtype=np.float64)
        if dn.shape != shape:
            raise CalibrationError(f"{d.path}: frame shape {dn.shape} differs from {shape}")
        # The camera's clip level (full well), which can sit far below the ADC's white level.
        sats.append(radiometry.saturated(dn))
        if darks is not None:
            try:
                dark = darks.for_exposure(t)
            except CalibrationFrameError as exc:
                raise CalibrationError(str(exc)) from None
            electrons.append((dn - dark.dn) * k)
            clip_e.append((white - dark.dn) * k)  # the clip in dark-subtracted electrons
            # Signal-independent variance: the frame's own (measured) dark noise plus that of
            # the master subtracted from it.
            noise_sd.append(k * math.sqrt(dark.temporal_var_dn2 + dark.master_var_dn2))
        else:
            electrons.append(radiometry.electrons(dn))
            clip_e.append((white - radiometry.black_level_dn) * k)
            noise_sd.append(math.sqrt(radiometry.read_noise_e**2 + k**2 / 12.0))
    # Weights, variance and the choice of brackets from the neighbours' flux, never the pixel's
    # own noisy value (calibration.hdr.merge_brackets_local: own-value weights and saturation
    # tests bias the flux and any σ-weighted fit by O(1/N_electrons)). Off-sample neighbours
    # (holder, background) do not enter the local estimate.
    flux, var, all_sat = merge_brackets_local(
        electrons,
        exposures,
        sats,
        np.asarray(noise_sd),
        clip_e,
        valid=on_sample,
        cfa=decoded[0].channels == "CFA",
    )
    if flat is not None:
        if flat.gain.shape != flux.shape:
            raise CalibrationError(f"flat field shape {flat.gain.shape} ≠ frame {flux.shape}")
        flux, var = flat.apply(flux, var)
    return flux, var, all_sat


def _monitor_factor(recs, level: float) -> float:
    """Mean monitor reading of a pose's captures divided by the commanded level (1 if the light
    reported no reading). The monitor is a photodiode on the lamp: it tracks output drift."""
    readings = []
    for r in recs:
        light = (r.devices or {}).get("light") or {}
        value = light.get("measured")
        if isinstance(value, int | float) and math.isfinite(value) and value > 0:
            readings.append(float(value))
    if not readings or level <= 0:
        return 1.0
    return float(np.mean(readings)) / level


@dataclass
class _Plane:
    """One colour channel of a pose at channel resolution, with its per-pixel geometry."""

    name: str
    flux: np.ndarray  # e/s per channel value (flat-corrected)
    var: np.ndarray
    all_sat: np.ndarray
    geo: object  # PixelGeometry; on_sample includes the edge margin (and whole superpixels)
    offset: float
    step: int
    sites: int


def _pose_planes(
    decoded, exposures, axes, radiometry, intr, kin, sample_size_m, options, darks, flat
):
    """Merge a pose's brackets and split it into colour planes with their geometry; also the
    image segmentation of the sample (bool at channel resolution, None if disabled)."""
    cam_pos, light_pos = kin.camera_position_m(axes), kin.light_position_m(axes)
    # Where each full-resolution pixel (photosite) lands on the sample, edge margin included.
    on_full = pixel_geometry(
        intr, cam_pos, light_pos, sample_size_m, margin_m=options.margin_m
    ).on_sample
    flux_all, var_all, sat_all = _merge_pose(
        decoded, exposures, radiometry, darks, flat, on_sample=on_full
    )
    names, fluxes, variances, sats, step, offsets, sites = _channels_of(
        flux_all, var_all, sat_all, decoded[0].channels, decoded[0].cfa_pattern
    )
    geos: dict[float, object] = {}
    sites_on = None
    if step > 1:
        # A superpixel is on the sample only if every photosite of it is: at grazing views one
        # photosite spans more than the edge margin, so the centroid's test is not enough.
        sites_on = _block_all(on_full, step)
    planes = []
    for c, name in enumerate(names):
        offset = offsets[c]
        if offset not in geos:
            geos[offset] = pixel_geometry(
                intr,
                cam_pos,
                light_pos,
                sample_size_m,
                step=step,
                offset=offset,
                margin_m=options.margin_m,
            )
        geo = geos[offset]
        if sites_on is not None:
            geo = type(geo)(
                geo.point_m, geo.wi, geo.wo, geo.light_distance_m, geo.on_sample & sites_on
            )
        planes.append(_Plane(name, fluxes[c], variances[c], sats[c], geo, offset, step, sites[c]))
    seg = None
    if options.segment:
        # The image of all colours together (a superpixel per value for a mosaic) around the
        # sample's projected corners, in that image's pixel coordinates.
        half = sample_size_m / 2.0
        corners_m = np.array(
            [[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]]
        )
        corners = (project_points(intr, cam_pos, corners_m) - (step - 1) / 2.0) / step
        image = np.sum(fluxes, axis=0)
        noise = np.sqrt(np.sum(variances, axis=0))
        # A pixel saturated in every bracket is bright whatever its merged value says.
        sat_any = np.any(sats, axis=0)
        finite = np.isfinite(image) & ~sat_any
        image = np.where(sat_any, image[finite].max() if finite.any() else 0.0, image)
        if np.all(np.isfinite(corners)):
            seg = segment_sample(
                image, corners, noise_sd=noise, band_px=options.segment_band_px
            ).mask
    return planes, seg


def _reference_scale(
    run_dir, refs, radiometry, intr, kin, sample_size_m, options, darks, flat, level
) -> ReferenceScale:
    """Effective intensity per channel from the reference-target captures (calibration.reference):
    per pose the mean over on-target pixels of L̃/(f_ref cos θ_i/r²), divided by the monitor's
    relative reading at that pose, then combined over poses."""
    target = load_reference_target(run_dir)
    lut = {"R": 0, "G": 1, "B": 2}
    per_pose: list[dict] = []
    names: list[str] | None = None
    for pose, entries in sorted(refs.items()):
        entries = sorted(entries, key=lambda e: float(e["exposure_s"]))
        decoded = [decode_frame(Path(run_dir) / e["path"]) for e in entries]
        exposures = [float(e["exposure_s"]) for e in entries]
        axes = {k: float(v) for k, v in entries[0]["axes_rad"].items()}
        planes, seg = _pose_planes(
            decoded, exposures, axes, radiometry, intr, kin, sample_size_m, options, darks, flat
        )
        readings = [
            float(e["light_measured"])
            for e in entries
            if isinstance(e.get("light_measured"), int | float) and e["light_measured"] > 0
        ]
        monitor = float(np.mean(readings)) / level if readings and level > 0 else 1.0
        ks, ss = [], []
        for pl in planes:
            valid = pl.geo.on_sample & ~pl.all_sat
            if seg is not None:
                valid &= seg
            if valid.sum() < 2:
                raise CalibrationFrameError(f"pose {pose}: the target is not in view")
            wi, wo = pl.geo.wi[valid], pl.geo.wo[valid]
            f_all = target.f_ref(wi, wo)
            f_ref = f_all.mean(axis=1) if pl.name == "Y" else f_all[:, lut[pl.name]]
            scale = radiometry.radiance_per_electron_rate / pl.sites
            e_geom = surface_irradiance(1.0, wi[:, 2], pl.geo.light_distance_m[valid])
            k, sk = pixel_scale(pl.flux[valid] * scale, pl.var[valid] * scale**2, e_geom, f_ref)
            ks.append(k / monitor)
            ss.append(sk / monitor)
        names = [pl.name for pl in planes]
        per_pose.append({"pose": pose, "k_W_sr": ks, "sigma_W_sr": ss})
    k_all = np.array([p["k_W_sr"] for p in per_pose])
    s_all = np.array([p["sigma_W_sr"] for p in per_pose])
    res = [combine_scales(k_all[:, c], s_all[:, c]) for c in range(k_all.shape[1])]
    return ReferenceScale(
        channels=list(names or []),
        k=np.array([r[0] for r in res]),
        sigma=np.array([r[1] for r in res]),
        n_poses=len(per_pose),
        birge=np.array([r[2] for r in res]),
        per_pose=per_pose,
    )


def _reduce_pose(
    recs,
    decoded,
    radiometry,
    intr,
    kin,
    intensity,
    sample_size_m,
    options,
    cols,
    darks,
    flat,
    ref_rel=None,
) -> None:
    exposures = [float(r.exposure_s) for r in recs]
    planes, seg = _pose_planes(
        decoded,
        exposures,
        recs[0].axes_measured,
        radiometry,
        intr,
        kin,
        sample_size_m,
        options,
        darks,
        flat,
    )
    k_rad = radiometry.radiance_per_electron_rate
    ref_rel = np.zeros(3) if ref_rel is None else np.asarray(ref_rel, dtype=np.float64)
    for c, pl in enumerate(planes):
        name, geo = pl.name, pl.geo
        b = options.bin_px
        offset, step_c = pl.offset, pl.step
        flux, var, all_sat = pl.flux, pl.var, pl.all_sat
        off_image = np.zeros(flux.shape, bool) if seg is None else ~seg
        if options.mode == "center" and b > 1:
            # Keep the pixel nearest each region's centre; then treat it as a 1×1 region.
            h, w = geo.on_sample.shape[0] // b, geo.on_sample.shape[1] // b
            m = b // 2

            def pick(a, m=m, h=h, w=w, b=b):
                return a[m::b, m::b][:h, :w]

            geo = type(geo)(
                *(
                    pick(a)
                    for a in (geo.point_m, geo.wi, geo.wo, geo.light_distance_m, geo.on_sample)
                )
            )
            flux, var, all_sat, off_image = pick(flux), pick(var), pick(all_sat), pick(off_image)
            offset = offset + m * step_c
            step_c = step_c * b
            b = 1
        on = _block_all(geo.on_sample, b)
        if not on.any():
            continue
        e_surf_geom = surface_irradiance(1.0, geo.wi[..., 2], geo.light_distance_m)  # × I
        wi = _block_mean(geo.wi, b)
        wo = _block_mean(geo.wo, b)
        wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
        wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
        ti, pi = vector_to_spherical(wi[on])
        to, po = vector_to_spherical(wo[on])
        ys, xs = np.nonzero(on)
        px = (xs * b + (b - 1) / 2.0) * step_c + offset
        py = (ys * b + (b - 1) / 2.0) * step_c + offset
        scale = k_rad / pl.sites  # summed greens count twice the photosite area
        if name != "Y":
            i_c = float(intensity[min(c, len(intensity) - 1)])
            rel_c = float(ref_rel[min(c, len(ref_rel) - 1)])
        else:
            i_c, rel_c = float(np.mean(intensity)), float(np.mean(ref_rel))
        e_surf = e_surf_geom * i_c
        with np.errstate(divide="ignore", invalid="ignore"):
            f_px = flux * scale / e_surf
            var_f_px = var * (scale / e_surf) ** 2
        f_reg = _block_mean(f_px, b)[on]
        n_px = b * b
        # The reference scale's σ is common to every sample of the channel (a correlated
        # systematic); adding it in quadrature keeps each σ honest on its own.
        sigma_reg = np.sqrt(_block_mean(var_f_px, b)[on] / n_px + (f_reg * rel_c) ** 2)
        flags = np.zeros(f_reg.shape, np.int32)
        flags[_block_any(all_sat, b)[on]] |= Flags.SATURATED
        flags[_block_any(off_image, b)[on]] |= Flags.MASKED
        with np.errstate(divide="ignore", invalid="ignore"):
            snr = f_reg / sigma_reg
        flags[~(snr >= options.min_snr)] |= Flags.DARK
        n = f_reg.shape[0]
        cols["theta_i"].append(ti)
        cols["phi_i"].append(pi)
        cols["theta_o"].append(to)
        cols["phi_o"].append(po)
        cols["channel"].append(np.full(n, name, dtype=object))
        cols["f"].append(f_reg)
        cols["sigma"].append(sigma_reg)
        cols["flags"].append(flags)
        cols["capture_id"].append(np.full(n, recs[0].id, dtype=np.int64))
        cols["pixel_x"].append(np.round(px).astype(np.int32))
        cols["pixel_y"].append(np.round(py).astype(np.int32))

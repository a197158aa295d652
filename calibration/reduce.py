"""Reduce a run directory to BRDF samples (`samples.parquet`, DESIGN §4).

Per pose: decode every bracket (untouched frames from `frames/`), subtract the master dark of
that exposure (or the nominal black level when the run has no dark frames), convert to
electrons, merge brackets (noise-optimal HDR) per photosite, divide by the flat field
(vignetting × PRNU, when the run has flat frames), form colour channels (RGGB → 2×2
superpixels, greens summed), convert to radiance with the camera irradiance equation, divide by
the surface irradiance at each pixel's own surface point, and bin pixels into square regions
(σ of the mean from the noise model, including the dark and flat uncertainties).

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
from calibration.geometry import Intrinsics, pixel_geometry
from calibration.hdr import merge_brackets
from calibration.radiometry import CameraRadiometry, surface_irradiance
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
    options = options or ReduceOptions()
    run_dir = Path(run_dir)
    store = RunStore.open(run_dir)
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
                )
            if bar is not None:
                bar.advance(task)
    finally:
        if bar is not None:
            bar.stop()
    if skipped:
        print(
            f"warning: {len(skipped)} capture(s) skipped (unreadable frames), "
            f"first {skipped[0]['frame']}",
            file=sys.stderr,
        )
    if not cols:
        if skipped and len(skipped) == sum(len(r) for r in by_pose.values()):
            raise CalibrationError(f"{run_dir}: no frame could be decoded ({skipped[0]['reason']})")
        raise CalibrationError(f"{run_dir}: no pixel of any frame falls on the sample")
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
                    "method": "camera irradiance equation, point source E = I cos(theta_i)/r^2",
                    "intensity_W_sr": intensity.tolist() if absolute else None,
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
            print(f"warning: skipping capture {r.id}: {exc}", file=sys.stderr)
    return good, decoded


def _merge_pose(decoded, exposures, radiometry, darks, flat, on_sample=None):
    """Dark-subtract, convert to electrons, HDR-merge and flat-correct at full resolution.

    Returns flux (e/s per photosite or pixel, flat-corrected), its variance and the
    all-brackets-saturated mask, in the frames' own layout.
    """
    k = radiometry.gain_e_per_dn
    electrons, sats, noise_sd = [], [], []
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
            # Signal-independent variance: the frame's own (measured) dark noise plus that of
            # the master subtracted from it.
            noise_sd.append(k * math.sqrt(dark.temporal_var_dn2 + dark.master_var_dn2))
        else:
            electrons.append(radiometry.electrons(dn))
            noise_sd.append(math.sqrt(radiometry.read_noise_e**2 + k**2 / 12.0))
    flux, var, all_sat = merge_brackets(electrons, exposures, sats, np.asarray(noise_sd))
    # Second pass: weights and variance from the neighbours' flux, not the pixel's own noisy
    # value (see merge_brackets: an own-value variance biases the fit by O(1/N_electrons)).
    # Neighbours off the sample (holder, background) must not enter the local estimate: at the
    # edge they would pull it down and understate the variance of edge pixels.
    valid = ~all_sat if on_sample is None else ~all_sat & _broadcast_mask(on_sample, flux)
    local = _local_mean(flux, valid, cfa=decoded[0].channels == "CFA")
    # Which brackets to trust is decided from the neighbours' flux too. Dropping a bracket only
    # when the pixel's own value crossed the clip level is a selection on its noise: near the
    # threshold the long exposure survives only when it fluctuated low, biasing the flanks of
    # a specular peak low. A bracket whose expected signal is within 5σ of the clip level is
    # dropped whatever its own value (values at the clip are always dropped).
    clip_e = (radiometry.white_level_dn - radiometry.black_level_dn) * k
    ref = np.where(np.isfinite(local), local, flux)
    for i, t in enumerate(exposures):
        expected = np.maximum(ref, 0.0) * t
        near = expected + 5.0 * np.sqrt(expected + noise_sd[i] ** 2) >= clip_e
        sats[i] = sats[i] | near
    flux, var, all_sat = merge_brackets(
        electrons, exposures, sats, np.asarray(noise_sd), flux_for_weights=local
    )
    if flat is not None:
        if flat.gain.shape != flux.shape:
            raise CalibrationError(f"flat field shape {flat.gain.shape} ≠ frame {flux.shape}")
        flux, var = flat.apply(flux, var)
    return flux, var, all_sat


def _broadcast_mask(mask: np.ndarray, like: np.ndarray) -> np.ndarray:
    return mask if like.ndim == mask.ndim else np.broadcast_to(mask[..., None], like.shape)


def _local_mean(flux: np.ndarray, valid: np.ndarray, *, cfa: bool) -> np.ndarray:
    """Mean flux of each pixel's same-colour 3×3 neighbourhood, the pixel itself excluded
    (so the estimate is independent of its own noise); NaN where no valid neighbour exists."""
    from scipy.ndimage import uniform_filter

    out = np.full(flux.shape, np.nan)
    planes = (
        [(slice(i, None, 2), slice(j, None, 2)) for i in (0, 1) for j in (0, 1)]
        if cfa
        else [(slice(None), slice(None))]
    )
    for sl in planes:
        f = np.where(valid[sl], flux[sl], 0.0)
        v = valid[sl].astype(np.float64)
        size = (3, 3) + (1,) * (f.ndim - 2)
        tot = uniform_filter(f, size=size, mode="constant") * 9.0 - f
        cnt = uniform_filter(v, size=size, mode="constant") * 9.0 - v
        with np.errstate(invalid="ignore", divide="ignore"):
            out[sl] = np.where(cnt > 0.5, tot / np.maximum(cnt, 1e-12), np.nan)
    return out


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


def _reduce_pose(
    recs, decoded, radiometry, intr, kin, intensity, sample_size_m, options, cols, darks, flat
) -> None:
    exposures = [float(r.exposure_s) for r in recs]
    axes = recs[0].axes_measured
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
    k_rad = radiometry.radiance_per_electron_rate
    geos: dict[float, object] = {}
    sites_on = None
    if step > 1:
        # A superpixel is on the sample only if every photosite of it is: at grazing views one
        # photosite spans more than the edge margin, so the centroid's test is not enough.
        sites_on = _block_all(on_full, step)
    for c, name in enumerate(names):
        b = options.bin_px
        offset, step_c = offsets[c], step
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
        flux, var, all_sat = fluxes[c], variances[c], sats[c]
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
            flux, var, all_sat = pick(flux), pick(var), pick(all_sat)
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
        scale = k_rad / sites[c]  # summed greens count twice the photosite area
        i_c = (
            float(intensity[min(c, len(intensity) - 1)])
            if name != "Y"
            else float(np.mean(intensity))
        )
        e_surf = e_surf_geom * i_c
        with np.errstate(divide="ignore", invalid="ignore"):
            f_px = flux * scale / e_surf
            var_f_px = var * (scale / e_surf) ** 2
        f_reg = _block_mean(f_px, b)[on]
        n_px = b * b
        sigma_reg = np.sqrt(_block_mean(var_f_px, b)[on] / n_px)
        flags = np.zeros(f_reg.shape, np.int32)
        flags[_block_any(all_sat, b)[on]] |= Flags.SATURATED
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

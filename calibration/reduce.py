"""Reduce a run directory to BRDF samples (`samples.parquet`, DESIGN §4).

Per pose: decode every bracket (untouched frames from `frames/`), subtract the black level,
convert to electrons, merge brackets (noise-optimal HDR), convert to radiance with the camera
irradiance equation, divide by the surface irradiance at each pixel's own surface point, and
bin pixels into square regions (σ of the mean from the noise model).
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.config import RigConfig
from acquisition.kinematics import Kinematics
from acquisition.store import RunStore
from calibration.decode import decode_frame
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


def _channels_of(decoded, radiometry: CameraRadiometry):
    """Channel names, per-channel DN planes, per-channel saturation masks, pixel step and offset
    for geometry (Bayer → 2×2 superpixels), and photosites per channel value."""
    dn = np.asarray(decoded.dn, dtype=np.float64)
    # The camera's clip level (full well), which can sit far below the ADC's white level.
    sat = radiometry.saturated(dn)
    if decoded.channels == "CFA":
        pattern = str(decoded.cfa_pattern).upper()
        if pattern != "RGGB":
            raise CalibrationError(f"CFA pattern {pattern} not supported yet (RGGB only)")
        r, g1, g2, b = dn[0::2, 0::2], dn[0::2, 1::2], dn[1::2, 0::2], dn[1::2, 1::2]
        sr, sg1, sg2, sb = sat[0::2, 0::2], sat[0::2, 1::2], sat[1::2, 0::2], sat[1::2, 1::2]
        # Two green photosites are summed (not averaged) so the electron count stays Poisson.
        return ["R", "G", "B"], [r, g1 + g2, b], [sr, sg1 | sg2, sb], 2, 0.5, [1, 2, 1]
    if dn.ndim == 2:
        return ["Y"], [dn], [sat], 1, 0.0, [1]
    names = ["R", "G", "B"][: dn.shape[2]]
    return (
        names,
        [dn[..., c] for c in range(dn.shape[2])],
        [sat[..., c] for c in range(dn.shape[2])],
        1,
        0.0,
        [1] * dn.shape[2],
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

    cols: dict[str, list[np.ndarray]] = defaultdict(list)
    iterator = sorted(by_pose.items())
    bar = None
    if progress:
        from rich.progress import Progress

        bar = Progress(transient=True)
        bar.start()
        task = bar.add_task("calibrating", total=len(iterator))
    try:
        for pose_index, recs in iterator:
            _reduce_pose(
                pose_index,
                recs,
                run_dir,
                radiometry,
                intr,
                kin,
                intensity,
                sample_size_m,
                options,
                cols,
            )
            if bar is not None:
                bar.advance(task)
    finally:
        if bar is not None:
            bar.stop()
    if not cols:
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
                }
            ),
        },
    )
    write_samples(Path(out) if out is not None else run_dir / "samples.parquet", table)
    return table


def _reduce_pose(
    pose_index, recs, run_dir, radiometry, intr, kin, intensity, sample_size_m, options, cols
) -> None:
    decoded = [decode_frame(run_dir / r.frame_path) for r in recs]
    exposures = [float(r.exposure_s) for r in recs]
    per_bracket = [_channels_of(d, radiometry) for d in decoded]
    names, _, _, step, offset, sites = per_bracket[0]
    axes = recs[0].axes_measured
    geo = pixel_geometry(
        intr,
        kin.camera_position_m(axes),
        kin.light_position_m(axes),
        sample_size_m,
        step=step,
        offset=offset,
        margin_m=options.margin_m,
    )
    b = options.bin_px
    if options.mode == "center" and b > 1:
        # Keep the pixel nearest each region's centre; then treat it as a 1×1 region.
        c = b // 2
        geo = type(geo)(
            *(
                a[c::b, c::b][: geo.on_sample.shape[0] // b, : geo.on_sample.shape[1] // b]
                for a in (geo.point_m, geo.wi, geo.wo, geo.light_distance_m, geo.on_sample)
            )
        )
        per_bracket = [
            (
                names_,
                [p[c::b, c::b][: geo.on_sample.shape[0], : geo.on_sample.shape[1]] for p in planes],
                [m[c::b, c::b][: geo.on_sample.shape[0], : geo.on_sample.shape[1]] for m in sats],
                step_ * b,
                offset_ + c * step_,
                sites_,
            )
            for names_, planes, sats, step_, offset_, sites_ in per_bracket
        ]
        step, offset = per_bracket[0][3], per_bracket[0][4]
        b = 1
    on = _block_all(geo.on_sample, b)
    if not on.any():
        return
    cos_i = geo.wi[..., 2]
    e_surf_geom = surface_irradiance(1.0, cos_i, geo.light_distance_m)  # × I per channel
    wi = _block_mean(geo.wi, b)
    wo = _block_mean(geo.wo, b)
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    ti, pi = vector_to_spherical(wi[on])
    to, po = vector_to_spherical(wo[on])
    ys, xs = np.nonzero(on)
    px = (xs * b + (b - 1) / 2.0) * step + offset
    py = (ys * b + (b - 1) / 2.0) * step + offset
    k_rad = radiometry.radiance_per_electron_rate
    read_var = radiometry.read_noise_e**2 + radiometry.gain_e_per_dn**2 / 12.0
    for c, name in enumerate(names):
        electrons = [radiometry.electrons(pb[1][c]) for pb in per_bracket]
        sat = [pb[2][c] for pb in per_bracket]
        n_sites = sites[c]
        flux, var, all_sat = merge_brackets(
            electrons, exposures, sat, math.sqrt(read_var * n_sites)
        )
        scale = k_rad / n_sites  # summed greens count twice the photosite area
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

"""Reduce a run directory to BRDF samples (`samples.parquet`, docs/design.md §4).

Per pose: decode every bracket (untouched frames from `frames/`), subtract the master dark of
that exposure (or the nominal black level when the run has no dark frames), convert to
electrons, merge brackets (noise-optimal HDR) per photosite, divide by the flat field
(vignetting × PRNU, when the run has flat frames), form colour channels (RGGB → 2×2
superpixels, greens summed), convert to radiance with the camera irradiance equation, divide by
the surface irradiance at each pixel's own surface point, and bin pixels into square regions
(σ of the mean from the noise model, including the dark and flat uncertainties).

Radiometry (``ReduceOptions.radiometry``): "certified" divides by the light's certified intensity
(rig config) and trusts the camera irradiance equation (it needs the camera's stated quantum
efficiency); "reference" replaces both by the effective
intensity measured on a reference target (calibration.reference), whose own σ is added in
quadrature to every sample's σ (it is a correlated systematic; also reported in the metadata);
"auto" (default) uses the reference captures when the run has them, else the certified intensity.
Per texel (``ReduceOptions.texel_mm``): every sample also gets the optional int32 column `texel`,
the index of the texel of the sample plane its (region's mean) surface point falls in
(calibration.texels: grid from the sample's corner, index iy·n + ix, the grid in the metadata),
so each texel holds its own (ω_i, ω_o, f, σ) across poses; use ``bin_px = 1`` so a region never
straddles texels. Such a file is written to ``samples-texels.parquet`` by default and never
replaces an existing samples file made with other options (calibration.texels.check_replace).
Without either the result is relative and flagged so (``gonio.absolute`` = "false").

Segmentation (``ReduceOptions.segment``): per pose the sample is segmented in the image
(calibration.segmentation) around its geometric footprint; footprint pixels the image puts on the
holder or background (a mis-estimated pose, an occluding rim) are kept but flagged MASKED.

Everything comes from the run: run.toml's camera, sample, rig and geometric-calibration records
(what the rig file described, acquisition.description) and the calibration frames the run
recorded (`RUN/calibration/`, calibration.darks / flatfield / reference); never from a scene.
The per-pose work (merge, flat, colour planes, geometry, segmentation) is calibration.planes,
done only in the window around the sample's image (calibration.planes.footprint_window), while
the next pose's frames are decoded in a background thread (plumbing.prefetch). Each pose's
samples go to the file as they are made (`reduce_to_file`, brdfdata.samples.SampleStream), so the
memory of a run does not grow with its number of poses; `reduce_run` reads the file back for a
caller that fits the table at once.
Bad input: a frame listed in the manifest but missing → CalibrationError naming the first; a
frame that exists but cannot be decoded (truncated RAW, EXR without colour channels) → that
capture is skipped with a printed warning and counted in the Parquet metadata
(`gonio.skipped_captures`); nothing decodable at all → CalibrationError.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.config import RigConfig
from acquisition.kinematics import Kinematics
from acquisition.run_document import RunDocument
from acquisition.store import RunStore
from brdfdata.directions import vector_to_spherical
from brdfdata.samples import Flags, SampleStream, SampleTable, read_samples, write_samples_streamed
from calibration.darks import CalibrationFrameError, load_darks
from calibration.decode import FrameError, FrameIntegrityError, decode_frame
from calibration.flatfield import load_flat
from calibration.geometry import Intrinsics, RigGeometry
from calibration.hdr import local_mean
from calibration.linearity import MAX_POSES, Linearity, LinearityStats, bend_level
from calibration.planes import (
    Plane,
    PlaneError,
    RunCalibration,
    bracket_noise_e,
    bracket_zero_dn,
    pose_planes,
)
from calibration.radiometry import CameraRadiometry, surface_irradiance
from calibration.reference import (
    ReferenceScale,
    combine_scales,
    load_reference_target,
    pixel_scale,
    reference_entries,
)
from calibration.regions import region_means
from calibration.texels import TexelGrid, check_replace
from plumbing.atomic import check_writable_dir
from plumbing.errors import UserError
from plumbing.prefetch import prefetched
from plumbing.progress import Progress

__all__ = ["ReduceOptions", "CalibrationError", "ReducedSamples", "reduce_run", "reduce_to_file"]

CALIBRATION_VERSION = "3"  # 3: σ is statistical only; shared errors in gonio.budget


class CalibrationError(UserError, RuntimeError):
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
    # Per-texel samples: the side (mm) of square texels on the sample plane; each sample gets
    # the `texel` index of its region's mean surface point (calibration.texels). None: off.
    texel_mm: float | None = None
    # A pose frame whose SHA-256 differs from the manifest's: skipped with a counted warning
    # (False), or the calibration stops (True). Frames are always checked; darks, flats and
    # reference frames always stop on a mismatch (every sample depends on them).
    strict: bool = False


@dataclass(frozen=True)
class ReducedSamples:
    """What `reduce_to_file` wrote: the samples file, its row count and metadata, and the
    number of texels holding samples (per-texel reductions; else None)."""

    path: Path
    rows: int
    metadata: dict[str, str]
    texels: int | None = None


def reduce_run(
    run_dir: str | Path,
    options: ReduceOptions | None = None,
    *,
    out: str | Path | None = None,
    progress: bool = False,
) -> SampleTable:
    """Reduce `run_dir`, write `samples.parquet` into it (or to `out`) and return the table as
    written (read back: the reduction itself keeps only one pose's samples in memory)."""
    done = reduce_to_file(run_dir, options, out=out, progress=progress)
    return read_samples(done.path)


def reduce_to_file(
    run_dir: str | Path,
    options: ReduceOptions | None = None,
    *,
    out: str | Path | None = None,
    progress: bool = False,
) -> ReducedSamples:
    """Reduce `run_dir` into `samples.parquet` (or `out`), pose by pose: each pose's samples go
    to the file as they are made, so memory does not grow with the number of poses."""
    run_dir = Path(run_dir)
    # Closed on the way out: a long-lived process (study, report) must not leak SQLite handles.
    with RunStore.open(run_dir) as store:
        return _reduce_open_run(store, run_dir, options or ReduceOptions(), out, progress)


def _run_calibration(store: RunStore, run_dir: Path, options: ReduceOptions):
    """(RunCalibration, rig config) from run.toml and the run's calibration frames."""
    doc = RunDocument.of(store)
    rig, camera, sample_size_m = doc.rig, doc.camera, float(doc.sample["size_m"])
    try:
        radiometry = CameraRadiometry.from_description(camera)
        intr = Intrinsics.from_description(camera)
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{run_dir}/run.toml: [camera]: {exc}") from None
    geometry = RigGeometry.of_run(Kinematics(rig), doc.arm_offsets)
    try:
        darks = load_darks(run_dir)
        flat = load_flat(run_dir, darks, radiometry, intr)
    except (CalibrationFrameError, FrameError) as exc:
        raise CalibrationError(f"{run_dir}: {exc}") from None
    cal = RunCalibration(run_dir, radiometry, intr, geometry, sample_size_m, darks, flat, options)
    return cal, rig


def _measure_linearity(cal: RunCalibration, by_pose: dict[int, list]) -> Linearity | None:
    """The camera's response from the brackets of up to MAX_POSES poses spread over the run
    (calibration.linearity); None when no pose has two exposures far enough apart."""
    poses = [
        recs for _i, recs in sorted(by_pose.items())
        if len({r.exposure_taken_s for r in recs}) >= 2
    ]  # fmt: skip
    if not poses:
        return None
    pick = poses[:: max(1, math.ceil(len(poses) / MAX_POSES))][:MAX_POSES]
    radiometry = cal.radiometry
    stats = LinearityStats(radiometry.white_level_dn - radiometry.black_level_dn)
    for recs in pick:
        good, decoded = _decode_pose(recs, cal.run_dir, [], strict=False)  # the main pass tells
        if len(good) < 2:
            continue
        exposures = [r.exposure_taken_s for r in good]
        stats.add_pose(
            [d.dn for d in decoded],
            [bracket_zero_dn(cal, t) for t in exposures],
            exposures,
            radiometry.gain_e_per_dn,
            [bracket_noise_e(cal, t) for t in exposures],
            radiometry.white_level_dn,
            cfa=decoded[0].channels == "CFA",
        )
    return stats.result()


def _captures_by_pose(store: RunStore, run_dir: Path) -> dict[int, list]:
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
    return by_pose


@dataclass
class _Scale:
    """The light × camera scale: per-channel intensity (W/sr) and its relative 1-σ."""

    method: str
    absolute: bool
    intensity: np.ndarray
    rel: np.ndarray
    reference: ReferenceScale | None = None


def _radiometric_scale(cal: RunCalibration, rig: RigConfig) -> _Scale:
    run_dir, options = cal.run_dir, cal.options
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
    if method == "certified":
        absolute = rig.light.intensity_W_sr is not None
        if absolute and cal.radiometry.quantum_efficiency is None:
            if options.radiometry == "certified":
                raise CalibrationError(
                    f"{run_dir}: --radiometry certified needs camera.quantum_efficiency in the "
                    "rig file; record reference-target captures instead"
                )
            absolute = False  # the conversion is nominal: the values are relative
        intensity = (
            np.asarray(rig.light.intensity_W_sr, dtype=np.float64) * rig.light.level
            if absolute
            else np.ones(3)
        )
        return _Scale(method, absolute, intensity, np.zeros(3))
    if not refs:
        raise CalibrationError(
            f"{run_dir}: --radiometry reference but the run has no reference-target captures"
        )
    try:
        ref = _reference_scale(cal, refs, rig.light.level)
    except (CalibrationFrameError, FrameError, PlaneError) as exc:
        raise CalibrationError(f"{run_dir}: reference target: {exc}") from None
    return _Scale(method, True, ref.k, ref.sigma / ref.k, ref)


def _reduce_open_run(
    store: RunStore,
    run_dir: Path,
    options: ReduceOptions,
    out: str | Path | None,
    progress: bool,
) -> ReducedSamples:
    default = "samples-texels.parquet" if options.texel_mm else "samples.parquet"
    dest = Path(out) if out is not None else run_dir / default
    # A run on read-only media (an archive, a colleague's share) is read, never written: say so
    # before the reduction, not after it.
    check_writable_dir(dest.parent, "write the samples elsewhere with --out FILE")
    cal, rig = _run_calibration(store, run_dir, options)
    if options.bin_px > min(rig.camera.resolution):
        # a region larger than the frame holds no sample (and a huge one had hung the reduction)
        raise CalibrationError(
            f"--bin-px {options.bin_px}: larger than the camera's frame "
            f"({rig.camera.resolution[0]} × {rig.camera.resolution[1]} pixels); give 1 to "
            f"{min(rig.camera.resolution)}"
        )
    by_pose = _captures_by_pose(store, run_dir)
    try:
        cal = dataclasses.replace(cal, linearity=_measure_linearity(cal, by_pose))
    except (CalibrationFrameError, FrameError) as exc:
        raise CalibrationError(f"{run_dir}: {exc}") from None
    scale = _radiometric_scale(cal, rig)
    skipped: list[dict] = []
    texels: set[int] = set()
    metadata: dict[str, str] = {}

    def produce(stream: SampleStream) -> dict[str, str]:
        monitors: list[float] = []  # per pose, for the report's drift plot
        arm_poses: dict[int, dict] = {}  # per capture: the arms' pose (fitting.nuisance)
        poses = [recs for _pose_index, recs in sorted(by_pose.items())]

        def decode(recs: list) -> tuple[list, list]:
            return _decode_pose(recs, run_dir, skipped, options.strict)

        with Progress("calibrating", len(poses), enabled=progress, transient=True) as bar:
            # The next pose's frames are read and decoded while this one is reduced
            # (plumbing.prefetch): at most two poses' frames are in memory.
            for good, decoded in prefetched(decode, poses):
                if good:
                    level = rig.light.level
                    monitor = _monitor_factor(good, level) if options.light_monitor else 1.0
                    monitors.append(monitor)
                    try:
                        for piece in _reduce_pose(cal, good, decoded, scale.intensity * monitor):
                            stream.append(piece)
                            if "texel" in piece:
                                texels.update(np.unique(piece["texel"]).tolist())
                        arm_poses[good[0].id] = _arm_pose(cal, good[0])
                    except (PlaneError, CalibrationFrameError) as exc:
                        raise CalibrationError(f"{run_dir}: {exc}") from None
                bar.advance()
        if not stream.rows:
            # One line, no warnings before it: the error names the first frame that failed.
            if skipped and len(skipped) == sum(len(r) for r in by_pose.values()):
                reason = skipped[0]["reason"]
                raise CalibrationError(f"{run_dir}: no frame could be decoded ({reason})")
            raise CalibrationError(f"{run_dir}: no pixel of any frame falls on the sample")
        metadata.update(
            {
                **_metadata(cal, rig, scale, skipped, monitors),
                **_budget(rig, scale, RunDocument.of(store).arm_offsets, cal),
                "gonio.arm_poses": json.dumps(_with_approach(arm_poses)),
            }
        )
        if rig.light.radius_m > 0:  # the lamp's extent, for the fit (fitting.likelihood)
            metadata["gonio.lamp"] = json.dumps(
                {"radius_m": rig.light.radius_m, "distance_m": rig.geometry.light_distance_m}
            )
        if options.texel_mm:
            check_replace(dest, metadata)  # before the file replaces anything
        return metadata

    rows = write_samples_streamed(dest, produce)
    _warn_skipped(skipped)
    return ReducedSamples(dest, rows, metadata, len(texels) if options.texel_mm else None)


def _warn_skipped(skipped: list[dict]) -> None:
    """Warned only once the reduction has succeeded (the frames are counted in the Parquet
    metadata too); a handful are named, then the count."""
    if not skipped:
        return
    for rec in skipped[:5]:
        print(f"warning: skipping capture {rec['capture_id']}: {rec['reason']}", file=sys.stderr)
    print(
        f"warning: {len(skipped)} capture(s) skipped (unreadable or changed frames), "
        f"first {skipped[0]['frame']}",
        file=sys.stderr,
    )


def _budget(
    rig: RigConfig, scale: _Scale, arm_offsets: dict | None, cal: RunCalibration | None = None
) -> dict[str, str]:
    """The samples' uncertainty budget as Parquet metadata (``gonio.budget``, see
    _budget_components)."""
    return {"gonio.budget": json.dumps(_budget_components(rig, scale, arm_offsets, cal))}


def _arm_components(rig: RigConfig, arm_offsets: dict | None) -> list[dict]:
    """The arms' shared angle errors: the encoder zeros and the sample's tilt (measured by
    `gonio calibrate-rig`, to its σ; else the rig file's estimates
    ``geometry.axis_zero_sigma_deg`` and ``geometry.sample_tilt_sigma_deg``; else unknown) and the
    play and sag nobody measured. With sizes, the zeros carry the rig's kinematics preset (how
    an axis' zero moves θ_o: fitting.nuisance) and the fit marginalises them; the play and sag
    are named and not propagated (they differ from pose to pose)."""
    preset = rig.geometry.preset
    if arm_offsets and arm_offsets.get("sigma_deg"):
        # calibrate-rig's own σ of what it measured (camera zeros, the sample's tilt). Its
        # roll's is left out: a roll error δρ turns a pixel's ray about the optical axis, by
        # δρ times the pixel's angle off the axis (≤ 0.1 of δρ on a 12° field): not a term of
        # the arms' error model, and a few 0.01° after calibrate-rig.
        sig = {k: float(v) for k, v in arm_offsets["sigma_deg"].items() if k != "camera_roll"}
        zero = {"component": "arm angles: encoder zeros (gonio calibrate-rig)", "type": "A"}
    elif rig.geometry.axis_zero_sigma_deg or rig.geometry.sample_tilt_sigma_deg:
        sig = {k: float(v) for k, v in (rig.geometry.axis_zero_sigma_deg or {}).items()}
        if rig.geometry.sample_tilt_sigma_deg:
            sig.update(dict.fromkeys(("tilt_x", "tilt_y"), rig.geometry.sample_tilt_sigma_deg))
        zero = {"component": "arm angles: encoder zeros (rig file estimate)", "type": "B"}
    else:
        sig = None
        zero = {
            "component": "arm angles: encoder zeros",
            "type": "B",
            "size": "not measured (no arm-offsets file, no geometry.axis_zero_sigma_deg): "
            "mounting errors of a few 0.1° are usual",
            "propagated": False,
        }
    zero.update(sigma_deg=sig, kinematics=preset)
    if sig is not None:
        zero["size"] = ", ".join(f"{k} {v:.3g}°" for k, v in sig.items())
    geo = rig.geometry
    play = {"component": "arm angles: gear backlash and arm sag", "type": "B", "sigma_deg": None}
    if geo.backlash_deg is None and geo.arm_sag_deg is None:
        play.update(size="not assessed (Dynamixel X-series backlash ~0.25° per joint)",
                    propagated=False)  # fmt: skip
    else:
        play.update(
            play_deg=geo.backlash_deg,
            sag_sigma_deg=geo.arm_sag_deg,
            kinematics=preset,
            size=", ".join(
                f"{label} {v:.3g}°"
                for label, v in (("play", geo.backlash_deg), ("sag σ", geo.arm_sag_deg))
                if v is not None
            ),
        )
    for comp in (zero, play):
        comp.update(relative_sigma=None, shared_by="every sample of a pose (and of the run)")
    return [zero, play]


def _budget_components(
    rig: RigConfig, scale: _Scale, arm_offsets: dict | None, cal: RunCalibration | None = None
) -> list[dict]:
    """The uncertainty budget of the samples (GUM style): each component with its type (A:
    from these data's scatter, B: from elsewhere, e.g. a certificate), its size and what it is
    shared by. Only the statistical one is in the `sigma` column; a shared component is one
    error for all the samples it names and must never be averaged as if independent."""
    chans = ["R", "G", "B"]
    budget = [
        {
            "component": "statistical (photon, read, dark, flat noise)",
            "type": "A",
            "relative_sigma": None,
            "size": "per sample: the sigma column",
            "shared_by": "none (independent per sample)",
        }
    ]
    if scale.method == "reference" and scale.reference is not None:
        ref = scale.reference.describe()
        rel = dict(zip(ref["channels"], ref["rel_sigma"], strict=False))
        budget.append(
            {
                "component": "scale (reference target: its certificate and the fit of k)",
                "type": "A+B",
                "relative_sigma": rel,
                "size": ", ".join(f"{c} {100 * v:.3g} %" for c, v in rel.items()),
                "shared_by": "every sample of a channel (the whole run)",
            }
        )
    elif scale.absolute:
        rel_cert = rig.light.intensity_rel_sigma
        budget.append(
            {
                "component": "scale (lamp intensity certificate)",
                "type": "B",
                "relative_sigma": None if rel_cert is None else dict.fromkeys(chans, rel_cert),
                "size": "not stated in the rig file (light.intensity_rel_sigma)"
                if rel_cert is None
                else f"{100 * rel_cert:.3g} %",
                "shared_by": "every sample of a channel (the whole run)",
            }
        )
    if scale.absolute and rig.geometry.light_distance_sigma_m is not None:
        # E = I cos θ_i / r²: a distance error δ scales every f by (r/(r+δ))² ≈ 1 − 2δ/r, one
        # error for the run. Not with a reference target, measured at the same lamp distance:
        # its scale absorbs the distance.
        rel = 2.0 * rig.geometry.light_distance_sigma_m / rig.geometry.light_distance_m
        budget.append(
            {
                "component": "scale (lamp distance: 2σ_r/r)",
                "type": "B",
                "relative_sigma": dict.fromkeys(chans, rel),
                "size": f"{100 * rel:.3g} % (σ_r {1e3 * rig.geometry.light_distance_sigma_m:.3g}"
                f" mm at r = {rig.geometry.light_distance_m:g} m)",
                "shared_by": "every sample of the run (all channels alike)",
                # for a fit that carries the distance itself (fitting.nuisance: the lamp's
                # direction and 1/r² per pixel move with it, not only the scale)
                "light_distance_sigma_m": rig.geometry.light_distance_sigma_m,
            }
        )
    linearity = None if cal is None else cal.linearity
    le = rig.camera.linearity_error
    size = (
        "not stated in the rig file (camera.linearity_error)"
        if le is None
        else f"up to {100 * le:.3g} % of f (the datasheet's linearity error)"
    )
    if linearity is not None:  # measured from this run's brackets (calibration.linearity)
        size = f"{linearity.words()}; datasheet: {size}"
    budget.append(
        {
            "component": "linearity (camera response, EMVA 1288)",
            "type": "A+B" if linearity is not None else "B",
            # Not a scale: the error depends on each sample's signal level (bright and dim
            # samples are bent differently), so it is named, never folded into the scale.
            "relative_sigma": None,
            "size": size,
            "shared_by": "every sample of similar signal level (the whole run)",
            "propagated": False,
            **({} if linearity is None else {"measured": linearity.describe()}),
        }
    )
    budget += _arm_components(rig, arm_offsets) + [_bow_component(rig), _camera_distance(rig)]
    budget.append(_ambient_component(rig, scale))
    if cal is not None and cal.flat is not None:
        budget.append(_flat_source_component(rig, cal))
    return budget


def _nuisance_component(name: str, shared_by: str, sigma, unstated: str, stated) -> dict:
    """A shared error the fit carries as a nuisance when the rig states its size: the budget's
    row, with ``stated()`` (the size's words and what the fit needs) merged in, or named as
    left out of every interval (``unstated``, the rig key and a typical size) when it does not."""
    comp: dict = {
        "component": name,
        "type": "B",
        "relative_sigma": None,
        "sigma_deg": None,
        "shared_by": shared_by,
    }
    if sigma is None:
        comp.update(size=f"not stated in the rig file ({unstated}", propagated=False)
    else:
        comp.update(stated())
    return comp


def _bow_component(rig: RigConfig) -> dict:
    """The sample's bow (rig ``sample.bow_sigma_m``): a dome h = s (1 − (x² + y²)/R²) over the
    half side R leans the normal at (x, y) by the slope −2 s (x, y)/R², one error for every
    sample seen at that place on the sample. A fit that knows where each sample lies on the
    sample (the arms' positions, gonio.arm_poses) carries s as a nuisance (fitting.nuisance)."""
    sigma, half = rig.sample.bow_sigma_m, 0.5 * rig.sample.size_m
    return _nuisance_component(
        "sample flatness (bow)",
        "every sample at the same place on the sample (the whole run)",
        sigma,
        "sample.bow_sigma_m): a sheet curls 0.1–1 mm over 50 mm, a lapped tile ~10 µm",
        lambda: {
            "bow_sigma_m": sigma,
            "half_side_m": half,
            "size": f"sagitta σ {1e3 * sigma:.3g} mm over a {1e3 * half:.3g} mm half side "
            f"(edge slope {math.degrees(2.0 * sigma / half):.2g}°)",
        },
    )


def _ambient_component(rig: RigConfig, scale: _Scale) -> dict:
    """Light the lamp does not cause: radiance L_a A(ω_o) from the sample (A its directional
    albedo, ≤ 1), which calibration divides by the lamp's irradiance I cos θ_i / r² like the
    lamp's own, so every f carries an additive L_a A r² / (I cos θ_i). With the rig's
    ``light.ambient_sigma_W_m2_sr`` the fit carries L_a A as a nuisance; the per-channel I
    (W/sr, or the reference target's k) it needs is written here."""
    sigma = rig.light.ambient_sigma_W_m2_sr
    return _nuisance_component(
        "ambient light (not from the lamp)",
        "every sample (an offset, largest relative to f where f is small)",
        sigma,
        "light.ambient_sigma_W_m2_sr): a dark lab with black curtains ~5e-4 W m⁻² sr⁻¹, "
        "~0.1 % of a diffuse f",
        lambda: {
            "ambient_sigma_W_m2_sr": sigma,
            "intensity_W_sr": dict(zip("RGB", (float(v) for v in scale.intensity), strict=False)),
            "size": f"σ {sigma:.3g} W m⁻² sr⁻¹ (times the sample's albedo ≤ 1)",
        },
    )


def _camera_distance(rig: RigConfig) -> dict:
    """The camera's distance to its entrance pupil: each pixel's ray traced from the wrong
    point meets the sample elsewhere, where the lamp's irradiance differs (≤ 0.1 % of f for
    5 mm at 0.5 m). Carried as a nuisance by a fit that knows the arms' positions."""
    sigma = rig.geometry.camera_distance_sigma_m
    return _nuisance_component(
        "camera distance (entrance pupil)",
        "every sample of the run",
        sigma,
        "geometry.camera_distance_sigma_m): a pupil inside a lens is known to ~5–10 mm "
        "without a measurement; its effect on f is ≲ 0.1 %",
        lambda: {
            "camera_distance_sigma_m": sigma,
            "size": f"σ {1e3 * sigma:.3g} mm at {rig.geometry.camera_distance_m:g} m",
        },
    )


def _flat_source_component(rig: RigConfig, cal: RunCalibration) -> dict:
    """The flat-field source's fall-off: the master flat carries the source's radiance profile
    1 − a ρ/ρ_corner (ρ the squared tangent of a pixel's field angle, the leading even term of
    any smooth profile about the optical axis), so every calibrated f is divided by it. With
    the rig's ``calibration.flat_source_falloff_sigma`` the fit carries a as a nuisance, ρ per
    row from its pixel and the intrinsics written here (lens distortion left out: it moves ρ
    by k₁ρ², a few % of a few %)."""
    sigma, intr = rig.calibration.flat_source_falloff_sigma, cal.intrinsics

    def stated() -> dict:
        corners = [(0.0, 0.0), (intr.width - 1.0, 0.0), (0.0, intr.height - 1.0),
                   (intr.width - 1.0, intr.height - 1.0)]  # fmt: skip
        r2_corner = max(((u - intr.cx) / intr.fx) ** 2 + ((v - intr.cy) / intr.fy) ** 2
                        for u, v in corners)  # fmt: skip
        return {
            "falloff_sigma": sigma,
            "field": {
                "cx": intr.cx,
                "cy": intr.cy,
                "fx": intr.fx,
                "fy": intr.fy,
                "r2_corner": r2_corner,
            },  # fmt: skip
            "size": f"σ {100 * sigma:.3g} % from the optical axis to the frame's corner",
        }

    return _nuisance_component(
        "flat field source (fall-off)",
        "every sample seen at the same place in the frame (the whole run)",
        sigma,
        "calibration.flat_source_falloff_sigma): an integrating sphere's port ≤ 1 %, LED "
        "panels 2–5 % centre to corner",
        stated,
    )


def _evidence(cal: RunCalibration, monitors: list[float]) -> dict:
    """What the report shows as calibration evidence: each master dark's mean level and
    temporal noise (DN), the flat field's spread, and the light monitor per pose."""
    darks, flat = cal.darks, cal.flat
    return {
        "dark": (
            {}
            if darks is None
            else {
                f"{t:g}": {
                    "frames": m.n_frames,
                    "mean_dn": float(np.mean(m.dn)),
                    "noise_dn": float(np.sqrt(m.temporal_var_dn2)),
                }
                for t, m in sorted(darks.masters.items())
            }
        ),
        "flat": (
            None
            if flat is None
            else {
                "frames": flat.n_frames,
                "gain_min": float(np.nanmin(flat.gain)),
                "gain_max": float(np.nanmax(flat.gain)),
                "gain_sd": float(np.nanstd(flat.gain)),
            }
        ),
        "monitor_per_pose": [float(m) for m in monitors],
    }


def _metadata(
    cal: RunCalibration, rig: RigConfig, scale: _Scale, skipped: list, monitors: list[float]
) -> dict:
    options, darks, flat = cal.options, cal.darks, cal.flat
    notes = []
    if rig.light.manual:
        notes.append("the lamp was switched by hand (no monitor): its drift is uncorrected")
    if not scale.absolute:
        notes.append("values are relative (no certified intensity or quantum efficiency)")
    calib = {
        "version": CALIBRATION_VERSION,
        "run": str(cal.run_dir.name),
        "bin_px": options.bin_px,
        "radiometry": scale.method,
        "method": (
            "reference target: k = L_ref/(f_ref cos(theta_i)/r^2), "
            "f = L/(k cos(theta_i)/r^2); sigma statistical only, sigma_k in gonio.budget"
            if scale.method == "reference"
            else "camera irradiance equation, point source E = I cos(theta_i)/r^2"
        ),
        "intensity_W_sr": np.asarray(scale.intensity).tolist() if scale.absolute else None,
        "reference": None if scale.reference is None else scale.reference.describe(),
        "segment": options.segment,
        "mode": options.mode,
        # The DARK rule (f/σ below it), so a fit can censor at the same detection limit.
        "min_snr": options.min_snr,
        "dark": (
            None
            if darks is None
            else {f"{t:g}": m.n_frames for t, m in sorted(darks.masters.items())}
        ),
        "flat": None if flat is None else {"frames": flat.n_frames},
        "intrinsics": {
            "fx": cal.intrinsics.fx,
            "fy": cal.intrinsics.fy,
            "cx": cal.intrinsics.cx,
            "cy": cal.intrinsics.cy,
            "dist": list(cal.intrinsics.dist),
        },
        "arm_offsets_rad": dict(cal.geometry.offsets_rad),
        "light_drift_corrected": options.light_monitor and not rig.light.manual,
        "notes": notes,
        "evidence": _evidence(cal, monitors),
    }
    texels = {}
    if options.texel_mm:
        calib["texel_mm"] = options.texel_mm
        texels = TexelGrid(options.texel_mm * 1e-3, cal.sample_size_m).metadata()
    return {
        **texels,
        "gonio.absolute": "true" if scale.absolute else "false",
        "gonio.calibration": json.dumps(calib),
        "gonio.skipped_captures": json.dumps({"count": len(skipped), "captures": skipped}),
    }


def _decode_pose(recs, run_dir, skipped, strict: bool):
    """Decode a pose's brackets, each checked against its manifest SHA-256; a frame that cannot
    be decoded or does not match is skipped and recorded (`strict`: a mismatch stops)."""
    good, decoded = [], []
    for r in recs:
        try:
            decoded.append(decode_frame(run_dir / r.frame_path, r.sha256))
            good.append(r)
        except FrameIntegrityError as exc:
            if strict:
                raise CalibrationError(f"{exc} (--strict)") from None
            skipped.append({"capture_id": int(r.id), "frame": r.frame_path, "reason": str(exc)})
        except FrameError as exc:
            skipped.append({"capture_id": int(r.id), "frame": r.frame_path, "reason": str(exc)})
    return good, decoded


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


def _reference_scale(cal: RunCalibration, refs, level) -> ReferenceScale:
    """Effective intensity per channel from the reference-target captures (calibration.reference):
    per pose the mean over on-target pixels of L̃/(f_ref cos θ_i/r²), divided by the monitor's
    relative reading at that pose, then combined over poses; the certificate's own relative
    σ is added in quadrature (it is common to every pose)."""
    target = load_reference_target(cal.run_dir)
    size_m = target.size_m or cal.sample_size_m
    lut = {"R": 0, "G": 1, "B": 2}
    per_pose: list[dict] = []
    names: list[str] | None = None
    for pose, entries in sorted(refs.items()):
        entries = sorted(entries, key=lambda e: float(e["exposure_s"]))
        decoded = [decode_frame(Path(cal.run_dir) / e["path"], e.get("sha256")) for e in entries]
        exposures = [float(e["exposure_s"]) for e in entries]
        axes = {k: float(v) for k, v in entries[0]["axes_rad"].items()}
        planes, seg = pose_planes(cal, decoded, exposures, axes, size_m)
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
            scale = cal.radiometry.radiance_per_electron_rate / pl.sites
            e_geom = surface_irradiance(1.0, wi[:, 2], pl.geo.light_distance_m[valid])
            k, sk = pixel_scale(pl.flux[valid] * scale, pl.var[valid] * scale**2, e_geom, f_ref)
            ks.append(k / monitor)
            ss.append(sk / monitor)
        names = [pl.name for pl in planes]
        per_pose.append({"pose": pose, "k_W_sr": ks, "sigma_W_sr": ss})
    k_all = np.array([p["k_W_sr"] for p in per_pose])
    s_all = np.array([p["sigma_W_sr"] for p in per_pose])
    res = [combine_scales(k_all[:, c], s_all[:, c]) for c in range(k_all.shape[1])]
    k = np.array([r[0] for r in res])
    sigma = np.hypot(np.array([r[1] for r in res]), k * target.rel_sigma)
    return ReferenceScale(
        channels=list(names or []),
        k=k,
        sigma=sigma,
        n_poses=len(per_pose),
        birge=np.array([r[2] for r in res]),
        per_pose=per_pose,
    )


def _arm_pose(cal: RunCalibration, rec) -> dict:  # CaptureRecord
    """A pose as the fit's arm-angle nuisances need it (fitting.nuisance): the arms' azimuths
    [φ light, φ camera] (the plane each elevation turns in, defined on the normal too, where a
    direction's own φ is not), the elevation axes' angles (sag ∝ their sine) and the commanded
    axes (for the approach direction, which sets the side of the gears' play)."""
    pose = cal.geometry.kinematics.pose(cal.geometry.true_axes(rec.axes_measured))
    cam_m, light_m, _rot = cal.geometry.positions(rec.axes_measured)
    return {
        "phi": [float(pose.phi_i), float(pose.phi_o)],
        "light_m": [float(v) for v in light_m],
        "camera_m": [float(v) for v in cam_m],
        "axis": {k: float(v) for k, v in rec.axes_measured.items() if k.endswith("_theta")},
        "commanded": {k: float(v) for k, v in rec.axes_commanded.items()},
        # recorded by the rig at capture time (acquisition.rig.Rig.approach); older runs: None
        "recorded": (rec.devices or {}).get("approach"),
    }


#: A commanded change smaller than this is no move (the servo keeps the side of its play).
_MOVE_RAD = math.radians(0.01)


def _with_approach(poses: dict[int, dict]) -> dict[str, dict]:
    """The poses keyed by capture id (as text), each with ``approach`` {axis: +1 | −1 | 0}: the
    side of the last move of that axis before the capture (a gear's play leaves the arm lagging
    it by half the play) — as the rig recorded it, or for older runs inferred from the
    commanded targets in capture order (0 before the first change: unknown)."""
    last: dict[str, float] = {}
    side: dict[str, int] = {}
    out = {}
    for cid in sorted(poses):
        pose = dict(poses[cid])
        commanded, recorded = pose.pop("commanded"), pose.pop("recorded")
        for axis, target in commanded.items():
            if axis in last and abs(target - last[axis]) > _MOVE_RAD:
                side[axis] = 1 if target > last[axis] else -1
            last[axis] = target
        if isinstance(recorded, dict):  # the rig's own record: every move, the first too
            pose["approach"] = {axis: int(recorded.get(axis, 0)) for axis in commanded}
        else:
            pose["approach"] = {axis: side.get(axis, 0) for axis in commanded}
        out[str(cid)] = pose
    return out


def _reduce_pose(cal: RunCalibration, recs, decoded, intensity) -> Iterator[dict[str, np.ndarray]]:
    """The samples of one pose, one dict of columns per colour plane."""
    exposures = [r.exposure_taken_s for r in recs]  # what each frame had, not what was asked
    planes, seg = pose_planes(cal, decoded, exposures, recs[0].axes_measured)
    k_rad = cal.radiometry.radiance_per_electron_rate
    for c, pl in enumerate(planes):
        pl, off_image, b = _select(pl, seg, cal.options)
        scale = k_rad / pl.sites  # summed greens count twice the photosite area
        if pl.name != "Y":
            i_c = float(intensity[min(c, len(intensity) - 1)])
        else:
            i_c = float(np.mean(intensity))
        reg = region_means(pl, off_image, b, scale, i_c)
        if reg is None:
            continue
        wi = reg.wi / np.linalg.norm(reg.wi, axis=-1, keepdims=True)
        wo = reg.wo / np.linalg.norm(reg.wo, axis=-1, keepdims=True)
        ti, pi = vector_to_spherical(wi)
        to, po = vector_to_spherical(wo)
        px = (reg.cols * b + (b - 1) / 2.0) * pl.step + pl.offset + pl.origin[0]
        py = (reg.rows * b + (b - 1) / 2.0) * pl.step + pl.offset + pl.origin[1]
        f_reg = reg.f
        # Statistical σ only (photon, read and dark noise, flat-field noise). The scale's σ is
        # one error shared by every sample of the channel: in quadrature here it would average
        # away as 1/√N in kd and ks, so it goes to the budget (gonio.budget) instead and the
        # fit carries it as a shared component (fitting.budget).
        sigma_reg = np.sqrt(reg.var_f / (b * b))
        flags = np.zeros(f_reg.shape, np.int32)
        flags[reg.saturated] |= Flags.SATURATED
        flags[reg.masked] |= Flags.MASKED
        with np.errstate(divide="ignore", invalid="ignore"):
            snr = f_reg / sigma_reg
        flags[~(snr >= cal.options.min_snr)] |= Flags.DARK
        n = f_reg.shape[0]
        piece = {
            "theta_i": ti,
            "phi_i": pi,
            "theta_o": to,
            "phi_o": po,
            "channel": np.full(n, pl.name, dtype=object),
            "f": f_reg,
            "sigma": sigma_reg,
            "flags": flags,
            "capture_id": np.full(n, recs[0].id, dtype=np.int64),
            "pixel_x": np.round(px).astype(np.int32),
            "pixel_y": np.round(py).astype(np.int32),
        }
        if cal.options.texel_mm:
            grid = TexelGrid(cal.options.texel_mm * 1e-3, cal.sample_size_m)
            piece["texel"] = grid.index(reg.point_m).astype(np.int32)
        if cal.linearity is not None:  # the camera's remaining bend scales with it (linearity)
            piece["bend_level"] = _region_level(cal, pl, exposures, reg, b).astype(np.float32)
        yield piece


def _region_level(cal: RunCalibration, pl, exposures: list, reg, b: int) -> np.ndarray:
    """Each region's mean bend_level (calibration.linearity) over its b × b pixels, each pixel's
    level read from the regions around its own (`_around`), never from the region's pixels.

    Why: the level multiplies the model in the fit (1 + b · level, fitting.nuisance), and a
    level read from the sample's own flux carries the sample's noise — an upward fluctuation
    raises both f and its level — so the fit found a bend in noise alone. On the demo (67k
    samples, a straight camera) the bend's posterior sat at +0.04 ± 0.02 % in noisy runs and at
    0.00 without sensor noise, and it took m 1.2 of its half-widths low on average over six
    seeds (one of them outside its 95 % interval). Read from the regions around, the bend's
    posterior is 0.00 ± 0.02 % and m's error −0.5 half-widths on average over the same seeds
    (sd 0.7; seed 7 −2.2 → −1.5)."""
    gain = cal.radiometry.gain_e_per_dn
    flux = pl.flux / pl.sites
    h, w = flux.shape[0] // b, flux.shape[1] // b

    def blocks(a: np.ndarray) -> np.ndarray:
        return a[: h * b, : w * b].reshape(h, b, w, b).mean(axis=(1, 3))

    own = blocks(flux)
    usable = (
        np.isfinite(own)
        & (blocks(pl.all_sat.astype(np.float64)) == 0.0)
        & (blocks(pl.geo.on_sample.astype(np.float64)) == 1.0)
    )
    level = bend_level(_around(own, usable, b), exposures,
                       [bracket_noise_e(cal, t) for t in exposures],
                       cal.linearity.clip_dn * gain)  # fmt: skip
    return level.reshape(h, b, w, b).mean(axis=(1, 3))[reg.rows, reg.cols]


#: The eight neighbours of a region (row, column offsets, in regions).
_RING = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1))
#: Least squares of c + g_x x + g_y y + a x² + e x y + d y² through the eight (exact for any
#: quadratic surface: six unknowns, eight points, a unique solution).
_QUADRATIC = np.linalg.pinv(np.array([[1, x, y, x * x, x * y, y * y] for y, x in _RING], float))


def _around(own: np.ndarray, usable: np.ndarray, b: int) -> np.ndarray:
    """Each pixel's flux (an (h b, w b) image) estimated from the eight regions around its own:
    the quadratic surface through their means, evaluated at the pixel's place in its region —
    exact where the flux is quadratic over the three regions, where the plain mean of the eight
    is off by 3 (φ_xx + φ_yy) h²/8, and per pixel, so that a region half of whose pixels the
    merge read from another bracket gets the mean of their levels (the level jumps where a
    bracket clips). Where a neighbour is missing, the mean of those there, uniform over the
    region (calibration.hdr.local_mean); where none is, the region's own mean."""
    h, w = own.shape
    pad = np.pad(np.where(usable, own, 0.0), 1)
    ok = np.pad(usable, 1)
    ring = np.stack([pad[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy, dx in _RING])
    every = np.all([ok[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy, dx in _RING], axis=0)
    c = np.tensordot(_QUADRATIC, ring, axes=1)  # (6, h, w)
    u = (np.arange(b) - (b - 1) / 2.0) / b  # the pixel's offset from its region's centre
    x, y = u[None, None, None, :], u[None, :, None, None]
    surface = (c[0][:, None, :, None] + c[1][:, None, :, None] * x + c[2][:, None, :, None] * y
               + c[3][:, None, :, None] * x * x + c[4][:, None, :, None] * x * y
               + c[5][:, None, :, None] * y * y)  # fmt: skip
    mean = local_mean(np.where(usable, own, 0.0), usable, cfa=False)
    fallback = np.where(np.isfinite(mean), mean, own)[:, None, :, None]
    out = np.where(every[:, None, :, None], surface, fallback)
    return np.maximum(np.nan_to_num(out, nan=0.0), 0.0).reshape(h * b, w * b)


def _select(pl, seg, options):
    """(plane, off-image mask, bin) for the reduction mode: "center" keeps the pixel nearest
    each region's centre and treats it as a 1×1 region; "mean" keeps the plane as is."""
    off_image = np.zeros(pl.flux.shape, bool) if seg is None else ~seg
    b = options.bin_px
    if options.mode != "center" or b <= 1:
        return pl, off_image, b
    geo = pl.geo
    h, w = geo.on_sample.shape[0] // b, geo.on_sample.shape[1] // b
    m = b // 2

    def pick(a):
        return a[m::b, m::b][:h, :w]

    geo = type(geo)(
        *(pick(a) for a in (geo.point_m, geo.wi, geo.wo, geo.light_distance_m, geo.on_sample))
    )
    picked = Plane(
        pl.name,
        pick(pl.flux),
        pick(pl.var),
        pick(pl.all_sat),
        geo,
        pl.offset + m * pl.step,
        pl.step * b,
        pl.sites,
        pl.origin,
    )
    return picked, pick(off_image), 1

"""End-to-end orchestration: acquire → calibrate → fit → report, for the CLI and the demo."""

from __future__ import annotations

import datetime as _dt
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w
from pydantic import ValidationError
from rich.console import Console

from acquisition.config import (
    PlanConfig,
    RigConfig,
    format_validation_error,
    load_plan,
    load_rig,
)
from acquisition.exposure import exposure_ladder
from acquisition.plans import build_plan, lab_time_estimate
from acquisition.protocols import Frame
from acquisition.rig import build_rig
from acquisition.runner import RunOutcome, fmt_duration, run_acquisition, stop_requests
from acquisition.store import RunStore
from fitting.atomic import atomic_write_bytes
from gonio.backends import prepare_backends
from gonio.errors import UserError

__all__ = [
    "acquire",
    "AcquireResult",
    "config_dir",
    "Timings",
    "demo",
    "sample_levels_decoder",
    "plan_exposures_s",
]

console = Console(stderr=True)


def config_dir() -> Path:
    """`configs/` of the working directory if present, else the one beside the package."""
    here = Path.cwd() / "configs"
    if here.is_dir():
        return here
    return Path(__file__).resolve().parent.parent / "configs"


def _version() -> str:
    from importlib.metadata import version

    try:
        return version("gonio")
    except Exception:  # running from a source tree without an install
        return "0+unknown"


def _clean(d: Any) -> Any:
    """TOML has no null: drop None values recursively."""
    if isinstance(d, dict):
        return {k: _clean(v) for k, v in d.items() if v is not None}
    if isinstance(d, list | tuple):
        return [_clean(v) for v in d]
    return d


@dataclass
class AcquireResult:
    run_dir: Path
    outcome: RunOutcome
    resumed: bool
    compute_s: float
    lab_estimate_s: float
    extra: dict[str, Any] = field(default_factory=dict)


def acquire(
    rig_path: Path | str | None,
    plan_path: Path | str | None,
    out: Path | str,
    *,
    scene_path: Path | str | None = None,
    progress: bool = True,
    rig_config: RigConfig | None = None,
    plan_config: PlanConfig | None = None,
    scene_config: Any | None = None,
    announce: bool = True,
) -> AcquireResult:
    """Start a run in `out`, or resume it when `out` holds an incomplete run."""
    out = Path(out)
    t0 = time.perf_counter()
    resumed = (out / "manifest.sqlite").exists()
    scene: Any = None
    if resumed:
        store = RunStore.open(out, writable=True)
        frozen = store.run_config()
        try:
            rig = RigConfig.model_validate(frozen["rig"])
            plan_cfg = PlanConfig.model_validate(frozen["plan"])
        except KeyError as exc:
            raise UserError(f"{out}/run.toml: missing section [{exc.args[0]}]") from None
        except ValidationError as err:
            raise UserError(format_validation_error(out / "run.toml", err)) from None
        scene = frozen.get("scene")
        console.print(f"resuming {out}: {store.count('done')} capture(s) already done")
    else:
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise UserError(f"{out}: exists and is not a gonio run; choose a new --out directory")
        rig = rig_config or load_rig(_need(rig_path, "--rig"))
        plan_cfg = plan_config or load_plan(_need(plan_path, "--plan"))
        if scene_config is not None:
            scene = scene_config
        elif scene_path is not None:
            from simulator.scene import load_scene

            scene = load_scene(scene_path)
        store = None
    world = prepare_backends(rig, scene)
    plan = build_plan(rig, plan_cfg)
    estimate = lab_time_estimate(rig, plan_cfg)
    lab_estimate = estimate.total_max_s
    auto = plan_cfg.exposure_mode == "auto"
    if announce:
        brackets = (
            f"auto-exposure (≤ {plan_cfg.auto_exposure.max_brackets} frames/pose)"
            if auto
            else f"{len(plan_cfg.exposures_s)} exposure(s)"
        )
        bound = "at most " if auto else ""
        console.print(
            f"plan {plan_cfg.name}: {len(plan.poses)} poses × {brackets}, "
            f"{len(plan.skipped)} unreachable skipped; estimated lab time {bound}"
            f"{fmt_duration(estimate.phase1_s)} (moves {fmt_duration(plan.move_time_s)}, raster "
            f"order would be {fmt_duration(plan.raster_move_time_s)})"
        )
        if plan_cfg.type == "adaptive":
            console.print(
                f"adaptive: phase 2 refines around the peaks — at most "
                f"{estimate.refine_max_poses} poses, at most "
                f"{fmt_duration(estimate.phase2_max_s)}; total at most "
                f"{fmt_duration(estimate.total_max_s)}"
            )
    rig_dev = build_rig(rig)
    try:
        if store is None:
            doc = {
                "gonio": {
                    "version": _version(),
                    "started_at": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                },
                "rig": _clean(rig.model_dump(mode="json")),
                "plan": _clean(plan_cfg.model_dump(mode="json")),
                "camera": _clean(rig_dev.camera.describe()),
                "sample": {"size_m": _sample_size(world)},
            }
            if world is not None:
                doc["scene"] = _clean(world.scene.model_dump(mode="json"))
            store = RunStore.create(out, tomli_w.dumps(doc))
        if world is not None:
            _record_sim_calibration_frames(out, world, plan_exposures_s(plan_cfg))
        frozen_now = store.run_config()  # parsed once: camera and sample as frozen
        levels = sample_levels_decoder(
            frozen_now["camera"], rig, float(frozen_now["sample"]["size_m"])
        )
        with stop_requests() as flag:
            outcome = run_acquisition(
                store, rig_dev, plan, progress=progress, stop=flag, frame_levels=levels
            )
    finally:
        rig_dev.close()
        if store is not None:
            store.close()
    extra = {
        "lab_estimate": {
            "phase1_s": estimate.phase1_s,
            "phase2_max_s": estimate.phase2_max_s,
            "total_max_s": estimate.total_max_s,
            "is_upper_bound": auto or plan_cfg.type == "adaptive",
        },
        "phases": {
            "prescan_poses": outcome.prescan_poses,
            "refine_poses": outcome.refine_poses,
        },
    }
    return AcquireResult(out, outcome, resumed, time.perf_counter() - t0, lab_estimate, extra)


def plan_exposures_s(plan_cfg: PlanConfig) -> tuple[float, ...]:
    """Every exposure the plan may take: its brackets, or the auto-exposure ladder (what the
    master darks must cover)."""
    if plan_cfg.exposure_mode == "auto":
        return exposure_ladder(plan_cfg.auto_exposure)
    return tuple(plan_cfg.exposures_s)


def sample_levels_decoder(camera: dict[str, Any], rig: RigConfig, sample_size_m: float):
    """A `FrameLevels` for the runner: decode a frame (calibration.decode — the same decoder
    calibration uses) to linear levels, 0 at the black level and 1 at the camera's clip level
    (`white_level_dn` of its description, which can sit far below the ADC's white), and keep
    the pixels that see the sample: the sample square projected through the camera model at
    the measured arm angles (calibration.geometry.pixel_geometry). Without intrinsics in the
    description, the whole frame counts as the sample region."""
    import tempfile

    import numpy as np

    from acquisition.kinematics import Kinematics
    from calibration.decode import decode_frame
    from calibration.geometry import Intrinsics, pixel_geometry

    kin = Kinematics(rig)
    try:
        intr = Intrinsics.from_description(camera)
    except (KeyError, TypeError, ValueError):
        intr = None
    clip_dn = camera.get("white_level_dn")

    def levels(frame: Frame, axes_measured: dict[str, float]) -> np.ndarray:
        with tempfile.TemporaryDirectory(prefix="gonio-levels-") as tmp:
            path = Path(tmp) / f"frame{frame.suffix}"
            path.write_bytes(frame.data)
            d = decode_frame(path)
        black = np.asarray(d.black_level, dtype=np.float64)
        white = float(clip_dn) if clip_dn is not None else float(d.white_level)
        lv = (np.asarray(d.dn, dtype=np.float64) - black) / (white - black)
        if intr is None or (intr.height, intr.width) != lv.shape[:2]:
            return lv.ravel()
        on = pixel_geometry(
            intr,
            kin.camera_position_m(axes_measured),
            kin.light_position_m(axes_measured),
            sample_size_m,
        ).on_sample
        return lv[on].ravel()

    return levels


def _record_sim_calibration_frames(out: Path, world: Any, exposures_s: tuple[float, ...]) -> None:
    """Master darks (one set per exposure), a flat field and reference-target captures,
    recorded before the first pose as a lab would — only when the simulated sensor has an effect
    they correct (dark current, DSNU, PRNU, vignetting); a run that already has them (a resumed
    run) keeps its own."""
    from calibration.darks import calibration_frames, record_frames

    s = world.scene.sensor
    if not (s.vignetting or s.prnu > 0 or s.dark_current_e_s > 0 or s.dsnu_e > 0):
        return
    cam = world.camera
    if not calibration_frames(out, "dark"):
        record_frames(out, "dark", cam.capture_dark, list(exposures_s), 16)
    if not calibration_frames(out, "flat"):
        record_frames(out, "flat", cam.capture_flat, [max(exposures_s)], 32)
    if not calibration_frames(out, "reference"):
        # A Lambertian reference target at the standard poses (calibration.reference): with it
        # the reduction measures the light × camera scale instead of trusting certificates.
        from calibration.reference import record_reference_poses

        # Three brackets at most (shortest, middle, longest) span the HDR range; a long
        # auto-exposure ladder would only multiply the renders.
        ref_exposures = sorted(exposures_s)
        if len(ref_exposures) > 3:
            ref_exposures = [
                ref_exposures[0],
                ref_exposures[len(ref_exposures) // 2],
                ref_exposures[-1],
            ]
        record_reference_poses(
            out,
            lambda t, light_pos, cam_pos: cam.capture_reference(
                t, light_pos, cam_pos, level=world.rig.light.level
            ),
            world.kinematics,
            ref_exposures,
            level=world.rig.light.level,
        )


def _sample_size(world: Any) -> float:
    if world is not None:
        return float(world.scene.sample.size_m)
    raise UserError("a real rig must state the sample size (not supported yet in this version)")


def _need(value: Path | str | None, flag: str) -> Path:
    if value is None:
        raise UserError(f"{flag} is required when starting a new run")
    return Path(value)


@dataclass
class Timings:
    stages_s: dict[str, float] = field(default_factory=dict)


def demo(out: Path | None, scene_path: Path | None, quick: bool, progress: bool = True) -> Path:
    """Simulated acquisition → calibration → fit → report into `out`; returns the report path."""
    from calibration.reduce import ReduceOptions, reduce_run
    from fitting.export import write_material_xml
    from fitting.fit import fit_samples
    from gonio.report import write_report

    cfg = config_dir()
    if out is None:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        out = Path("runs") / f"demo-{stamp}"
    timings: dict[str, float] = {}
    t = time.perf_counter()
    res = acquire(
        cfg / "rigs" / "sim.toml",
        cfg / "plans" / "demo.toml",
        out,
        scene_path=scene_path,
        progress=progress,
    )
    timings["acquire (simulate)"] = time.perf_counter() - t
    if not res.outcome.complete:
        raise UserError(f"acquisition stopped: {res.outcome.reason}")
    t = time.perf_counter()
    # One pixel per 2×2 region ("center"): exact per-pixel directions (no averaging bias) and
    # a quarter of the photons — enough samples (~67k) for the fit to stay quick.
    table = reduce_run(out, ReduceOptions(bin_px=2, mode="center"), progress=progress)
    timings["calibrate"] = time.perf_counter() - t
    t = time.perf_counter()
    demo_fit = _demo_fit_settings(quick)
    fit = fit_samples(table, out_dir=out, progress=progress, **demo_fit)
    timings["fit"] = time.perf_counter() - t
    # The fitted material for a renderer: built-in roughconductor/blendbsdf where exact.
    write_material_xml(fit, out / f"material-{demo_fit['model_name']}.xml")
    t = time.perf_counter()
    report = write_report(out, compute_times_s=timings)
    timings["report"] = time.perf_counter() - t
    # Kept beside the run so `gonio report` and benchmarks can show what each stage cost.
    atomic_write_bytes(out / "timings.json", (json.dumps(timings, indent=2) + "\n").encode())
    return report


def _demo_fit_settings(quick: bool) -> dict[str, Any]:
    """The seed's Torrance-Sparrow form f = kd/π + ks·D G F/(π cos θi cos θo) with its
    Beckmann D, plus a Lambertian term. Two options match what Mitsuba renders: the specular
    part is a perfect conductor (F ≡ 1, fresnel="none"), and Mitsuba shadows with the Smith G1
    in its rational form (shadowing="smith-rational"). With the seed's V-cavity G instead, m
    still comes back to 1e-4 but kd is biased by ~3e-4 relative — invisible in a lab, yet
    several σ at the simulator's noise level, so the truth would fall outside the 95% interval.
    """
    return {
        "model_name": "torrance-sparrow",
        "options": {"fresnel": "none", "shadowing": "smith-rational"},
        "shared": ("m",),
        "walkers": 32,
        "steps": 1500 if quick else 4000,
        "seed": 1,
    }

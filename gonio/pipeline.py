"""End-to-end orchestration: acquire → calibrate → fit → report, for the CLI and the demo."""

from __future__ import annotations

import datetime as _dt
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w
from rich.console import Console

from acquisition.config import PlanConfig, RigConfig, load_plan, load_rig
from acquisition.plans import build_plan
from acquisition.rig import build_rig
from acquisition.runner import RunOutcome, fmt_duration, run_acquisition, stop_requests
from acquisition.store import RunStore
from fitting.atomic import atomic_write_bytes
from gonio.backends import prepare_backends
from gonio.errors import UserError

__all__ = ["acquire", "AcquireResult", "config_dir", "Timings", "demo"]

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
        rig = RigConfig.model_validate(frozen["rig"])
        plan_cfg = PlanConfig.model_validate(frozen["plan"])
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
    lab_estimate = plan.lab_time_s(rig.camera.readout_s, rig.settle_s)
    if announce:
        console.print(
            f"plan {plan_cfg.name}: {len(plan.poses)} poses × "
            f"{len(plan_cfg.exposures_s)} exposure(s), {len(plan.skipped)} unreachable "
            f"skipped; estimated lab time "
            f"{fmt_duration(lab_estimate)} (moves {fmt_duration(plan.move_time_s)}, raster order "
            f"would be {fmt_duration(plan.raster_move_time_s)})"
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
            _record_sim_calibration_frames(out, world, plan_cfg.exposures_s)
        with stop_requests() as flag:
            outcome = run_acquisition(store, rig_dev, plan, progress=progress, stop=flag)
    finally:
        rig_dev.close()
        if store is not None:
            store.close()
    return AcquireResult(out, outcome, resumed, time.perf_counter() - t0, lab_estimate)


def _record_sim_calibration_frames(out: Path, world: Any, exposures_s: tuple[float, ...]) -> None:
    """Master darks (one set per exposure) and a flat field, recorded before the first pose as
    a lab would — only when the simulated sensor has an effect they correct (dark current,
    DSNU, PRNU, vignetting); a run that already has them (a resumed run) keeps its own."""
    from calibration.darks import calibration_frames, record_frames

    s = world.scene.sensor
    if not (s.vignetting or s.prnu > 0 or s.dark_current_e_s > 0 or s.dsnu_e > 0):
        return
    cam = world.camera
    if not calibration_frames(out, "dark"):
        record_frames(out, "dark", cam.capture_dark, list(exposures_s), 16)
    if not calibration_frames(out, "flat"):
        record_frames(out, "flat", cam.capture_flat, [max(exposures_s)], 32)


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

"""End-to-end orchestration: acquire → calibrate → fit → report, for the CLI and the demo."""

from __future__ import annotations

import datetime as _dt
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console

from acquisition.calibration_capture import check_calibration_plan
from acquisition.config import (
    PlanConfig,
    RigConfig,
    load_plan,
    load_rig,
)
from acquisition.operator import AutoOperator, ConsoleOperator, Operator
from acquisition.plans import build_plan, lab_time_estimate
from acquisition.protocols import Frame
from acquisition.rig import build_rig
from acquisition.run_document import RunDocument, device_difference
from acquisition.runner import RunOutcome, fmt_duration, run_acquisition, stop_requests
from acquisition.store import RunStore
from gonio import version
from gonio.backends import prepare_backends
from gonio.errors import UserError
from gonio.plain_text import printable
from plumbing.atomic import atomic_write_bytes
from plumbing.locks import RunLock

__all__ = [
    "acquire",
    "AcquireSpec",
    "capture_calibration",
    "AcquireResult",
    "config_dir",
    "demo",
    "demo_fit_options",
    "demo_fit_choice",
    "SpineSpec",
    "SpineResult",
    "run_spine",
    "sample_levels_decoder",
]

# Run paths, plan names and device strings are data: never parsed as rich markup.
console = Console(stderr=True, markup=False, highlight=False)


def config_dir() -> Path:
    """The shipped `configs/`: inside the installed package (a wheel), else the source tree's.
    Never the working directory's: a lab's own configs/ must not change what the demo runs."""
    here = Path(__file__).resolve().parent
    shipped = here / "configs"
    return shipped if shipped.is_dir() else here.parent / "configs"


@dataclass
class AcquireResult:
    run_dir: Path
    outcome: RunOutcome
    resumed: bool
    compute_s: float
    lab_estimate_s: float
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class AcquireSpec:
    """What `acquire` runs: the rig and plan (objects, or the paths of their files; both None
    to resume), the emulated world for a simulated rig (a Scene, its dict, or a scene file;
    None: the rig file's own scene), the operator for steps that need hands (None: asked on
    the console), a progress bar, and the plan's announcement."""

    rig: RigConfig | Path | str | None = None
    plan: PlanConfig | Path | str | None = None
    scene: Any | None = None
    operator: Operator | None = None
    progress: bool = True
    announce: bool = True

    def configs(self) -> tuple[RigConfig, PlanConfig, Any]:
        """(rig, plan, scene) for a new run, files loaded with one-line errors."""
        rig = self.rig if isinstance(self.rig, RigConfig) else load_rig(_need(self.rig, "--rig"))
        plan = self.plan
        if not isinstance(plan, PlanConfig):
            plan = load_plan(_need(plan, "--plan"))
        scene = self.scene
        if isinstance(scene, str | Path):
            from gonio.backends import load_scene

            scene = load_scene(scene)
        return rig, plan, scene


def _check_resume_rig(out: Path, frozen: RigConfig, given: RigConfig | Path | str | None) -> None:
    """A run directory is data: resuming it needs the rig file this machine trusts (--rig), and
    the run's frozen rig must name the same devices, camera backend and commands. Everything
    else (geometry, plan, scene) is the run's own, so the poses stay the ones it started with."""
    if given is None:
        raise UserError(
            f"resuming {out} needs --rig: the rig file of this instrument (a run directory never "
            "chooses the devices or commands it runs)"
        )
    trusted = given if isinstance(given, RigConfig) else load_rig(given)
    diff = device_difference(frozen, trusted)
    if diff is not None:
        where, theirs, ours = diff
        source = given if not isinstance(given, RigConfig) else "the rig given"
        raise UserError(
            f"{out}: the run's rig differs from {source} in {where} (run: {theirs!r}, rig "
            f"file: {ours!r}); a run resumes only on the devices and commands of the rig file "
            "it is given — check that this run is yours and give the rig file it was started with"
        )


def _check_resume_plan(out: Path, frozen: PlanConfig, given: PlanConfig | Path | str | None):
    """A run resumes with the plan it started with (frozen in its run.toml): a --plan that
    differs from it would be ignored without a word, so it is refused; the same plan, or none,
    resumes."""
    if given is None:
        return
    plan = given if isinstance(given, PlanConfig) else load_plan(given)
    theirs, ours = frozen.model_dump(), plan.model_dump()
    if theirs == ours:
        return
    key = next(k for k in theirs if theirs.get(k) != ours.get(k))
    source = given if not isinstance(given, PlanConfig) else "the plan given"
    raise UserError(
        f"{out}: the run's plan differs from {source} in {key} (run: {theirs[key]!r}, plan "
        f"file: {ours[key]!r}); a run resumes with the plan it started with — leave --plan out "
        "to resume it, or start that plan in a new --out directory"
    )


def acquire(out: Path | str, spec: AcquireSpec | None = None) -> AcquireResult:
    """Start a run in `out`, or resume it when `out` holds an incomplete run.

    The run records what the rig file says about the instrument (camera, sample, reference
    target, geometric calibration) into run.toml — what calibration will use — and takes the
    plan's calibration phases before its poses. The operator answers the steps that need
    hands; on a simulated rig the world performs what it confirms.
    """
    out = Path(out)
    spec = spec or AcquireSpec()
    t0 = time.perf_counter()
    resumed = (out / "manifest.sqlite").exists()
    store = None
    if resumed:
        store = RunStore.open(out, writable=True)
        try:
            frozen = RunDocument.of(store)
        except BaseException:
            store.close()
            raise
        rig, plan_cfg, scene = frozen.rig, frozen.plan, frozen.scene
        try:
            _check_resume_rig(out, rig, spec.rig)
            _check_resume_plan(out, plan_cfg, spec.plan)
        except BaseException:
            store.close()
            raise
    else:
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise UserError(f"{out}: exists and is not a gonio run; choose a new --out directory")
        rig, plan_cfg, scene = spec.configs()
    try:
        plan_name = str(spec.plan) if isinstance(spec.plan, str | Path) else "plan"
        check_calibration_plan(rig, plan_cfg, plan_name)
        world = prepare_backends(rig, scene)
        plan = build_plan(rig, plan_cfg)
        # One writer per run: a second `acquire --out RUN` (or a retake) is refused before it
        # opens a device or prints a plan, not let in to drive the same arms (plumbing.locks;
        # the kernel drops the lock if this process dies). Taken once the configs are known
        # good, so a refused command leaves nothing behind.
        out.parent.mkdir(parents=True, exist_ok=True)  # the run (and its lock) go in there
        lock = RunLock(out).acquire()
    except BaseException:
        if store is not None:
            store.close()
        raise
    try:
        if store is not None:
            done = store.count("done")
            console.print(f"resuming {printable(out)}: {done} capture(s) already done")
        estimate = lab_time_estimate(rig, plan_cfg, plan)
        if spec.announce:
            _announce(plan_cfg, plan, estimate)
        hands = ConsoleOperator() if spec.operator is None else spec.operator
        if world is not None:
            hands = world.hands(hands)
        outcome = _run(out, store, (rig, plan_cfg, plan), world, hands, spec.progress)
    finally:
        lock.release()
    auto = plan_cfg.exposure_mode == "auto"
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
    elapsed = time.perf_counter() - t0
    return AcquireResult(out, outcome, resumed, elapsed, estimate.total_max_s, extra)


def _run(out: Path, store, what, world, hands, progress: bool) -> RunOutcome:
    """Open the devices, freeze run.toml for a new run, and run the plan (always closing)."""
    rig, plan_cfg, plan = what
    rig_dev = build_rig(rig)
    try:
        if store is None:
            doc = RunDocument.new(
                rig,
                plan_cfg,
                version=version(),
                device=rig_dev.camera.describe(),
                scene=None if world is None else world.scene.model_dump(mode="json"),
            )
            store = RunStore.create(out, doc.toml())
        frozen = RunDocument.of(store)  # parsed once: camera and sample as frozen
        levels = sample_levels_decoder(frozen.camera, rig, float(frozen.sample["size_m"]))
        with stop_requests() as flag:
            return run_acquisition(
                store,
                rig_dev,
                plan,
                progress=progress,
                stop=flag,
                frame_levels=levels,
                operator=hands,
            )
    finally:
        rig_dev.close()
        if store is not None:
            store.close()


CAPTURE_KINDS = ("dark", "flat", "reference")


def capture_calibration(
    run_dir: Path | str,
    kind: str,
    *,
    rig_path: Path | str | None = None,
    rig_config: RigConfig | None = None,
    scene_path: Path | str | None = None,
    scene_config: Any | None = None,
    operator: Operator | None = None,
) -> int:
    """`gonio capture KIND RUN`: record a new take of darks, a flat or the reference target
    into an existing run (also a finished one); earlier takes stay on disk and in the manifest,
    and calibration uses the newest complete take. The phase settings are the run's plan's
    (or the defaults); the rig description is the rig file given (e.g. a new reference
    certificate). Returns the number of frames captured."""
    from acquisition.calibration_capture import CalibrationPhases
    from acquisition.config import (
        CalibrationPhasesConfig,
        DarkPhaseConfig,
        FlatPhaseConfig,
        ReferencePhaseConfig,
    )
    from acquisition.runlog import LOG_NAME, RunLog
    from acquisition.runner import safe_stop

    if kind not in CAPTURE_KINDS:
        raise UserError(f"capture: KIND must be one of {', '.join(CAPTURE_KINDS)} (got {kind!r})")
    run_dir = Path(run_dir)
    store = RunStore.open(run_dir, writable=True, calibration_only=True)
    try:
        lock = RunLock(run_dir).acquire()  # one writer per run (see acquire)
    except BaseException:
        store.close()
        raise
    try:
        plan_cfg = RunDocument.of(store).plan
        rig = rig_config or load_rig(_need(rig_path, "--rig"))
        phase = (
            getattr(plan_cfg.calibration, kind)
            or {
                "dark": DarkPhaseConfig,
                "flat": FlatPhaseConfig,
                "reference": ReferencePhaseConfig,
            }[kind]()
        )
        probe = plan_cfg.model_copy(
            update={"calibration": CalibrationPhasesConfig(**{kind: phase})}
        )
        check_calibration_plan(rig, probe, "the run's plan")
        scene = scene_config
        if scene is None and scene_path is not None:
            from gonio.backends import load_scene

            scene = load_scene(scene_path)
        world = prepare_backends(rig, scene)
        hands = ConsoleOperator() if operator is None else operator
        if world is not None:
            hands = world.hands(hands)
        rig_dev = build_rig(rig)
        log = RunLog(run_dir / LOG_NAME, rig_dev.clock.now)
        try:
            with stop_requests() as flag:
                phases = CalibrationPhases(
                    store, rig_dev, plan_cfg, hands, log.emit, lambda: bool(flag.reason)
                )
                ok = _capture_take(phases, kind, phase, rig_dev, rig)
                phases.ready_for_measurement()
            reason = f"capture {kind}: " + ("complete" if ok else f"stopped ({flag.reason})")
            safe_stop(rig_dev, store, reason, park=kind == "reference", log=log)
        except BaseException as exc:
            safe_stop(rig_dev, store, f"capture {kind}: {exc}", park=False, log=log)
            raise
        finally:
            log.close()
            rig_dev.close()
        if not ok:
            raise UserError(f"capture {kind} stopped ({flag.reason}); run it again to finish")
        return phases.captured
    finally:
        store.close()
        lock.release()


def _capture_take(phases: Any, kind: str, phase: Any, rig_dev: Any, rig: RigConfig) -> bool:
    """One new take of `kind`; the reference needs torque and the lamp (warmed up)."""
    if kind == "dark":
        return phases.dark(phase, new_take=True)
    if kind == "flat":
        return phases.flat(phase, new_take=True)
    rig_dev.torque(True)
    rig_dev.light.set_intensity(rig.light.level)
    if rig.light.manual:
        from acquisition.operator import ask, step

        ask(phases.operator, step("lamp_on", warmup_s=rig.light.warmup_s))
    rig_dev.light.on()
    if rig.light.warmup_s:
        rig_dev.clock.sleep(rig.light.warmup_s)
    return phases.reference(phase, new_take=True)


def _announce(plan_cfg: PlanConfig, plan: Any, estimate: Any) -> None:
    auto = plan_cfg.exposure_mode == "auto"
    brackets = (
        f"auto-exposure (≤ {plan_cfg.auto_exposure.max_brackets} frames/pose)"
        if auto
        else f"{len(plan_cfg.exposures_s)} exposure(s)"
    )
    bound = "at most " if auto else ""
    console.print(
        f"plan {printable(plan_cfg.name)}: {len(plan.poses)} poses × {brackets}, "
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
    if plan_cfg.type == "retro" and plan.retro_gap_deg is not None:
        console.print(
            f"retro-reflection: the camera gets within {plan.retro_gap_deg:.2f} deg of the light "
            "(the rig's min_separation_deg); the peak inside that gap is not measured"
        )
    cal = plan_cfg.calibration
    kinds = [k for k in ("dark", "flat", "reference") if getattr(cal, k) is not None]
    if kinds:
        console.print(f"calibration phases first: {', '.join(kinds)}")


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
            rotation=kin.camera_rotation(axes_measured),
            mask_only=True,
        ).on_sample
        return lv[on].ravel()

    return levels


def _need(value: Path | str | None, flag: str) -> Path:
    if value is None:
        raise UserError(f"{flag} is required when starting a new run")
    return Path(value)


@dataclass(frozen=True)
class SpineSpec:
    """One pass of the spine: acquire as `acquire` says (AcquireSpec), calibrate with `reduce`
    (calibration.reduce.ReduceOptions; None: the defaults) and fit with `fit`
    (fitting.fit.FitOptions; None: stop after calibration)."""

    acquire: AcquireSpec
    reduce: Any = None
    fit: Any = None


@dataclass
class SpineResult:
    run_dir: Path
    acquired: AcquireResult
    table: Any  # brdfdata.samples.SampleTable
    fit: Any  # fitting.result.FitResult | None
    timings_s: dict[str, float]  # wall seconds per stage: acquire, calibrate, fit
    lab_time_s: float  # on the rig's clock
    poses: int  # measured poses


def run_spine(run_dir: Path | str, spec: SpineSpec) -> SpineResult:
    """acquire → calibrate → fit, the one spine the demo, the studies and the benchmarks run."""
    from calibration.reduce import ReduceOptions, reduce_run
    from fitting.fit import fit_samples

    run_dir = Path(run_dir)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    res = acquire(run_dir, spec.acquire)
    timings["acquire"] = time.perf_counter() - t
    if not res.outcome.complete:
        raise UserError(f"{run_dir}: acquisition stopped: {res.outcome.reason}")
    t = time.perf_counter()
    progress = spec.acquire.progress
    table = reduce_run(run_dir, spec.reduce or ReduceOptions(), progress=progress)
    timings["calibrate"] = time.perf_counter() - t
    fit = None
    if spec.fit is not None:
        t = time.perf_counter()
        fit = fit_samples(table, spec.fit, out_dir=run_dir, progress=progress)
        timings["fit"] = time.perf_counter() - t
    with RunStore.open(run_dir) as store:
        lab = float(store.meta("lab_time_s") or "nan")
        poses = len({r.pose_index for r in store.captures("done")})
    return SpineResult(run_dir, res, table, fit, timings, lab, poses)


def demo(
    out: Path | None,
    scene_path: Path | None,
    quick: bool,
    progress: bool = True,
    seed: int | None = None,
) -> Path:
    """Simulated acquisition → calibration → fit → report into `out`; returns the report path.
    `seed`: another realization (the scene's noise seed and the fit's), None: the scene's."""
    from calibration.reduce import ReduceOptions
    from fitting.export import write_material_xml
    from gonio.report import write_report

    cfg = config_dir()
    if out is None:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        out = Path("runs") / f"demo-{stamp}"
    if (out / "manifest.sqlite").exists() or (out.exists() and any(Path(out).iterdir())):
        raise UserError(f"{out}: exists; choose a new --out directory for the demo")
    from gonio.backends import load_scene

    rig = load_rig(cfg / "rigs" / "sim.toml")
    scene = load_scene(scene_path) if scene_path is not None else None
    if seed is not None:
        scene = scene or load_scene(_need(rig.scene, "the rig's scene"))
        scene = scene.model_copy(update={"seed": int(seed)})
    # The model the fit uses is the one the scene's material is, when there is one.
    fit_opts, line = demo_fit_choice(
        scene if scene is not None else load_scene(_need(rig.scene, "the rig's scene")), quick
    )
    if seed is not None:
        fit_opts = fit_opts.replace(seed=int(seed))
    console.print(line, soft_wrap=True, markup=False)
    spec = SpineSpec(
        AcquireSpec(
            rig=rig,
            plan=load_plan(cfg / "plans" / "demo.toml"),
            scene=scene,
            operator=AutoOperator(),  # the simulated lab's hands do every calibration step
            progress=progress,
            announce=True,
        ),
        # One pixel per 2×2 region ("center"): exact per-pixel directions (no averaging bias)
        # and a quarter of the photons — enough samples (~67k) for the fit to stay quick.
        reduce=ReduceOptions(bin_px=2, mode="center"),
        fit=fit_opts,
    )
    res = run_spine(out, spec)
    timings = {
        "acquire (simulate)": res.timings_s["acquire"],
        "calibrate": res.timings_s["calibrate"],
        "fit": res.timings_s["fit"],
    }
    # The fitted material for a renderer: built-in roughconductor/blendbsdf where exact.
    write_material_xml(res.fit, out / f"material-{spec.fit.model}.xml")
    t = time.perf_counter()
    report = write_report(out, compute_times_s=timings)
    timings["report"] = time.perf_counter() - t
    # Kept beside the run so `gonio report` and benchmarks can show what each stage cost.
    atomic_write_bytes(out / "timings.json", (json.dumps(timings, indent=2) + "\n").encode())
    return report


def demo_fit_choice(scene: Any, quick: bool):  # FitOptions, str
    """(fit options, one line saying what is fitted) for the demo of `scene`: the model and
    options its material *is* (gonio.backends.scene_fit_model), else the demo's own model
    (demo_fit_options) with the statement that no parameter truth exists for the scene."""
    from gonio.backends import material_type, scene_fit_model

    base = demo_fit_options(quick)
    match = scene_fit_model(scene)
    if match is None:
        opts = ", ".join(f"{k}={v}" for k, v in base.model_options.items())
        return base, (
            f"demo: no model here represents the scene's material {material_type(scene)} "
            f"exactly; fitting {base.model} ({opts}) — no parameter truth exists for this scene"
        )
    chosen = base.replace(model=match["model"], model_options=dict(match["options"]))
    if match["model"] != "torrance-sparrow":
        chosen = chosen.replace(shared=None)  # the model's own default sharing
    opts = ", ".join(f"{k}={v}" for k, v in chosen.model_options.items()) or "no options"
    return chosen, (
        f"demo: the scene's material is {match['describe']}: fitting {chosen.model} ({opts})"
    )


def demo_fit_options(quick: bool):
    """The seed's Torrance-Sparrow form f = kd/π + ks·D G F/(π cos θi cos θo) with its
    Beckmann D, plus a Lambertian term. Two options match what Mitsuba renders: the specular
    part is a perfect conductor (F ≡ 1, fresnel="none"), and Mitsuba shadows with the Smith G1
    in its rational form (shadowing="smith-rational"). With the seed's V-cavity G instead, m
    still comes back to 1e-4 but kd is biased by ~3e-4 relative — invisible in a lab, yet
    several σ at the simulator's noise level, so the truth would fall outside the 95% interval.
    """
    from fitting.fit import FitOptions
    from fitting.mcmc import McmcOptions

    return FitOptions(
        model="torrance-sparrow",
        model_options={"fresnel": "none", "shadowing": "smith-rational"},
        shared=("m",),
        mcmc=McmcOptions(walkers=32, max_steps=1500 if quick else 4000),
        seed=1,
    )

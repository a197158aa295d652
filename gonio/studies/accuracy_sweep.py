"""The accuracy-vs-time sweep: every configuration through the one spine, one CSV row per fitted
parameter (the study: gonio/studies/__init__.py)."""

from __future__ import annotations

import dataclasses
import itertools
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from acquisition.config import PlanConfig
from gonio.studies.common import machine, read_typed_rows, sim_rig, write_rows
from plumbing.progress import Progress

__all__ = [
    "StudyConfig",
    "RunSpec",
    "run_sweep",
    "spp_ladder",
    "read_csv",
    "write_csv",
    "config_fields",
    "config_from_fields",
    "CSV_COLUMNS",
    "CSV_NAME",
    "RECORD_NAME",
    "MATERIALS",
    "PLANS",
    "ADAPTIVE_PLANS",
    "EXPOSURES",
]

CSV_NAME = "accuracy-vs-time.csv"
RECORD_NAME = "accuracy-vs-time.json"

# Two material characters: a broad, rough lobe and a sharp, glossy one (m ≈ 0.05).
MATERIALS: dict[str, dict[str, Any]] = {
    "rough": {"alpha": 0.30, "weight": 0.30, "reflectance": (0.50, 0.40, 0.30)},
    "glossy": {"alpha": 0.05, "weight": 0.30, "reflectance": (0.50, 0.40, 0.30)},
}


# Plan sizes: θ_i × θ_o × Δφ grids (isotropic plans; Δφ = 180° is the specular plane).
PLANS: dict[str, dict[str, tuple[float, ...]]] = {
    "grid-S": {
        "theta_i_deg": (25.0, 50.0),
        "theta_o_deg": (0.0, 20.0, 40.0, 60.0),
        "delta_phi_deg": (180.0, 120.0),
    },
    "grid-M": {
        "theta_i_deg": (20.0, 40.0, 60.0),
        "theta_o_deg": (0.0, 12.0, 24.0, 36.0, 48.0, 60.0, 72.0),
        "delta_phi_deg": (180.0, 150.0, 90.0),
    },
    "grid-L": {
        "theta_i_deg": (15.0, 30.0, 45.0, 60.0),
        "theta_o_deg": (0.0, 8.0, 16.0, 24.0, 32.0, 40.0, 48.0, 56.0, 64.0, 72.0),
        "delta_phi_deg": (180.0, 160.0, 135.0, 90.0),
    },
}


# Adaptive two-phase plans (acquisition.plans.refine_around_peak): a coarse pre-scan (one of the
# grids above), then a patch of fine poses around each incidence's brightest pose, ± span every
# step (θ_o and arc length in Δφ). The span is the pre-scan's θ_o spacing (20° for grid-S) so the
# true peak, somewhere between two coarse samples, lies inside the patch.
ADAPTIVE_PLANS: dict[str, dict[str, Any]] = {
    "adaptive-S": {"prescan": "grid-S", "refine_span_deg": 10.0, "refine_step_deg": 10.0},
    "adaptive-M": {"prescan": "grid-S", "refine_span_deg": 10.0, "refine_step_deg": 5.0},
    "adaptive-L": {"prescan": "grid-S", "refine_span_deg": 10.0, "refine_step_deg": 2.5},
}


# Exposure schemes (sensor noise level): a very short exposure (a few hundred electrons on the
# diffuse part: shot-noise limited, SNR ≈ 10–20 per pixel), a normal one, and a two-exposure
# HDR bracket that keeps the specular peak unsaturated and the diffuse part bright.
EXPOSURES: dict[str, tuple[float, ...]] = {
    "short": (0.0002,),
    "single": (0.002,),
    "bracket": (0.002, 0.016),
}


# The realistic rig's world: configs/scenes/<this>.toml (its lamp, drift and sensor), with the
# study's material and a fresh draw of the instrument budget's shared errors per seed.
REALISTIC_SCENE = "realistic"
# Seed of the Sobol' points the realistic rigs' errors are drawn from (every plan sees the
# same rigs, so the plans differ only in what they measure).
REALISTIC_DRAWS_SEED = 17

# The study's area-lamp variant of the base scene: the 10 mm disk of configs/scenes/effects.toml,
# with the base lamp's intensity (same far-field signal as the point lamp, see LightSpec).
AREA_LAMP_RADIUS_M = 0.005


CSV_COLUMNS = [
    "axis",
    "material",
    "plan",
    "plan_type",
    "poses",
    "refine_poses",
    "exposures",
    "mcmc_steps",
    "light",
    "spp",
    "planned_spp",
    "seed",
    "rig",
    "samples",
    "lab_time_s",
    "simulate_s",
    "calibrate_s",
    "fit_s",
    "compute_s",
    "param",
    "truth",
    "median",
    "rel_error",
    "half_width_68",
    "rel_half_width_68",
    "covered_68",
    "covered_95",
    "rel_sys_68",
]


_TEXT_COLUMNS = ("axis", "material", "plan", "plan_type", "exposures", "light", "param", "rig")


@dataclass(frozen=True)
class RunSpec:
    """One configuration of the sweep. `spp` None = what the effect planner derives."""

    axis: str  # "plan" | "mcmc" | "spp" | "adaptive": which side of the study it belongs to
    material: str
    plan: str
    exposures: str
    mcmc_steps: int
    light: str = "base"  # "base" = the base scene's lamp; "area" = the area-lamp variant
    spp: int | None = None
    rig: str = "ideal"  # "ideal": photon and sensor noise only; "realistic": REALISTIC_SCENE


@dataclass(frozen=True)
class StudyConfig:
    materials: tuple[str, ...] = ("rough", "glossy")
    plans: tuple[str, ...] = ("grid-S", "grid-M", "grid-L")
    exposures: tuple[str, ...] = ("short", "single", "bracket")
    mcmc_steps: tuple[int, ...] = (300, 1200)
    seeds: int = 3
    walkers: int = 24
    channel: str = "G"  # one channel keeps the study fast; the others behave alike
    # Render spp: swept on an area-lamp variant of the base scene, on this plan and exposure.
    spp_sweep: bool = True
    spp_plan: str = "grid-S"  # the smallest plan: the spp effect is per sample, renders cost
    spp_exposures: str = "single"
    # Adaptive vs grid: these adaptive plans, on these materials and exposure schemes.
    adaptive: tuple[str, ...] = ("adaptive-S", "adaptive-M", "adaptive-L")
    adaptive_materials: tuple[str, ...] = ("glossy",)
    adaptive_exposures: tuple[str, ...] = ("short",)
    # The realistic rig (REALISTIC_SCENE with the instrument budget's shared errors, a fresh
    # draw of them per seed: each seed is another rig): these plans, material and exposures,
    # `realistic_seeds` rigs, and MCMC long enough for the nuisance parameters (17 with G).
    # 32 rigs: coverage is a statement about rigs, and the issue asks it over ≥ 30 (binomial sd
    # of a 95 % coverage 0.039 at 32, against 0.077 at the 8 this study ran before).
    realistic_plans: tuple[str, ...] = ("grid-S", "grid-M", "grid-L")
    realistic_material: str = "rough"
    realistic_exposures: str = "bracket"
    realistic_seeds: int = 32
    realistic_steps: int = 600

    @classmethod
    def quick(cls, seeds: int | None = None) -> StudyConfig:
        # 8 realistic rigs keep the sweep within its 10 minutes (32 take ~16 min more);
        # `--quick --rigs 32` is the page's coverage run.
        return cls(mcmc_steps=(300, 1200), seeds=seeds or 3, realistic_seeds=8)


def _scene(base, material: str, seed: int, light: str = "base", spp: int | None = None):
    """The base scene with the study's material (Lambert + Beckmann lobe) and `light`."""
    from gonio.backends import blend_scene

    update: dict[str, Any] = {"seed": seed, "name": f"study-{material}"}
    if light == "area":
        update["area_light_radius_m"] = AREA_LAMP_RADIUS_M
    update["render"] = base.render.model_copy(update={"spp": spp})
    return blend_scene(base, MATERIALS[material], **update)


def spp_ladder(planned: int) -> list[int]:
    """spp values swept for a scene whose planner asks `planned` spp: 1, 4, 16, … (n = 1, 2, 4,
    … samples per side) up to half the planned value, then the planned value itself."""
    out, n = [], 1
    while n * n <= planned / 2:
        out.append(n * n)
        n *= 2
    return [*out, planned]


def _configurations(cfg: StudyConfig, base) -> list[RunSpec]:
    """The sweep: every plan × exposure at the shortest MCMC, plus every MCMC length on the
    middle plan with brackets (MCMC length does not change lab time, only compute time), the
    spp ladder on the area-lamp variant (only where the planner asks for more than 1 spp), the
    adaptive plans, and the plans on the realistic rig."""
    from gonio.backends import planned_spp

    runs = []
    short = min(cfg.mcmc_steps)
    for mat, plan, exp in itertools.product(cfg.materials, cfg.plans, cfg.exposures):
        runs.append(RunSpec("plan", mat, plan, exp, short))
    middle = cfg.plans[len(cfg.plans) // 2]
    for mat, steps in itertools.product(cfg.materials, cfg.mcmc_steps):
        if steps != short:
            runs.append(RunSpec("mcmc", mat, middle, "bracket", steps))
    if cfg.spp_sweep:
        for mat in cfg.materials:
            planned = planned_spp(_scene(base, mat, 0, "area"))
            if planned <= 1:
                continue  # the area lamp needs no spp here either: nothing to sweep
            for spp in spp_ladder(planned):
                runs.append(
                    RunSpec("spp", mat, cfg.spp_plan, cfg.spp_exposures, short, "area", spp)
                )
    for mat, plan, exp in itertools.product(
        cfg.adaptive_materials, cfg.adaptive, cfg.adaptive_exposures
    ):
        runs.append(RunSpec("adaptive", mat, plan, exp, short))
    for plan in cfg.realistic_plans:
        runs.append(
            RunSpec(
                "realistic",
                cfg.realistic_material,
                plan,
                cfg.realistic_exposures,
                cfg.realistic_steps,
                rig="realistic",
            )
        )
    return runs


def _plan_config(name: str, exposures: str) -> PlanConfig:
    if name in ADAPTIVE_PLANS:
        a = ADAPTIVE_PLANS[name]
        prescan = PlanConfig(name="prescan", type="isotropic", **PLANS[a["prescan"]])
        return PlanConfig(
            name=name,
            type="adaptive",
            prescan=prescan,
            refine_span_deg=a["refine_span_deg"],
            refine_step_deg=a["refine_step_deg"],
            exposures_s=EXPOSURES[exposures],
        )
    return PlanConfig(name=name, exposures_s=EXPOSURES[exposures], **PLANS[name])


def run_sweep(
    cfg: StudyConfig, *, scene_path: Path | None = None, progress: bool = True
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Every configuration × seed through the one spine (gonio.pipeline.run_spine): the rows,
    and the run record (configuration, machine at start and end, wall time)."""
    from gonio.backends import load_scene
    from gonio.pipeline import config_dir

    wall0 = time.perf_counter()
    record: dict[str, Any] = {"config": config_fields(cfg), "machine": {"start": machine()}}
    base = load_scene(scene_path or config_dir() / "scenes" / "demo.toml")
    rig = sim_rig()
    jobs = [
        (spec, seed)
        for spec in _configurations(cfg, base)
        for seed in range(cfg.realistic_seeds if spec.rig == "realistic" else cfg.seeds)
    ]
    rows: list[dict[str, Any]] = []
    with (
        tempfile.TemporaryDirectory() as tmp,
        Progress("study", len(jobs), enabled=progress) as bar,
    ):
        for k, (spec, seed) in enumerate(jobs):
            rows += _one_run(spec, seed, base, rig, cfg, Path(tmp) / f"run{k:04d}")
            bar.advance()
    if cfg.realistic_plans:
        record["realistic"] = _realistic_record(cfg, rig)
    record["machine"]["end"] = machine()
    record["machine"]["wall_s"] = time.perf_counter() - wall0
    return rows, record


def _one_run(spec: RunSpec, seed: int, base, rig, cfg: StudyConfig, run_dir: Path) -> list[dict]:
    """One configuration and seed: acquire → calibrate → fit, and a row per parameter."""
    from calibration.reduce import ReduceOptions
    from fitting.fit import FitOptions
    from fitting.mcmc import McmcOptions
    from gonio.backends import planned_spp
    from gonio.backends import scene_truth as reference_parameters
    from gonio.pipeline import AcquireSpec, SpineSpec, run_spine

    scene = _scene(base, spec.material, seed, spec.light, spec.spp)
    plan = _plan_config(spec.plan, spec.exposures)
    operator = None
    if spec.rig == "realistic":
        scene, rig, plan, operator = _realistic(spec, seed, cfg, rig, plan)
    truth = reference_parameters(scene)
    fit_opts = FitOptions(
        model="torrance-sparrow",
        model_options={"fresnel": "none", "shadowing": "smith-rational"},
        channels=[cfg.channel],
        mcmc=McmcOptions(walkers=cfg.walkers, max_steps=spec.mcmc_steps),
        seed=seed,
        n_starts=3,
    )
    res = run_spine(
        run_dir,
        SpineSpec(
            AcquireSpec(
                rig=rig,
                plan=plan,
                scene=scene,
                progress=False,
                announce=False,
                operator=operator,
            ),
            reduce=ReduceOptions(bin_px=4, mode="center"),
            fit=fit_opts,
        ),
    )
    fit = res.fit.to_dict()
    t = res.timings_s
    phases = res.acquired.extra.get("phases", {}) if res.acquired.extra else {}
    common = {
        "axis": spec.axis,
        "material": spec.material,
        "plan": spec.plan,
        "plan_type": "adaptive" if spec.plan in ADAPTIVE_PLANS else "grid",
        "poses": res.poses,
        "refine_poses": int(phases.get("refine_poses", 0)),
        "exposures": spec.exposures,
        "mcmc_steps": spec.mcmc_steps,
        "light": scene.light.type,
        "spp": planned_spp(scene),
        "planned_spp": planned_spp(_scene(base, spec.material, seed, spec.light)),
        "seed": seed,
        "rig": spec.rig,
        "samples": int(fit["n_samples"]) if fit.get("n_samples") else len(res.table),
        "lab_time_s": res.lab_time_s,
        "simulate_s": t["acquire"],
        "calibrate_s": t["calibrate"],
        "fit_s": t["fit"],
        "compute_s": t["acquire"] + t["calibrate"] + t["fit"],
    }
    rows = []
    for name, p in fit["parameters"].items():
        key = name if name in truth else f"{name}_{cfg.channel}"
        bare = name.rsplit("_", 1)[0]
        tv = truth.get(key, truth.get(f"{bare}_{cfg.channel}"))
        if tv is None or tv == 0:
            continue
        half = 0.5 * (p["p84"] - p["p16"])
        rows.append(
            {
                **common,
                "param": bare,
                "truth": tv,
                "median": p["median"],
                "rel_error": abs(p["median"] / tv - 1.0),
                "half_width_68": half,
                "rel_half_width_68": half / abs(tv),
                "covered_68": int(p["p16"] <= tv <= p["p84"]),
                "covered_95": int(p["p2.5"] <= tv <= p["p97.5"]),
                # The budget's systematic part of the 68 % half-width (fitting.nuisance:
                # split_uncertainty); 0 on the ideal rig, whose budget is empty.
                "rel_sys_68": float(p.get("sd_sys") or 0.0) / abs(tv),
            }
        )
    return rows


def _realistic(spec: RunSpec, seed: int, cfg: StudyConfig, rig, plan: PlanConfig):
    """Seed `seed`'s realistic rig: REALISTIC_SCENE with the study's material and a draw of the
    instrument budget's shared errors (the seed-th of `realistic_seeds` scrambled Sobol' points:
    simulator.instrument_draws.sobol_normal says why not a Latin hypercube),
    the rig file stating that budget, the plan with the darks and flat field a lab records,
    and an operator for the flat source."""
    from acquisition.config import CalibrationPhasesConfig, DarkPhaseConfig, FlatPhaseConfig
    from acquisition.operator import AutoOperator
    from gonio.backends import instrument_budget, load_scene, sobol_normal
    from gonio.pipeline import config_dir

    budget = instrument_budget()
    world = _scene(
        load_scene(config_dir() / "scenes" / f"{REALISTIC_SCENE}.toml"), spec.material, seed
    )
    z = sobol_normal(cfg.realistic_seeds, budget.N_DRAWS, REALISTIC_DRAWS_SEED)[seed]
    # Uncorrected, the realistic sensor's PRNU alone puts χ²/dof at 1.37 (tests/
    # test_coverage_realistic.py): a lab records darks and a flat field.
    phases = CalibrationPhasesConfig(dark=DarkPhaseConfig(count=8), flat=FlatPhaseConfig(count=16))
    return (
        budget.world(world, z, seed=4000 + seed),
        budget.rig(rig, lamp_radius_m=world.light.radius_m if world.light.type == "area" else 0.0),
        plan.model_copy(update={"calibration": phases}),
        AutoOperator(),
    )


def _realistic_record(cfg: StudyConfig, rig) -> dict[str, Any]:
    """What the page states of the realistic rig: its scene, the budget it draws from (and the
    rig file states), and the simulation stages a drawn world runs."""
    from gonio.backends import effect_names, instrument_budget

    spec = RunSpec("realistic", cfg.realistic_material, cfg.realistic_plans[0],
                   cfg.realistic_exposures, cfg.realistic_steps, rig="realistic")  # fmt: skip
    plan = _plan_config(spec.plan, spec.exposures)
    world, *_ = _realistic(spec, 0, cfg, rig, plan)
    return {
        "scene": REALISTIC_SCENE,
        "budget": instrument_budget().stated(),
        "stages": effect_names(world),
        "light": {
            "type": world.light.type,
            "radius_m": world.light.radius_m,
            "drift_per_hour": world.light.drift_per_hour,
        },  # fmt: skip
    }


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    write_rows(path, rows, CSV_COLUMNS)


_INT_COLUMNS = (
    "poses",
    "refine_poses",
    "mcmc_steps",
    "spp",
    "planned_spp",
    "seed",
    "samples",
    "covered_68",
    "covered_95",
)


#: Columns a CSV from before the realistic rig lacks, with what its rows were: the ideal rig,
#: no systematic part. Such a file still reads (and plans from its ideal rows).
_LATER_COLUMNS = {"rig": "ideal", "rel_sys_68": 0.0}


def read_csv(path: Path) -> list[dict[str, Any]]:
    """The rows as the sweep made them: text, integer and float columns."""
    required = [c for c in CSV_COLUMNS if c not in _LATER_COLUMNS]
    rows = read_typed_rows(path, _TEXT_COLUMNS, _INT_COLUMNS, required=required)
    for r in rows:
        for column, value in _LATER_COLUMNS.items():
            r.setdefault(column, value)
    return rows


def config_fields(cfg: StudyConfig) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def config_from_fields(fields: dict[str, Any]) -> StudyConfig:
    """The StudyConfig a run record stores (lists back to tuples)."""
    return StudyConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})

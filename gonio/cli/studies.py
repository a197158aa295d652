"""Commands of the simulated rig and its studies: simulate plan, study accuracy-vs-time,
study real-materials, plan."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated

import typer

from gonio.cli._app import ANALYSIS, SIMULATION, app, out

simulate_app = typer.Typer(no_args_is_help=True, help="The simulated rig.")


app.add_typer(simulate_app, name="simulate", rich_help_panel=SIMULATION)


@simulate_app.command("plan")
def simulate_plan(scene: Annotated[Path, typer.Argument(help="Scene TOML.")]) -> None:
    """Print the simulation stages a scene needs and their estimated cost per capture."""
    from gonio.backends import effects_description, load_scene

    out.print(effects_description(load_scene(scene)), markup=False, highlight=False)


study_app = typer.Typer(no_args_is_help=True, help="Studies run on the simulated rig.")


_FROM_CSV = typer.Option(
    "--from-csv", help="Rebuild the page and plots from the CSVs in --out (no sweep)."
)


app.add_typer(study_app, name="study", rich_help_panel=SIMULATION)


@study_app.command("accuracy-vs-time")
def study_accuracy_vs_time(
    quick: Annotated[bool, typer.Option("--quick", help="The ≤ 10-minute sweep.")] = False,
    scene: Annotated[
        Path | None,
        typer.Option(
            "--scene", help="Base scene (sensor, light, camera); materials are the study's."
        ),
    ] = None,
    seeds: Annotated[int | None, typer.Option("--seeds", help="Repeats per configuration.")] = None,
    out_dir: Annotated[
        Path, typer.Option("--out", help="Where the document, plot and CSV go.")
    ] = Path("docs"),
    rigs: Annotated[
        int | None,
        typer.Option(
            "--rigs",
            help="Realistic rigs per plan, each a fresh draw of a typical lab's shared errors "
            "(default 32, 8 with --quick; ≥ 30 for a coverage to mean much; 0: leave the "
            "realistic rig out).",
        ),
    ] = None,
    from_csv: Annotated[bool, _FROM_CSV] = False,
) -> None:
    """What accuracy costs in time: sweep poses, exposures and MCMC length on the simulated rig;
    writes accuracy-vs-time.csv (+ .json run record), then .md and the plots from them."""
    from gonio.errors import UserError
    from gonio.studies.accuracy_sweep import StudyConfig
    from gonio.studies.accuracy_vs_time import run_study

    if from_csv:
        from gonio.studies.accuracy_document import write_document

        out.print(str(write_document(out_dir)))
        return
    if seeds is not None and seeds < 1:
        raise UserError("--seeds must be ≥ 1")
    if rigs is not None and rigs < 0:
        raise UserError("--rigs must be ≥ 0")
    cfg = StudyConfig.quick(seeds) if quick else StudyConfig(seeds=seeds or 3)
    if rigs is not None:
        cfg = dataclasses.replace(
            cfg, realistic_seeds=rigs, realistic_plans=cfg.realistic_plans if rigs else ()
        )
    rows = run_study(out_dir, cfg, scene_path=scene, progress=True)
    out.print(f"{out_dir / 'accuracy-vs-time.md'}: {len(rows)} result rows")


@study_app.command("real-materials")
def study_real_materials(
    quick: Annotated[bool, typer.Option("--quick", help="The ≤ 10-minute variant.")] = False,
    out_dir: Annotated[
        Path, typer.Option("--out", help="Where the document, plots and CSVs go.")
    ] = Path("docs"),
    seed: Annotated[int, typer.Option("--seed", help="Sensor-noise and MCMC seed.")] = 0,
    from_csv: Annotated[bool, _FROM_CSV] = False,
) -> None:
    """Fit every model to four RGL-measured and two Ngan materials on the simulated rig; score
    each fit on held-out directions; writes the CSVs (+ .json run record), then
    real-materials.md and the plots from them."""
    from gonio.errors import UserError
    from gonio.studies.materials_sweep import RealMaterialsConfig
    from gonio.studies.real_materials import run_real_materials

    if from_csv:
        from gonio.studies.materials_document import write_document

        out.print(str(write_document(out_dir)))
        return
    if seed < 0:
        raise UserError("--seed must be ≥ 0")
    cfg = RealMaterialsConfig.quick_config(seed) if quick else RealMaterialsConfig(seed=seed)
    rows = run_real_materials(out_dir, cfg, progress=True)
    out.print(f"{out_dir / 'real-materials.md'}: {len(rows)} fits")


def _describe_plan(plan_path: Path, rig_path: Path | None, model: str | None) -> None:
    """A plan on a rig: poses, lab time, the retro gap, and which hemisphere regions the model
    needs (all regions without --model) that the plan leaves empty or sparse."""
    from acquisition.config import load_plan, load_rig
    from acquisition.plans import build_plan, expand_grid, lab_time_estimate, plan_coverage
    from brdfdata import coverage
    from fitting import models
    from gonio.errors import UserError
    from gonio.pipeline import config_dir

    rig = load_rig(rig_path or config_dir() / "rigs" / "sim.toml")
    cfg = load_plan(plan_path)
    try:
        needs = models.entry(model).needs if model else coverage.REGIONS
    except KeyError as exc:
        raise UserError(str(exc).strip("'\"")) from None
    plan = build_plan(rig, cfg)
    est = lab_time_estimate(rig, cfg, plan)
    out.print(
        f"plan {cfg.name} on rig {rig.name}: {len(plan.poses)} poses "
        f"({len(plan.skipped)} unreachable skipped), lab time ≈ {est.phase1_s / 60:.1f} min"
    )
    phase1 = [p.pose.deg() for p in plan.poses] if cfg.type != "adaptive" else expand_grid(cfg)
    rep = plan_coverage(phase1, needs)
    who = f"{models.resolve(model)} needs" if model else "all regions"
    out.print(f"coverage ({who}):", markup=False)
    for line in rep.lines():
        out.print(f"  {line}", markup=False)
    gaps = [f"{r.region} {r.status}" for r in rep.regions if r.status != "ok"]
    if gaps:
        out.print(
            f"warning: this plan leaves {', '.join(gaps)}: what those regions determine will "
            "rest on the prior or be biased; add poses there (see configs/plans/)",
            markup=False,
        )


@app.command(name="plan", rich_help_panel=ANALYSIS)
def plan_cmd(
    target: Annotated[
        str | None, typer.Option("--target", help="PARAM=REL_ERROR, e.g. m=0.05.")
    ] = None,
    material: Annotated[
        str, typer.Option(help='Material character: "rough" or "glossy".')
    ] = "rough",
    results: Annotated[Path, typer.Option(help="Study CSV.")] = Path("docs/accuracy-vs-time.csv"),
    plan_file: Annotated[
        Path | None,
        typer.Option("--plan", help="Describe this plan instead: poses, lab time, coverage."),
    ] = None,
    rig: Annotated[
        Path | None,
        typer.Option("--rig", help="Rig TOML: for --plan; with --target, its shared-error floor."),
    ] = None,
    model: Annotated[
        str | None, typer.Option("--model", help="With --plan: the regions this model needs.")
    ] = None,
) -> None:
    """Pick the cheapest plan expected to reach a target accuracy (from the study's results),
    or with --plan describe a plan: what it measures and what a model needs that it leaves out."""
    from gonio.errors import UserError

    if plan_file is not None:
        _describe_plan(plan_file, rig, model)
        return
    if target is None:
        raise UserError("gonio plan needs --target PARAM=REL_ERROR, or --plan FILE to describe")
    from gonio.studies.plan_choice import plan_for_target

    for line in plan_for_target(target, material, results, rig):
        out.print(line, markup=False)

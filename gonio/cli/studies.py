"""Commands of the simulated rig and its studies: simulate plan, study accuracy-vs-time,
study real-materials, plan."""

from __future__ import annotations

import dataclasses
import math
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
            "(0: leave the realistic rig out).",
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
    _plan_for_target(target, material, results, rig)


def _plan_for_target(target: str, material: str, results: Path, rig: Path | None) -> None:
    """`gonio plan --target`: the study's cheapest plan for the target, on the realistic rig
    when `rig` states its shared errors, else on the ideal rig (statistical only, with the
    rig's certificate as a floor when it states one)."""
    from gonio.errors import UserError
    from gonio.studies.accuracy_analysis import pick_plan
    from gonio.studies.accuracy_sweep import read_csv

    param, sep, value = target.partition("=")
    try:
        rel = float(value)
    except ValueError:
        rel = -1.0
    if not sep or not param or not 0 < rel < 1:
        raise UserError(f"--target {target!r}: expected PARAM=REL_ERROR with 0 < REL_ERROR < 1")
    if not results.exists():
        raise UserError(
            f"{results}: no study results; run `gonio study accuracy-vs-time --quick` first"
        )
    rows = read_csv(results)
    if not any(r["param"] == param for r in rows):
        known = ", ".join(sorted({r["param"] for r in rows}))
        raise UserError(f"--target: parameter {param!r} is not in the study (known: {known})")
    if not any(r["material"] == material for r in rows):
        raise UserError(f"--material {material!r} is not in the study")
    floor = None
    if rig is not None:
        from acquisition.config import load_rig
        from gonio.studies.accuracy_analysis import (
            shared_scale_floor,
            stated_budget,
            systematic_floor,
        )

        rig_cfg = load_rig(rig)
        stated = stated_budget(rig_cfg)
        measured = systematic_floor(rows, param)
        if measured is not None and stated.keys() - {"cert_rel_sigma"}:
            _plan_on_realistic_rig(rows, param, rel, material, rig_cfg, stated, results)
            return
        floor = shared_scale_floor(rig_cfg, param)
    stat_target = rel
    if floor is not None:
        if floor[0] >= rel:
            raise UserError(
                f"no plan reaches ±{100 * rel:g}% on {param} on this rig: its shared scale "
                f"uncertainty is {100 * floor[0]:.3g}% ({floor[1]}), one error for every sample "
                "that more poses or longer exposures cannot average away"
            )
        stat_target = math.sqrt(rel**2 - floor[0] ** 2)  # statistical ⊕ systematic ≤ target
    best = pick_plan(rows, param, stat_target, material)
    if best is None:
        raise UserError(
            f"no plan in the study reaches ±{100 * rel:g}% on {param} for a {material} material"
        )
    out.print(
        f"{best['plan']}: {best['poses']} poses, {best['exposures']} exposure, "
        f"MCMC {best['mcmc_steps']} steps → expected {param} error "
        f"{100 * best['rel_error']:.2f}% (median over seeds); expected lab time "
        f"{best['lab_time_s'] / 60:.1f} min"
    )
    if floor is None:
        why = (
            "give --rig to include your rig's shared floor"
            if rig is None
            else f"your rig states no shared error that moves {param} (arm-angle errors are "
            "not in the budget yet)"
        )
        out.print(
            "That figure is statistical only: the study's simulated rig has no instrument "
            f"errors; {why}.",
            markup=False,
        )
        from gonio.studies.accuracy_analysis import systematic_floor

        measured = systematic_floor(rows, param)
        if measured is not None:
            out.print(
                f"On the study's realistic rig (a typical lab's shared errors) no plan gets "
                f"{param} below ±{100 * measured['floor']:.3g}%: that floor is systematic.",
                markup=False,
            )
    else:
        total = math.hypot(best["rel_error"], floor[0])
        out.print(
            f"With this rig's shared scale uncertainty of {100 * floor[0]:.3g}% ({floor[1]}): "
            f"expected total {param} error {100 * total:.2f}% (statistical ⊕ systematic).",
            markup=False,
        )


_BUDGET_WORDS = {
    "cert_rel_sigma": ("certificate", lambda v: f"{100 * v:.3g} %"),
    "distance_sigma_m": ("lamp distance", lambda v: f"{1e3 * v:.3g} mm"),
    "zero_sigma_deg": ("encoder zeros", lambda v: f"{v:.3g}°"),
    "tilt_sigma_deg": ("sample tilt", lambda v: f"{v:.3g}°"),
    "play_deg": ("gears' play", lambda v: f"{v:.3g}°"),
    "sag_sigma_deg": ("arm sag", lambda v: f"{v:.3g}°"),
}


def _budget_words(sizes: dict) -> str:
    return ", ".join(
        f"{word} {fmt(sizes[k])}" for k, (word, fmt) in _BUDGET_WORDS.items() if k in sizes
    )


def _plan_on_realistic_rig(rows, param, rel, material, rig_cfg, stated, results) -> None:
    """`gonio plan --target` for a rig that states its shared errors: from the study's realistic
    rig, the cheapest plan whose 68 % half-width (its statistical part ⊕ the systematic part
    for this rig: the shared scale swapped for the rig's own, gonio.studies.accuracy_analysis.
    realistic_choices) and whose RMS error over the study's rigs both reach the target; or one
    line saying that no plan can, because the floor those errors leave is above the target."""
    from gonio.errors import UserError
    from gonio.studies.accuracy_analysis import realistic_choices, shared_scale_sigma
    from gonio.studies.accuracy_sweep import RECORD_NAME
    from gonio.studies.common import read_record

    record = results.with_name(RECORD_NAME)
    study = read_record(record).get("realistic", {}).get("budget") if record.exists() else None
    scale_study = shared_scale_sigma(budget=study) if study else None
    scale_rig = shared_scale_sigma(rig_cfg)
    choices = realistic_choices(rows, param, scale_study, scale_rig)
    top = max(choices, key=lambda s: (s["poses"], s["lab_time_s"]))
    floor = top["rel_sys_rig"]
    words = []
    if top["scale_swapped"]:
        words.append(
            f"The shared scale is your rig's ({100 * scale_rig:.3g} %, "
            + (
                "its reference target's certificate"
                if rig_cfg.reference is not None
                else "its lamp's certificate and distance"
            )  # fmt: skip
            + f") in place of the study's ({100 * scale_study:.3g} %)."
        )
    angles = [k for k in _BUDGET_WORDS if k not in ("cert_rel_sigma", "distance_sigma_m")]
    if study and any(abs(stated.get(k, 0.0) - study[k]) > 1e-9 for k in angles):
        words.append(
            f"The study's realistic rig states {_budget_words(study)}; yours states "
            f"{_budget_words(stated) or 'none of these'}: the arms' part of the floor moves "
            "with those sizes."
        )
    if top["material"] != material:
        words.append(
            f"The realistic rig was studied on a {top['material']} material; its floor stands "
            f"in for your {material} one."
        )
    if floor >= rel:
        raise UserError(
            f"no plan reaches ±{100 * rel:g}% on {param} on this rig: its shared errors leave "
            f"±{100 * floor:.3g}% (the systematic part of the 68 % interval on the study's "
            f"largest realistic plan, {top['plan']} with {top['poses']} poses, over "
            f"{top['n']} rigs), which more poses or longer exposures cannot average away"
            + (". " + " ".join(words).rstrip(".") if words else "")
        )
    # Both the quoted uncertainty and the error the rigs really showed must meet the target
    # (a small plan's intervals can be too narrow: the study's page says where).
    ok = [s for s in choices if max(s["rel_total_rig"], s["rel_error_rig"]) <= rel]
    if not ok:
        raise UserError(
            f"no plan in the study reaches ±{100 * rel:g}% on {param} on this rig: the "
            f"largest, {top['plan']}, gives ±{100 * top['rel_total_rig']:.3g}% (of which "
            f"{100 * floor:.3g}% systematic, the floor)"
        )
    best = min(ok, key=lambda s: (s["lab_time_s"], s["compute_s"]))
    out.print(
        f"{best['plan']}: {best['poses']} poses, {best['exposures']} exposure, "
        f"MCMC {best['mcmc_steps']} steps → expected {param} uncertainty "
        f"±{100 * best['rel_total_rig']:.2f}% (68 %, including the instrument budget: "
        f"systematic {100 * best['rel_sys_rig']:.2f}%, statistical "
        f"{100 * best['rel_stat_68']:.2f}%; RMS error {100 * best['rel_error_rig']:.2f}% "
        f"over {best['n']} simulated rigs); expected lab "
        f"time {best['lab_time_s'] / 60:.1f} min",
        markup=False,
    )
    for line in words:
        out.print(line, markup=False)

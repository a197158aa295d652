"""The `gonio` command line. Subcommand names and options are contracts (issue #2)."""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

__all__ = ["app", "main"]

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="gonio: gonioreflectometer acquisition, calibration and BRDF fitting.",
    pretty_exceptions_enable=False,
)
out = Console()
err = Console(stderr=True)
_DEBUG = {"on": False}


def _version_cb(value: bool) -> None:
    if value:
        from gonio.pipeline import _version

        out.print(f"gonio {_version()}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_cb, is_eager=True, help="Show version.")
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors.")] = False,
) -> None:
    _DEBUG["on"] = debug


@app.command()
def demo(
    out_dir: Annotated[Path | None, typer.Option("--out", help="Run directory to create.")] = None,
    scene: Annotated[Path | None, typer.Option("--scene", help="Scene TOML to simulate.")] = None,
    quick: Annotated[bool, typer.Option("--quick", help="Shorter MCMC (≈1 min).")] = False,
) -> None:
    """Simulated acquisition → calibration → fit → report; prints the report path."""
    from gonio.pipeline import demo as run_demo
    from gonio.runs import check_run_path

    if out_dir is not None:
        check_run_path(out_dir)  # no '..' in run paths (gonio/runs.py)
    report = run_demo(out_dir, scene, quick)
    out.print(str(report))


@app.command()
def acquire(
    rig: Annotated[Path | None, typer.Option("--rig", help="Rig TOML.")] = None,
    plan: Annotated[Path | None, typer.Option("--plan", help="Plan TOML.")] = None,
    out_dir: Annotated[
        Path, typer.Option("--out", help="Run directory (resumed if incomplete).")
    ] = ...,  # type: ignore[assignment]
    scene: Annotated[Path | None, typer.Option("--scene", help="Override the rig's scene.")] = None,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Run a plan on a rig into OUT; resume OUT when it holds an incomplete run."""
    from gonio.pipeline import acquire as run_acquire
    from gonio.runs import check_run_path

    check_run_path(out_dir)  # no '..' in run paths (gonio/runs.py)
    from acquisition.kinematics import Unreachable
    from gonio.errors import UserError

    try:
        res = run_acquire(rig, plan, out_dir, scene_path=scene, progress=progress)
    except Unreachable as exc:  # an explicit pose the rig cannot reach: name the plan file
        if plan is None:
            raise
        raise UserError(f"{plan}: {exc}; change or remove that pose") from None
    o = res.outcome
    out.print(
        f"{res.run_dir}: {o.reason}; {o.captured} new capture(s), {o.adopted} recovered, "
        f"{o.total_done} done in total; lab time {o.lab_time_s:.1f} s"
    )
    if not o.complete:
        raise typer.Exit(3)


@app.command()
def calibrate(
    run_dir: Annotated[Path, typer.Argument(help="Run directory.")],
    bin_px: Annotated[int, typer.Option(help="Region size in (super)pixels.")] = 4,
    mode: Annotated[
        str,
        typer.Option(
            help='"mean" of the region\'s pixels (every photon) or '
            '"center" pixel only (exact directions).'
        ),
    ] = "mean",
    radiometry: Annotated[
        str,
        typer.Option(
            help='"reference": scale from the run\'s reference-target captures; "certified": '
            'the light\'s certified intensity; "auto": reference if the run has its captures.'
        ),
    ] = "auto",
    segment: Annotated[
        bool, typer.Option(help="Segment the sample in each image; flag the rest MASKED.")
    ] = True,
) -> None:
    """Reduce RUN_DIR's frames to RUN_DIR/samples.parquet."""
    from calibration.reduce import ReduceOptions, reduce_run

    if bin_px < 1:
        raise typer.BadParameter("--bin-px must be ≥ 1")
    if mode not in ("mean", "center"):
        raise typer.BadParameter('--mode must be "mean" or "center"')
    if radiometry not in ("auto", "certified", "reference"):
        raise typer.BadParameter('--radiometry must be "auto", "certified" or "reference"')
    options = ReduceOptions(bin_px=bin_px, mode=mode, radiometry=radiometry, segment=segment)
    table = reduce_run(run_dir, options, progress=True)
    out.print(f"{run_dir / 'samples.parquet'}: {len(table)} samples")


def _kv(items: list[str], what: str) -> dict[str, str]:
    from gonio.errors import UserError

    result = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UserError(f"{what} {item!r}: expected KEY=VALUE")
        result[key.strip()] = value.strip()
    return result


@app.command()
def fit(
    samples: Annotated[
        Path,
        typer.Argument(help="samples.parquet (any table with the DESIGN §4 required columns)."),
    ],
    model: Annotated[
        str,
        typer.Option(
            "--model", help='Model name (see `gonio models`), or "all" to fit and rank every one.'
        ),
    ] = "torrance-sparrow",
    option: Annotated[list[str], typer.Option("--option", help="Model option KEY=VALUE.")] = [],  # noqa: B006
    fix: Annotated[list[str], typer.Option("--fix", help="Hold NAME=VALUE fixed.")] = [],  # noqa: B006
    shared: Annotated[str, typer.Option(help="Comma list of parameters shared by channels.")] = "m",
    compare_shared: Annotated[
        bool,
        typer.Option(
            "--compare-shared",
            help="Also fit each model with every parameter per channel; rank both.",
        ),
    ] = False,
    channels: Annotated[str | None, typer.Option(help="Comma list, e.g. R,G,B.")] = None,
    priors: Annotated[
        Path | None, typer.Option("--priors", help="Priors TOML (bounds, energy conservation).")
    ] = None,
    likelihood: Annotated[
        str, typer.Option("--likelihood", help="gaussian | student-t (robust to outliers).")
    ] = "gaussian",
    censor: Annotated[
        bool,
        typer.Option("--censor", help="Treat saturated/dark samples as censored, not excluded."),
    ] = False,
    no_mcmc: Annotated[bool, typer.Option("--no-mcmc", help="Least squares only.")] = False,
    walkers: Annotated[int, typer.Option(help="emcee walkers.")] = 32,
    steps: Annotated[int, typer.Option(help="Maximum MCMC steps.")] = 3000,
    time_budget: Annotated[float | None, typer.Option(help="MCMC wall-time budget [s].")] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    out_dir: Annotated[
        Path | None, typer.Option("--out", help="Output directory (default: beside SAMPLES).")
    ] = None,
) -> None:
    """Fit a model to SAMPLES: writes fit-NAME.json, fit-NAME.h5 and material-NAME.xml
    (Mitsuba 3); with --model all or --compare-shared also compare.json (ranked by PSIS-LOO)."""
    from fitting import models as model_registry
    from fitting.compare import candidates, run_comparison
    from fitting.export import write_material_xml
    from fitting.likelihood import LIKELIHOOD_KINDS
    from fitting.priors import PriorsError, load_priors
    from fitting.samples import read_samples
    from gonio.errors import UserError

    table = read_samples(samples)
    if model != "all" and model not in model_registry.names():
        raise UserError(f"unknown model {model!r}; known: {', '.join(model_registry.names())}, all")
    if likelihood not in LIKELIHOOD_KINDS:
        raise UserError(f"--likelihood {likelihood!r}: use one of {', '.join(LIKELIHOOD_KINDS)}")
    if walkers < 2 or steps < 1:
        raise UserError("--walkers must be ≥ 2 and --steps ≥ 1")
    try:
        fixed = {k: float(v) for k, v in _kv(fix, "--fix").items()}
    except ValueError as exc:
        raise UserError(f"--fix: {exc}") from None
    chans = [c.strip() for c in channels.split(",")] if channels else None
    dest = out_dir or samples.parent
    shared_names = tuple(s.strip() for s in shared.split(",") if s.strip())
    try:
        prior_cfg = load_priors(priors) if priors is not None else None
        cands = candidates(
            model, _kv(option, "--option"), shared_names, compare_shared=compare_shared
        )
    except (PriorsError, TypeError, ValueError) as exc:
        raise UserError(str(exc).splitlines()[0]) from None

    def show(c, result) -> None:
        xml = write_material_xml(result, Path(dest) / f"material-{c.label}.xml")
        t = Table(title=f"{c.label} fit ({xml.name})")
        for col in ("parameter", "MAP", "median", "p16", "p84"):
            t.add_column(col, justify="right")
        for name, p in result.to_dict()["parameters"].items():
            t.add_row(name, *(f"{p[k]:.5g}" for k in ("map", "median", "p16", "p84")))
        out.print(t)

    kwargs = dict(
        channels=chans,
        mcmc=not no_mcmc,
        walkers=walkers,
        steps=steps,
        time_budget_s=time_budget,
        seed=seed,
        likelihood=likelihood,
        censor=censor,
        progress=True,
    )
    try:
        if len(cands) == 1 and not compare_shared:
            from fitting.fit import fit_samples

            c = cands[0]
            result = fit_samples(
                table,
                c.model,
                options=c.options,
                shared=c.shared,
                fix=fixed,
                priors=prior_cfg,
                out_dir=dest,
                **kwargs,
            )
            show(c, result)
            return
        ranked, _ = run_comparison(
            table, cands, out_dir=dest, fix=fixed, priors=prior_cfg, on_fit=show, **kwargs
        )
    except PriorsError as exc:
        raise UserError(str(exc).splitlines()[0]) from None

    def num(x: float) -> str:
        return f"{x:.0f}" if abs(x) >= 100 else f"{x:.1f}"

    t = Table(title=f"Model comparison, {ranked[0].n} samples (best first; elpd in nats)")
    for col in (
        "model",
        "shared",
        "k",
        "elpd_loo ± SE",
        "p_loo",
        "WAIC",
        "ΔELPD ± SE",
        "max k̂",
        "AIC",
        "BIC",
    ):
        t.add_column(col, justify="right", no_wrap=True)
    for s in ranked:
        t.add_row(
            s.label,
            ",".join(s.shared) or "–",
            str(s.k),
            f"{num(s.elpd_loo)} ± {num(s.se_loo)}",
            num(s.p_loo),
            num(s.waic),
            f"{num(s.d_elpd)} ± {num(s.d_se)}",
            f"{s.khat_max:.2f}",
            num(s.aic),
            num(s.bic),
        )
    # Wrapped or truncated numbers are unreadable: give the table the width it needs.
    Console(width=max(out.width, 150)).print(t)
    for s in ranked:
        for w in s.warnings:
            out.print(f"note: {s.label}: {w}")
    out.print(str(Path(dest) / "compare.json"))


@app.command(name="calibrate-camera")
def calibrate_camera(
    images: Annotated[list[Path], typer.Argument(help="Board images (JPEG/PNG/TIFF).")],
    board: Annotated[
        str,
        typer.Option(
            "--board",
            help="charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT or chessboard:COLSxROWS:SQUARE_M",
        ),
    ] = ...,  # type: ignore[assignment]
    fix_aspect: Annotated[bool, typer.Option("--fix-aspect", help="Hold fx/fy fixed.")] = False,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Write the result as JSON.")
    ] = None,
) -> None:
    """Camera intrinsics and distortion from board images (OpenCV 5)."""
    from calibration.camera_model import (
        calibrate_images,
        format_result,
        parse_board,
        write_result_json,
    )

    result = calibrate_images(list(images), parse_board(board), fix_aspect=fix_aspect)
    out.print(format_result(result), markup=False, highlight=False)
    if json_out is not None:
        write_result_json(result, json_out)


@app.command()
def report(run_dir: Annotated[Path, typer.Argument(help="Run directory.")]) -> None:
    """Write RUN_DIR/report.html (self-contained)."""
    from gonio.report import write_report

    out.print(str(write_report(run_dir)))


simulate_app = typer.Typer(no_args_is_help=True, help="The simulated rig.")
app.add_typer(simulate_app, name="simulate")


@simulate_app.command("plan")
def simulate_plan(scene: Annotated[Path, typer.Argument(help="Scene TOML.")]) -> None:
    """Print the simulation stages a scene needs and their estimated cost per capture."""
    from simulator.planner import plan_effects
    from simulator.scene import load_scene

    out.print(plan_effects(load_scene(scene)).describe(), markup=False, highlight=False)


@app.command(name="models")
def models_cmd(
    check: Annotated[
        bool, typer.Option("--check", help="Measure properties of each model.")
    ] = False,
) -> None:
    """List the BRDF models with their parameters, units and bounds."""
    from fitting import models as registry

    t = Table(title="BRDF models (f_r in 1/sr)")
    for col in ("model", "parameter", "unit", "lower", "upper", "sampled in"):
        t.add_column(col)
    for name in registry.names():
        m = registry.get(name)
        for i, p in enumerate(m.parameters):
            t.add_row(
                name if i == 0 else "",
                p.name,
                p.unit,
                f"{p.lower:g}",
                f"{p.upper:g}",
                "log" if p.log else "linear",
            )
    out.print(t)
    if check:
        from fitting.properties import property_table

        rows = property_table()
        pt = Table(title="Measured properties (quadrature and random direction pairs)")
        for col in (
            "model",
            "options",
            "reciprocal",
            "energy ≤ 1",
            "isotropic",
            "finite",
            "max albedo",
            "max recip. err",
        ):
            pt.add_column(col)
        for r in rows:
            opts = ",".join(f"{v}" for v in r["options"].values()) or "–"
            pt.add_row(
                r["model"],
                opts,
                *(
                    "yes" if r[k] else "NO"
                    for k in ("reciprocal", "energy_conserving", "isotropic", "finite")
                ),
                f"{r['max_albedo']:.4f}",
                f"{r['max_reciprocity_error']:.1e}",
            )
        out.print(pt)
        out.print(
            "energy ≤ 1: directional albedo ≤ 1 at every tested θo and parameter set; the "
            "seed's Phong k_s(l̂·r̂)^n is reciprocal but not energy conserving."
        )


runs_app = typer.Typer(no_args_is_help=True, help="Run directories: list and inspect.")
app.add_typer(runs_app, name="runs")


@runs_app.command("list")
def runs_list(
    root: Annotated[Path, typer.Option("--root", help="Folder holding run directories.")] = Path(
        "runs"
    ),
) -> None:
    """Table of runs: status, captures done/total, start, lab time, last stop reason."""
    from gonio.runs import find_runs, runs_table

    if not find_runs(root):
        out.print(f"no runs under {root}")
        return
    out.print(runs_table(root))


@runs_app.command("show")
def runs_show(
    run: Annotated[Path, typer.Argument(help="Run directory (or its name under --root).")],
    root: Annotated[Path, typer.Option("--root", help="Where to look for a bare name.")] = Path(
        "runs"
    ),
    verify: Annotated[bool, typer.Option(help="Verify every frame's SHA-256.")] = True,
) -> None:
    """Config summary, counts, events (with stop reasons) and checksum verification of RUN."""
    from gonio.runs import resolve_run, show_run

    path = resolve_run(run, root)  # a bare name stays inside --root; no '..' (gonio/runs.py)
    group, problems = show_run(path, verify=verify)
    out.print(group)
    if problems:
        raise typer.Exit(4)


rig_app = typer.Typer(no_args_is_help=True, help="Rig hardware.")
app.add_typer(rig_app, name="rig")


@rig_app.command("check")
def rig_check(
    rig: Annotated[Path, typer.Option("--rig", help="Rig TOML.")] = ...,  # type: ignore[assignment]
) -> None:
    """Ping every servo; read model, firmware, voltage, temperature, limits, error status."""
    from acquisition.config import load_rig
    from acquisition.protocols import DeviceFault
    from gonio.backends import prepare_backends
    from gonio.errors import UserError
    from gonio.runs import check_rig, rig_check_table

    cfg = load_rig(rig)
    prepare_backends(cfg)
    try:
        rows = check_rig(cfg)
    except DeviceFault as exc:  # the bus itself cannot be opened
        raise UserError(f"{rig}: bus.url: {exc}") from None
    out.print(rig_check_table(cfg, rows))
    if not all(r.ok for r in rows):
        raise typer.Exit(3)


study_app = typer.Typer(no_args_is_help=True, help="Studies run on the simulated rig.")
app.add_typer(study_app, name="study")


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
) -> None:
    """What accuracy costs in time: sweep poses, exposures and MCMC length on the simulated rig;
    writes accuracy-vs-time.md, .png and .csv."""
    from gonio.errors import UserError
    from gonio.study import StudyConfig, run_study

    if seeds is not None and seeds < 1:
        raise UserError("--seeds must be ≥ 1")
    cfg = StudyConfig.quick(seeds) if quick else StudyConfig(seeds=seeds or 3)
    rows = run_study(out_dir, cfg, scene_path=scene, progress=True)
    out.print(f"{out_dir / 'accuracy-vs-time.md'}: {len(rows)} result rows")


@study_app.command("real-materials")
def study_real_materials(
    quick: Annotated[bool, typer.Option("--quick", help="The ≤ 10-minute variant.")] = False,
    out_dir: Annotated[
        Path, typer.Option("--out", help="Where the document, plots and CSVs go.")
    ] = Path("docs"),
    seed: Annotated[int, typer.Option("--seed", help="Sensor-noise and MCMC seed.")] = 0,
) -> None:
    """Fit every model to four RGL-measured and two Ngan materials on the simulated rig; score
    each fit on held-out directions; writes real-materials.md, .png and .csv."""
    from gonio.errors import UserError
    from gonio.real_materials import RealMaterialsConfig, run_real_materials

    if seed < 0:
        raise UserError("--seed must be ≥ 0")
    cfg = RealMaterialsConfig.quick_config(seed) if quick else RealMaterialsConfig(seed=seed)
    rows = run_real_materials(out_dir, cfg, progress=True)
    out.print(f"{out_dir / 'real-materials.md'}: {len(rows)} fits")


@app.command(name="plan")
def plan_cmd(
    target: Annotated[str, typer.Option("--target", help="PARAM=REL_ERROR, e.g. m=0.05.")] = ...,  # type: ignore[assignment]
    material: Annotated[
        str, typer.Option(help='Material character: "rough" or "glossy".')
    ] = "rough",
    results: Annotated[Path, typer.Option(help="Study CSV.")] = Path("docs/accuracy-vs-time.csv"),
) -> None:
    """Pick the cheapest plan expected to reach a target accuracy (from the study's results)."""
    from gonio.errors import UserError
    from gonio.study import pick_plan, read_csv

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
    best = pick_plan(rows, param, rel, material)
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


def main() -> None:
    """Entry point: user mistakes print one line (no traceback) and exit 2."""
    warnings.filterwarnings("ignore", category=FutureWarning)
    from gonio.errors import user_error_types

    debug = "--debug" in sys.argv[1:] or os.environ.get("GONIO_DEBUG") == "1"
    try:
        rc = app(standalone_mode=False)
        if isinstance(rc, int) and rc:
            sys.exit(rc)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        err.print("aborted")
        sys.exit(130)
    except KeyboardInterrupt:
        err.print("interrupted")
        sys.exit(130)
    except Exception as exc:  # the one place where errors meet the user
        # Usage errors (unknown option, bad value) are click exceptions — but typer ≥ 0.16
        # vendors click, so match the class by name across both copies rather than by identity.
        if any(c.__name__ == "ClickException" for c in type(exc).__mro__):
            exc.show()  # type: ignore[attr-defined]
            sys.exit(exc.exit_code)
        if debug:
            raise
        if isinstance(exc, user_error_types()):
            msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            # Plain write, not rich: rich would wrap a long path onto a second line.
            sys.stderr.write(f"error: {msg}\n")
            sys.exit(2)
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        sys.stderr.write(
            f"internal error: {type(exc).__name__}: {first} (run with --debug for a traceback)\n"
        )
        sys.exit(1)


if __name__ == "__main__":
    main()

"""Commands at the rig: demo, acquire, capture, calibrate, calibrate-camera, calibrate-rig,
rig check, runs list/show."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from gonio.cli._app import (
    ANSWERS_OPTION,
    LAB,
    SIMULATION,
    YES_OPTION,
    app,
    operator_for,
    out,
    scene_for,
)
from gonio.plain_text import printable


@app.command(rich_help_panel=SIMULATION)
def demo(
    out_dir: Annotated[Path | None, typer.Option("--out", help="Run directory to create.")] = None,
    scene: Annotated[Path | None, typer.Option("--scene", help="Scene TOML to simulate.")] = None,
    quick: Annotated[bool, typer.Option("--quick", help="Shorter MCMC (≈1 min).")] = False,
    seed: Annotated[
        int | None,
        typer.Option(help="Another realization: the sensor's noise and the fit's seed."),
    ] = None,
) -> None:
    """Simulated acquisition → calibration → fit → report; prints the report path."""
    from gonio.pipeline import demo as run_demo
    from gonio.runs import check_run_path

    if out_dir is not None:
        check_run_path(out_dir)  # no '..' in run paths (gonio/runs.py)
    report = run_demo(out_dir, scene, quick, seed=seed)
    _demo_verdicts(report.parent)
    out.print(str(report))


def _demo_verdicts(run_dir: Path) -> None:
    """The demo fit's verdicts (as `gonio fit` prints them) and a line naming any fail."""
    from fitting.result import read_fit
    from fitting.verdicts import failed
    from gonio.cli.fit import show_verdicts

    for path in sorted(run_dir.glob("fit-*.json")):
        verdicts = read_fit(path).verdicts or []
        show_verdicts(verdicts, f"{path.name} verdicts")
        names = failed(verdicts)
        if names:
            out.print(f"demo fit {path.name} failed: {', '.join(names)} (see the verdicts above)")


@app.command(rich_help_panel=LAB)
def acquire(
    rig: Annotated[Path | None, typer.Option("--rig", help="Rig TOML.")] = None,
    plan: Annotated[Path | None, typer.Option("--plan", help="Plan TOML.")] = None,
    out_dir: Annotated[
        Path, typer.Option("--out", help="Run directory (resumed if incomplete).")
    ] = ...,  # type: ignore[assignment]
    scene: Annotated[Path | None, typer.Option("--scene", help="Override the rig's scene.")] = None,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
    yes: Annotated[bool, YES_OPTION] = False,
    answers: Annotated[Path | None, ANSWERS_OPTION] = None,
) -> None:
    """Run a plan on a rig into OUT (its calibration phases first); resume OUT when it holds an
    incomplete run — with --rig again: the run's devices and commands must match that file."""
    from gonio.pipeline import AcquireSpec
    from gonio.pipeline import acquire as run_acquire
    from gonio.runs import check_run_path

    check_run_path(out_dir)  # no '..' in run paths (gonio/runs.py)
    from acquisition.kinematics import Unreachable
    from gonio.errors import UserError

    try:
        spec = AcquireSpec(
            rig=rig, plan=plan, scene=scene, progress=progress, operator=operator_for(yes, answers)
        )
        res = run_acquire(out_dir, spec)
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


@app.command(rich_help_panel=LAB)
def calibrate(
    run_dir: Annotated[Path, typer.Argument(help="Run directory.")],
    bin_px: Annotated[
        int | None,
        typer.Option(help="Region size in (super)pixels (default 4; 1 with --per-texel)."),
    ] = None,
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
    per_texel: Annotated[
        float | None,
        typer.Option(
            "--per-texel",
            metavar="MM",
            help="Texel side in mm: give every sample its texel index on the sample plane "
            "(writes RUN_DIR/samples-texels.parquet).",
        ),
    ] = None,
    strict: Annotated[
        bool,
        typer.Option(
            "--strict",
            help="Stop at a frame whose SHA-256 differs from the manifest's (default: skip it "
            "with a counted warning).",
        ),
    ] = False,
    samples_out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            help="Samples file to write instead of the one in RUN_DIR (e.g. for a run on "
            "read-only media).",
        ),
    ] = None,
) -> None:
    """Reduce RUN_DIR's frames to RUN_DIR/samples.parquet (per texel: samples-texels.parquet)."""
    from calibration.reduce import ReduceOptions, reduce_to_file

    if per_texel is not None and not per_texel > 0:
        raise typer.BadParameter("--per-texel must be a texel side > 0 in mm")
    if bin_px is None:
        bin_px = 1 if per_texel is not None else 4
    if bin_px < 1:
        raise typer.BadParameter("--bin-px must be ≥ 1")
    if mode not in ("mean", "center"):
        raise typer.BadParameter('--mode must be "mean" or "center"')
    if radiometry not in ("auto", "certified", "reference"):
        raise typer.BadParameter('--radiometry must be "auto", "certified" or "reference"')
    options = ReduceOptions(
        bin_px=bin_px,
        mode=mode,
        radiometry=radiometry,
        segment=segment,
        texel_mm=per_texel,
        strict=strict,
    )
    # Written pose by pose and not read back: memory does not grow with the run's length.
    done = reduce_to_file(run_dir, options, out=samples_out, progress=True)
    texels = "" if done.texels is None else f" in {done.texels} texels"
    out.print(f"{printable(done.path)}: {done.rows} samples{texels}", markup=False)
    _print_budget(done.metadata)


def _print_budget(metadata: dict[str, str]) -> None:
    """The samples' uncertainty budget as a GUM-style table (component, type, size, shared by)."""
    from rich.table import Table

    from fitting.budget import budget_words, read_budget

    rows = budget_words(read_budget(metadata))
    grid = Table(title="Uncertainty budget (type A: from these data; B: from elsewhere)")
    for col in ("component", "type", "size", "shared by"):
        grid.add_column(col)
    for row in rows:
        grid.add_row(*row)
    out.print(grid)
    out.print(
        "Only the statistical component is in each sample's σ; the shared ones are one error "
        "for all the samples they name, and the fit carries them as systematic parts."
    )


@app.command(name="calibrate-camera", rich_help_panel=LAB)
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
    from gonio.errors import UserError

    if json_out is not None and json_out.exists():
        raise UserError(f"{json_out}: exists; choose a new --json file (calibrations are kept)")
    result = calibrate_images(list(images), parse_board(board), fix_aspect=fix_aspect)
    out.print(format_result(result), markup=False, highlight=False)
    if json_out is not None:
        write_result_json(result, json_out)


@app.command(name="calibrate-rig", rich_help_panel=LAB)
def calibrate_rig_cmd(
    rig: Annotated[Path, typer.Option("--rig", help="Rig TOML.")] = ...,  # type: ignore[assignment]
    board: Annotated[
        str,
        typer.Option(
            "--board", help="charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (as calibrate-camera)"
        ),
    ] = ...,  # type: ignore[assignment]
    out_file: Annotated[
        Path, typer.Option("--out", help="Arm-offsets JSON to write (never overwritten).")
    ] = ...,  # type: ignore[assignment]
    scene: Annotated[
        Path | None, typer.Option("--scene", help="Simulated rigs: the world.")
    ] = None,
    yes: Annotated[bool, YES_OPTION] = False,
    answers: Annotated[Path | None, ANSWERS_OPTION] = None,
) -> None:
    """Camera-arm zero offsets and sample-plane tilt from board views on the rig; point the rig
    file's calibration.arm_offsets at OUT and `gonio calibrate` uses them."""
    from acquisition.config import load_rig
    from acquisition.rig import build_rig
    from calibration.camera_model import parse_board
    from gonio.backends import prepare_backends
    from gonio.rig_calibration import calibrate_rig

    cfg = load_rig(rig)
    spec = parse_board(board)
    scene_cfg = scene_for(scene)
    world = prepare_backends(cfg, scene_cfg)
    hands = operator_for(yes, answers)
    if world is not None:
        hands = world.hands(hands)
    rig_dev = build_rig(cfg)
    try:
        doc = calibrate_rig(cfg, rig_dev, spec, out_file, hands)
    finally:
        rig_dev.close()
    o, t, sg = doc["offsets_deg"], doc["tilt_deg"], doc["sigma_deg"]
    out.print(
        f"{out_file}: camera θ offset {o['camera_theta']:+.3f}° ± {sg['camera_theta']:.3f}, "
        f"φ offset {o['camera_phi']:+.3f}° ± {sg['camera_phi']:.3f}; tilt x {t['x']:+.3f}° ± "
        f"{sg['tilt_x']:.3f}, y {t['y']:+.3f}° ± {sg['tilt_y']:.3f}; camera roll "
        f"{doc['camera_roll_deg']:+.3f}° ± {sg['camera_roll']:.3f} ({doc['n_views']} views, "
        f"RMS {1e3 * doc['rms_m']:.2f} mm)"
    )


@app.command(name="capture", rich_help_panel=LAB)
def capture_cmd(
    kind: Annotated[str, typer.Argument(help="dark | flat | reference")],
    run_dir: Annotated[Path, typer.Argument(help="Run directory.")],
    rig: Annotated[Path, typer.Option("--rig", help="Rig TOML.")] = ...,  # type: ignore[assignment]
    scene: Annotated[
        Path | None, typer.Option("--scene", help="Simulated rigs: the world.")
    ] = None,
    yes: Annotated[bool, YES_OPTION] = False,
    answers: Annotated[Path | None, ANSWERS_OPTION] = None,
) -> None:
    """Retake one kind of calibration frames into RUN_DIR (a new take; earlier ones are kept,
    calibration uses the newest complete take)."""
    from gonio.pipeline import capture_calibration
    from gonio.runs import check_run_path

    check_run_path(run_dir)
    n = capture_calibration(
        run_dir, kind, rig_path=rig, scene_path=scene, operator=operator_for(yes, answers)
    )
    out.print(f"{run_dir}: {n} {kind} frame(s) captured (new take)")


runs_app = typer.Typer(no_args_is_help=True, help="Run directories: list and inspect.")


app.add_typer(runs_app, name="runs", rich_help_panel=LAB)


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


app.add_typer(rig_app, name="rig", rich_help_panel=LAB)


@rig_app.command("check")
def rig_check(
    rig: Annotated[Path, typer.Option("--rig", help="Rig TOML.")] = ...,  # type: ignore[assignment]
    scene: Annotated[
        Path | None, typer.Option("--scene", help="Simulated rigs: the world.")
    ] = None,
    exposure_s: Annotated[float, typer.Option("--exposure-s", help="Test frame exposure.")] = 0.002,
) -> None:
    """Servos (model, firmware, voltage, temperature, present angle vs limits, error status),
    the light's identity and monitor reading, and one test frame's statistics. Moves nothing."""
    from acquisition.config import load_rig
    from acquisition.protocols import DeviceFault
    from gonio.backends import prepare_backends
    from gonio.errors import UserError
    from gonio.rig_check import check_camera, check_light, check_rig, rig_check_report

    cfg = load_rig(rig)
    scene_cfg = scene_for(scene)
    prepare_backends(cfg, scene_cfg)
    try:
        rows = check_rig(cfg)
    except DeviceFault as exc:  # the bus itself cannot be opened
        raise UserError(f"{rig}: bus.url: {exc}") from None
    devices = [check_light(cfg), check_camera(cfg, exposure_s)]
    out.print(rig_check_report(cfg, rows, devices))
    if not all(r.ok for r in rows) or not all(d.ok for d in devices):
        raise typer.Exit(3)

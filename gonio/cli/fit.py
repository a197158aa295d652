"""Commands on data: fit, models, report, import, export, data list/fetch."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from gonio.cli._app import ANALYSIS, DATA, app, kv_pairs, out
from gonio.cli.fit_options import (
    BinOption,
    ModelOption,
    NoWidenOption,
    SamplerOption,
    TemperaturesOption,
)
from gonio.plain_text import plain


@app.command(rich_help_panel=ANALYSIS)
def fit(
    samples: Annotated[
        Path,
        typer.Argument(
            help="samples.parquet: any table with the samples contract's columns (see "
            "docs/formats.md); other formats: `gonio import`."
        ),
    ],
    model: ModelOption = "torrance-sparrow",
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
    drop_flagged: Annotated[
        bool,
        typer.Option(
            "--drop-flagged",
            help="Exclude DARK/SATURATED samples (the old default) instead of censoring them.",
        ),
    ] = False,
    censor: Annotated[
        bool,
        typer.Option(
            "--censor", hidden=True, help="Accepted for old scripts: censoring is the default."
        ),
    ] = False,
    accept_poor_fit: Annotated[
        bool,
        typer.Option(
            "--accept-poor-fit", help="Exit 0 even when a verdict fails (the fit is kept)."
        ),
    ] = False,
    no_mcmc: Annotated[bool, typer.Option("--no-mcmc", help="Least squares only.")] = False,
    walkers: Annotated[int, typer.Option(help="emcee walkers.")] = 32,
    steps: Annotated[
        int,
        typer.Option(help="Cap on MCMC steps (the chain stops once R̂ < 1.01, ESS ≥ 400)."),
    ] = 3000,
    time_budget: Annotated[float | None, typer.Option(help="MCMC wall-time budget [s].")] = None,
    sampler: SamplerOption = "ensemble",
    temperatures: TemperaturesOption = 8,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    out_dir: Annotated[
        Path | None, typer.Option("--out", help="Output directory (default: beside SAMPLES).")
    ] = None,
    merge_duplicates: Annotated[
        bool, typer.Option("--merge-duplicates", help="Merge repeated rows (combined σ).")
    ] = False,
    bin_deg: BinOption = None,
    no_widen: NoWidenOption = False,
) -> None:
    """Fit a model to SAMPLES: writes fit-NAME.json, fit-NAME.h5 and material-NAME.xml
    (Mitsuba 3); with several models or --compare-shared also compare.json (ranked by
    PSIS-LOO where it is reliable; the others listed with the reason).
    The samples contract (columns, units, flags, metadata) is in docs/formats.md."""
    from gonio.errors import UserError

    if censor and drop_flagged:
        raise UserError("--censor and --drop-flagged contradict each other: give one")
    if censor:
        out.print("note: --censor is the default now (it does nothing); --drop-flagged excludes")
    table = _read_for_fit(samples, bin_deg, merge_duplicates)
    sampling = (likelihood, walkers, steps, time_budget, sampler, temperatures)
    model, fixed, prior_cfg, cands, skipped, mcmc = _checked_fit_args(
        table, model, fix, priors, (option, shared, compare_shared), sampling
    )
    chans = [c.strip() for c in channels.split(",")] if channels else None
    from fitting.fit import FitOptions

    base = FitOptions(
        model=model,
        fix=fixed,
        priors=prior_cfg,
        channels=chans,
        mcmc=None if no_mcmc else mcmc,
        seed=seed,
        likelihood=likelihood,
        censor=not drop_flagged,
        binned_source=samples if "gonio.binned" in table.metadata else None,
        widen_for_mismatch=not no_widen,
    )
    setups = _check_setups(table, cands, base, compare_shared, priors)
    _show_flag_counts(table, chans, drop_flagged)
    dest = Path(out_dir or samples.parent)
    _run_fits(table, (base, setups, skipped), cands, (compare_shared, accept_poor_fit), dest)


def _read_for_fit(samples: Path, bin_deg: float | None, merge_duplicates: bool):
    """The samples table, binned (streamed) when asked or when it is large; one line says so."""
    import numpy as np

    from brdfdata.samples import read_samples
    from brdfdata.samples.table import EXCLUDING
    from fitting.binning import AUTO_BIN_DEG, AUTO_BIN_ROWS, BinOptions, read_binned, rows_in
    from gonio.errors import UserError

    if bin_deg is not None and not bin_deg >= 0:  # negative or NaN
        raise UserError(f"--bin {bin_deg}: give a cell width in degrees, or 0 for every row")
    if bin_deg is None:
        bin_deg = AUTO_BIN_DEG if rows_in(samples) > AUTO_BIN_ROWS else 0.0
    if bin_deg == 0:
        table = read_samples(samples, merge_duplicates=merge_duplicates)
    else:
        table, report = read_binned(
            samples, BinOptions(width_deg=bin_deg), merge_duplicates=merge_duplicates
        )
        out.print(report.line(), markup=False)
    if not np.any((np.asarray(table.flags, np.int64) & EXCLUDING) == 0):
        why = "every row is flagged MASKED or BELOW_HORIZON — check the table's flags column"
        raise UserError(f"{samples}: no usable samples to fit: {why}")
    return table


def _run_fits(table, fitting_plan, cands, flags, dest: Path) -> None:
    """One fit (or a ranked comparison), each shown with its verdicts; exit 3 on a fail.
    ``fitting_plan``: the base FitOptions, each candidate's checked setup and the models left
    out (listed in compare.json)."""
    from fitting.compare import candidate_options, run_comparison
    from fitting.fit import fit_samples
    from fitting.priors import PriorsError
    from gonio.errors import UserError

    base, setups, skipped = fitting_plan
    for s in skipped:
        out.print(f"not fitted: {s.model}: {s.reason}", markup=False, soft_wrap=True)
    compare_shared, accept_poor_fit = flags
    results = {}

    def show(c, result) -> None:
        _show_fit(c, result, dest)
        results[c.label] = result

    try:
        if len(cands) == 1 and not compare_shared:
            c = cands[0]
            opts = candidate_options(base, c, comparison=False)
            fit = fit_samples(table, opts, out_dir=dest, progress=True, setup=setups[c.label])
            show(c, fit)
            verdict_exit(results[c.label].verdicts, accept_poor_fit)
            return
        ranked, _ = run_comparison(
            table,
            cands,
            base,
            out_dir=dest,
            on_fit=show,
            progress=True,
            setups=setups,
            skipped=skipped,
        )
    except PriorsError as exc:
        raise UserError(str(exc).splitlines()[0]) from None
    _show_comparison(ranked, dest)
    best = ranked[0] if ranked and ranked[0].rank == 1 else None
    if best is None:  # no score is reliable: there is no best model to stand on
        what = "no model could be ranked (each one's reason is above; compare.json lists them)"
        if accept_poor_fit:
            out.print(f"{what} — accepted (--accept-poor-fit)", soft_wrap=True)
            return
        out.print(f"{what} — rerun with --accept-poor-fit to accept", soft_wrap=True)
        raise typer.Exit(code=3)
    # A comparison ranks poor models below good ones: only the best one's fails decide the exit.
    verdict_exit(results[best.label].verdicts, accept_poor_fit, best.label)


def _check_setups(table, cands, base, compare_shared: bool, priors_path) -> dict:
    """Each candidate's fit setup (fitting.fit.fit_setup: model, channels, parameter space),
    built before anything is printed or written — so a priors file, --channels, --fix or
    --shared that does not suit the model is the command's only line — and then used by its
    fit. Returns {label: FitSetup}."""
    from fitting.compare import candidate_options
    from fitting.fit import fit_setup
    from fitting.priors import PriorsError
    from gonio.errors import UserError

    comparison = len(cands) > 1 or compare_shared  # the run_comparison path of _run_fits
    setups = {}
    for c in cands:
        try:
            setups[c.label] = fit_setup(table, candidate_options(base, c, comparison=comparison))
        except (PriorsError, ValueError) as exc:
            line = str(exc).splitlines()[0]
            if line.startswith("channel(s) "):  # as the option is named on this command line
                line = "--channels " + line.removeprefix("channel(s) ").replace(
                    " not in the samples", ": not in the samples", 1
                )
            where = f"{priors_path}: " if priors_path is not None and "prior" in line else ""
            raise UserError(f"{where}{line}") from None
    return setups


def _show_flag_counts(table, chans, drop_flagged: bool) -> None:
    """One line: how many DARK and SATURATED samples the fitted channels hold, and their fate."""
    import numpy as np

    from brdfdata.samples import Flags

    sel = np.isin(table.channel, chans) if chans else np.ones(len(table), bool)
    flags = np.asarray(table.flags, dtype=np.int64)[sel]
    sat = int(np.sum((flags & Flags.SATURATED) != 0))
    dark = int(np.sum(((flags & Flags.DARK) != 0) & ((flags & Flags.SATURATED) == 0)))
    fate = (
        "dropped (--drop-flagged)"
        if drop_flagged
        else "censored: they enter as bounds (--drop-flagged to exclude them)"
    )
    out.print(f"flagged samples: {dark} DARK, {sat} SATURATED of {int(sel.sum())}; {fate}")


def _checked_fit_args(table, model: str, fix, priors, cand_args, mcmc_args):
    """(model, fixed values, priors, candidates, models left out, the sampler's options) from
    the fit command's options for the samples ``table``, each mistake one line (UserError)."""
    from fitting import models
    from fitting.compare import candidates
    from fitting.likelihood import LIKELIHOOD_KINDS
    from fitting.priors import PriorsError, load_priors
    from gonio.errors import UserError

    option, shared, compare_shared = cand_args
    from fitting.mcmc import SAMPLERS, McmcOptions

    likelihood, walkers, steps, time_budget, sampler, temperatures = mcmc_args
    if model != "all" and "all" in (n.strip() for n in model.split(",")):
        raise UserError(f"--model {model}: all names every model; give it alone")
    if model != "all":
        try:  # an alias (e.g. "ts") names its model
            model = ",".join(models.resolve(n.strip()) for n in model.split(",") if n.strip())
        except models.UnknownModelError as exc:
            raise UserError(f"{exc}, all") from None
        if not model:
            raise UserError("--model: give a model name (see `gonio models`), or all")
    if likelihood not in LIKELIHOOD_KINDS:
        raise UserError(f"--likelihood {likelihood!r}: use one of {', '.join(LIKELIHOOD_KINDS)}")
    if walkers < 2 or steps < 1:
        raise UserError("--walkers must be ≥ 2 and --steps ≥ 1")
    if time_budget is not None and not 0 < time_budget < 1e7:
        raise UserError(f"--time-budget {time_budget}: give seconds > 0 (or leave it out)")
    if sampler not in SAMPLERS:
        raise UserError(f"--sampler {sampler!r}: use one of {', '.join(SAMPLERS)}")
    if not 1 <= temperatures <= 64:
        raise UserError(f"--temperatures {temperatures}: give 1 to 64 (1: no tempering)")
    try:
        fixed = {k: float(v) for k, v in kv_pairs(fix, "--fix").items()}
    except ValueError as exc:
        raise UserError(f"--fix: {exc}") from None
    shared_names = tuple(x.strip() for x in shared.split(",") if x.strip())
    try:
        prior_cfg = load_priors(priors) if priors is not None else None
        opts, directions = kv_pairs(option, "--option"), (table.wi, table.wo)
        cands, skipped = candidates(
            model, opts, shared_names, compare_shared=compare_shared, directions=directions
        )
    except (PriorsError, TypeError, ValueError) as exc:
        raise UserError(str(exc).splitlines()[0]) from None
    mcmc = McmcOptions(walkers, steps, time_budget, sampler=sampler, temperatures=temperatures)
    return model, fixed, prior_cfg, cands, skipped, mcmc


def _show_fit(c, result, dest: Path) -> None:
    """Export the material for Mitsuba and print the parameter table of one fit."""
    from fitting.export import export_material

    export = export_material(result, dest / f"material-{c.label}.xml")
    xml = export.xml_path
    if export.table_path is not None:  # not a built-in: say how close the table is
        out.print(f"note: {xml.name}: {export.note}", markup=False, soft_wrap=True)
    t = Table(title=f"{c.label} fit ({xml.name})")
    for col in ("parameter", "MAP", "median", "p16", "p84"):
        t.add_column(col, justify="right")
    for name, p in result.to_dict()["parameters"].items():
        t.add_row(name, *(f"{p[k]:.5g}" for k in ("map", "median", "p16", "p84")))
    out.print(t)
    for note in result.extras.get("notes", []):
        out.print(f"note: {note}", markup=False, soft_wrap=True)
    modes = result.diagnostics.get("modes")
    if modes is not None:  # a tempered chain: how many modes, and the mass of each
        out.print(f"posterior: {modes['words']}", markup=False, soft_wrap=True)
    show_verdicts(result.verdicts or [], f"{c.label} verdicts")


_STATUS_STYLE = {"ok": "green", "warning": "yellow", "fail": "bold red"}


def show_verdicts(verdicts, title: str = "verdicts") -> None:
    """The verdict table (fitting.verdicts): status word, reason, advice."""
    if not verdicts:
        return
    t = Table(title=title)
    for col in ("verdict", "status", "reason", "advice"):
        t.add_column(col, overflow="fold")
    for v in verdicts:
        style = _STATUS_STYLE.get(v["status"], "")
        status = plain(v["status"])
        status.stylize(style)
        t.add_row(plain(v["name"]), status, plain(v["reason"]), plain(v["advice"]))
    out.print(t)  # a table when it fits, else its rows as records (gonio.cli._app)


def verdict_exit(verdicts, accept: bool, label: str | None = None) -> None:
    """The last line, and exit 3 when a verdict failed (unless --accept-poor-fit)."""
    from fitting.verdicts import failed

    names = failed(verdicts or [])
    if not names:
        return
    what = f"{label} fit" if label else "fit"
    if accept:
        out.print(f"{what} written; it failed: {', '.join(names)} — accepted (--accept-poor-fit)")
        return
    out.print(
        f"{what} written, but it failed: {', '.join(names)} — rerun with --accept-poor-fit to "
        "accept",
        soft_wrap=True,
    )
    raise typer.Exit(code=3)


def _show_comparison(ranked, dest: Path) -> None:
    """The model-comparison table (ranked best first, then the unranked), the margin of each
    ranked model over the best in words, and why each unranked one is not ranked."""
    from fitting.compare import margin_words

    def num(x: float) -> str:
        if not math.isfinite(x):
            return "–"
        return f"{x:.0f}" if abs(x) >= 100 else f"{x:.1f}"

    order = "best first" if ranked[0].rank == 1 else "none could be ranked"
    t = Table(title=f"Model comparison, {ranked[0].n} samples ({order}; elpd in nats)")
    for col in (
        "rank",
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
    for r in ranked:
        t.add_row(
            str(r.rank) if r.rank else "not ranked",
            r.label,
            ",".join(r.shared) or "–",
            str(r.k),
            f"{num(r.elpd_loo)} ± {num(r.se_loo)}",
            num(r.p_loo),
            num(r.waic),
            f"{num(r.d_elpd)} ± {num(r.d_se)}" if r.rank else "–",
            f"{r.khat_max:.2f}",
            num(r.aic),
            num(r.bic),
        )
    out.print(t)  # a table when it fits, else its rows as records (gonio.cli._app)
    best = ranked[0] if ranked[0].rank == 1 else None
    for r in ranked:
        if r.rank and r is not best:
            out.print(margin_words(best, r), markup=False, soft_wrap=True)
    for r in ranked:
        if not r.rank:
            out.print(f"not ranked: {r.label}: {r.why_unranked}", markup=False, soft_wrap=True)
    notes: dict[str, list[str]] = {}  # one line per note, naming every model it is about
    for r in ranked:
        for w in r.warnings:
            notes.setdefault(w, []).append(r.label)
    for w, labels in notes.items():
        who = "every model" if len(labels) == len(ranked) > 1 else ", ".join(labels)
        out.print(f"note: {who}: {w}", markup=False, soft_wrap=True)
    out.print(str(dest / "compare.json"))


@app.command(rich_help_panel=ANALYSIS)
def report(
    run_dir: Annotated[Path | None, typer.Argument(help="Run directory.")] = None,
    samples: Annotated[
        Path | None, typer.Option("--samples", help="Samples table of a fit not made in a run.")
    ] = None,
    fit_json: Annotated[Path | None, typer.Option("--fit", help="Its fit-MODEL.json.")] = None,
    out_path: Annotated[
        Path | None, typer.Option("--out", help="With --fit: where (default beside the fit).")
    ] = None,
) -> None:
    """Write RUN_DIR/report.html, or with --samples S --fit F.json a report of any fit."""
    from gonio.errors import UserError
    from gonio.report import write_fit_report, write_report

    if samples is not None or fit_json is not None or out_path is not None:
        if run_dir is not None or samples is None or fit_json is None:
            raise UserError("report: give RUN_DIR, or --samples SAMPLES --fit FIT.json [--out]")
        out.print(str(write_fit_report(samples, fit_json, out_path)))
        return
    if run_dir is None:
        raise UserError("report: give RUN_DIR, or --samples SAMPLES --fit FIT.json [--out]")
    out.print(str(write_report(run_dir)))


# -- offline data: import, export, the data files (issue 16; logic in brdfdata.formats) -----------
@app.command(name="import", rich_help_panel=DATA)
def import_cmd(
    fmt: Annotated[str, typer.Argument(metavar="FORMAT", help="rgl | merl | csv")],
    file: Annotated[Path, typer.Argument(help="The file to convert.")],
    out_path: Annotated[Path, typer.Option("--out", help="Samples table to write.")] = ...,  # type: ignore[assignment]
    grid: Annotated[
        str | None,
        typer.Option(help="rgl/merl: 'measured' or theta_i=0:60:15,theta_o=0:80:5,phi_o=… (deg)."),
    ] = None,
    sigma: Annotated[
        str | None, typer.Option(help="COLUMN | rel=0.02 | abs=VALUE (1/sr) | repeats.")
    ] = None,
    angles: Annotated[str, typer.Option(help="csv: angle unit, deg or rad.")] = "rad",
    column: Annotated[
        list[str], typer.Option(help="csv: CONTRACT=FILE_COLUMN, e.g. theta_i=ti.")
    ] = [],  # noqa: B006
    value: Annotated[list[str], typer.Option(help="csv: per-channel values, CHANNEL=COLUMN.")] = [],  # noqa: B006
    channel_column: Annotated[
        str, typer.Option(help="csv: column naming the channel.")
    ] = "channel",
    channel: Annotated[str, typer.Option(help="csv: channel of a lone f column.")] = "Y",
    delimiter: Annotated[str | None, typer.Option(help="csv: field separator (sniffed).")] = None,
    wavelengths: Annotated[str | None, typer.Option(help="rgl spectral: nm list, 450,550.")] = None,
    merge_duplicates: Annotated[
        bool, typer.Option("--merge-duplicates", help="Merge repeated rows (combined σ).")
    ] = False,
) -> None:
    """Convert an RGL .bsdf, a MERL .binary or a delimited text table into a samples table
    (docs/formats.md), with the source file and its SHA-256 in the Parquet metadata."""
    from brdfdata.formats.convert import ImportOptions, import_samples
    from brdfdata.samples import write_samples
    from gonio.errors import UserError

    try:
        wl = tuple(float(w) for w in wavelengths.split(",")) if wavelengths else None
    except ValueError:
        raise UserError(
            f"--wavelengths {wavelengths!r}: expected numbers in nm, e.g. 450,550"
        ) from None
    opts = ImportOptions(
        grid=grid,
        sigma=sigma,
        angles=angles,
        columns=kv_pairs(column, "--column"),
        values=kv_pairs(value, "--value"),
        channel_column=channel_column,
        default_channel=channel,
        delimiter=delimiter,
        wavelengths_nm=wl,
        merge_duplicates=merge_duplicates,
    )
    table = import_samples(fmt, file, opts)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    write_samples(out_path, table)
    flagged = int((table.flags != 0).sum())
    chans = ",".join(table.channels)
    out.print(
        f"{out_path}: {len(table)} samples ({flagged} flagged), channels {chans}", soft_wrap=True
    )


@app.command(name="export", rich_help_panel=DATA)
def export_cmd(
    fmt: Annotated[str, typer.Argument(metavar="FORMAT", help="merl | csv")],
    source: Annotated[Path, typer.Argument(help="SAMPLES.parquet, or for merl a fit-MODEL.json.")],
    out_path: Annotated[Path, typer.Option("--out", help="File to write.")] = ...,  # type: ignore[assignment]
    angles: Annotated[str, typer.Option(help="csv: angle unit, deg or rad.")] = "rad",
) -> None:
    """Write samples (or, for MERL, a fitted model) in another format: the twins of `import`."""
    from brdfdata.formats.convert import export_file
    from fitting.export import export_fit

    export = export_fit if source.suffix.lower() == ".json" else export_file
    path, what = export(fmt, source, out_path, angles)
    out.print(f"{path}: {what}", soft_wrap=True)


data_app = typer.Typer(no_args_is_help=True, help="Real data files (data/README.md).")


app.add_typer(data_app, name="data", rich_help_panel=DATA)


@data_app.command("list")
def data_list() -> None:
    """Every known data file: where it is found and whether its SHA-256 matches."""
    from brdfdata.data_paths import FETCHED, DataNotFound, manifest, verify

    t = Table(title="gonio data (search order: $GONIO_DATA, data/, share/gonio/data, cache)")
    for col in ("file", "shipped", "status", "path"):
        t.add_column(col)
    for rel, entry in sorted({**manifest(), **FETCHED}.items()):
        try:
            path, ok = verify(rel)
            status = "ok" if ok else "HASH MISMATCH"
        except DataNotFound:
            path, status = "", f"missing (gonio data fetch {rel.split('/')[0]})"
        t.add_row(plain(rel), "yes" if entry.shipped else "no", plain(status), plain(path))
    out.print(t)


@data_app.command("fetch")
def data_fetch(
    group: Annotated[str, typer.Argument(help="A data group not shipped, e.g. camera_raw.")],
    source: Annotated[
        Path | None, typer.Option("--from", help="Copy from this folder instead of downloading.")
    ] = None,
) -> None:
    """Download (or copy) a data group into the cache, checking every SHA-256."""
    from brdfdata.data_paths import fetch

    for path in fetch(group, source):
        out.print(str(path))


@app.command(name="models", rich_help_panel=ANALYSIS)
def models_cmd(
    name: Annotated[
        str | None, typer.Argument(help="One model: a name, named variant or alias.")
    ] = None,
    option: Annotated[
        list[str], typer.Option("--option", help="Option KEY=VALUE of NAME (shows its parameters).")
    ] = [],  # noqa: B006
    check: Annotated[
        bool, typer.Option("--check", help="Measure properties of each model.")
    ] = False,
) -> None:
    """List the BRDF models: parameters (units, bounds), options (allowed values, default *),
    aliases, declared properties, reference; --check measures the properties."""
    from fitting import models
    from gonio.errors import UserError

    opts = kv_pairs(option, "--option")
    if opts and name is None:
        raise UserError("--option needs a model NAME (gonio models NAME --option KEY=VALUE)")
    try:
        names = [models.resolve(name)] if name is not None else models.names()
        built = {n: models.get(n, **opts) for n in names}
    except (KeyError, ValueError) as exc:
        raise UserError(str(exc).splitlines()[0]) from None

    t = Table(title="BRDF models (f_r in 1/sr)")
    for col in ("model", "parameter", "unit", "lower", "upper", "sampled in"):
        t.add_column(col)
    for n, m in built.items():
        for i, p in enumerate(m.parameters):
            t.add_row(
                n if i == 0 else "",
                p.name,
                p.unit,
                f"{p.lower:g}",
                f"{p.upper:g}",
                "log" if p.log else "linear",
            )
    out.print(t)
    ot = Table(title="Options (* = default), aliases, declared properties, reference")
    for col in ("model", "options", "aliases", "properties", "needs", "reference"):
        ot.add_column(col, overflow="fold")
    for n, m in built.items():
        e = models.entry(n)
        lines = [o.describe() for o in e.options]
        if e.base is not None:
            fixed = ", ".join(f"{k}={v}" for k, v in e.fixed.items())
            lines.insert(0, f"variant of {e.base}: {fixed}")
        props = [k.replace("_", "-") for k in ("reciprocal", "energy_conserving", "isotropic")]
        flags = [
            p if m.flags.get(k) else f"not {p}"
            for k, p in zip(("reciprocal", "energy_conserving", "isotropic"), props, strict=True)
        ]
        ot.add_row(
            n,
            "\n".join(lines) or "–",
            ", ".join(e.aliases) or "–",
            "\n".join(flags),
            ", ".join(e.needs) or "–",
            e.reference,
        )
    out.print(ot)
    if not check:
        return
    from fitting.models.properties import property_table

    rows = property_table(names=names)
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
        pt.add_row(
            r["model"],
            ",".join(f"{v}" for v in r["options"].values()) or "–",
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
        "seed's Phong k_s(l̂·r̂)^n is reciprocal but not energy conserving; anisotropic models "
        "are not isotropic by design."
    )

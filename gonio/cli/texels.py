"""Commands that fit on a Dask cluster (issue 20): fit-texels (a spatially varying sample, one
fit per texel) and fit-batch (a material library, one fit per samples table)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from gonio.cli._app import SCALE_OUT, app, kv_pairs, out

_SCHEDULER = typer.Option(
    "--scheduler",
    help="Dask scheduler address, e.g. tcp://host:8786 (default: a LocalCluster here).",
)
_WORKERS = typer.Option("--workers", help="LocalCluster worker processes (default: one per core).")
_MODEL = typer.Option("--model", help="Model name (see `gonio models`).")
_OPTION = typer.Option("--option", help="Model option KEY=VALUE.")


def _fit_options(model: str, option: list[str], shared: str, knobs: tuple[int, int, int, bool]):
    """FitOptions for a per-texel or per-table fit; mistakes are one-line UserErrors."""
    from fitting import models
    from fitting.compare import shared_for
    from fitting.fit import FitOptions
    from fitting.texels import texel_fit_options
    from gonio.errors import UserError

    walkers, steps, seed, discrepancy = knobs
    opts = kv_pairs(option, "--option")
    try:
        model = models.resolve(model)
        # `--shared m`, the default, names the lobe's width: a model without one shares nothing
        shared_names = shared_for(
            models.get(model, **opts),
            tuple(x.strip() for x in shared.split(",") if x.strip()),
            model,
        )
    except (models.UnknownModelError, TypeError, ValueError) as exc:
        raise UserError(str(exc).splitlines()[0]) from None
    if walkers < 2 or steps < 1:
        raise UserError("--walkers must be ≥ 2 and --steps ≥ 1")
    base = FitOptions(
        model=model,
        model_options=opts,
        shared=shared_names,
        seed=seed,
        discrepancy=discrepancy,
    )
    return texel_fit_options(base, walkers=walkers, steps=steps)


@app.command(name="fit-texels", rich_help_panel=SCALE_OUT)
def fit_texels_cmd(
    samples: Annotated[
        Path, typer.Argument(help="Per-texel samples (gonio calibrate --per-texel).")
    ],
    model: Annotated[str, _MODEL] = "torrance-sparrow",
    option: Annotated[list[str], _OPTION] = [],  # noqa: B006
    shared: Annotated[str, typer.Option(help="Comma list of parameters shared by channels.")] = "m",
    scheduler: Annotated[str | None, _SCHEDULER] = None,
    workers: Annotated[int | None, _WORKERS] = None,
    walkers: Annotated[int, typer.Option(help="emcee walkers per texel.")] = 16,
    steps: Annotated[int, typer.Option(help="Maximum MCMC steps per texel.")] = 600,
    seed: Annotated[int, typer.Option(help="Seed; texel t uses a stream of (seed, t).")] = 0,
    discrepancy: Annotated[
        bool, typer.Option(help="Fit a fractional model-discrepancy term per texel.")
    ] = True,
    chunk: Annotated[int, typer.Option(help="Texels per Dask task.")] = 16,
    min_samples: Annotated[int, typer.Option(help="Fewest good samples a texel needs.")] = 20,
    out_dir: Annotated[
        Path | None, typer.Option("--out", help="Output folder (default: SAMPLES-texels/ beside).")
    ] = None,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Fit every texel of SAMPLES (least squares, then MCMC) as Dask tasks: writes
    OUT/texels.parquet (one row per texel), OUT/maps/ (PNG previews, EXR textures, a Mitsuba
    material) and OUT/chunks/ (finished tasks; a rerun fits only what is missing)."""
    from brdfdata.samples import read_samples
    from fitting.texels import texel_groups
    from gonio.scaleout.cluster import dask_client
    from gonio.scaleout.texels import TexelJob, run_texel_job

    options = _fit_options(model, option, shared, (walkers, steps, seed, discrepancy))
    texel_groups(read_samples(samples))  # a missing file or texel column: one line, no cluster
    dest = out_dir or samples.with_name(samples.stem + "-texels")
    job = TexelJob(samples, dest, options, chunk_texels=chunk, min_samples=min_samples)
    with dask_client(scheduler, workers) as client:
        res = run_texel_job(job, client, progress=progress)
    rate = res.fitted_now / res.wall_s if res.wall_s > 0 else 0.0
    out.print(
        f"{res.table_path}: {res.texels} texels ({res.fitted_now} fitted now, "
        f"{res.chunks_skipped} chunk(s) already done); {res.wall_s:.1f} s, {rate:.2f} texels/s"
    )


@app.command(name="fit-batch", rich_help_panel=SCALE_OUT)
def fit_batch_cmd(
    tables: Annotated[str, typer.Argument(help="A folder of *.parquet samples, or a glob.")],
    model: Annotated[str, _MODEL] = "torrance-sparrow",
    option: Annotated[list[str], _OPTION] = [],  # noqa: B006
    shared: Annotated[str, typer.Option(help="Comma list of parameters shared by channels.")] = "m",
    scheduler: Annotated[str | None, _SCHEDULER] = None,
    workers: Annotated[int | None, _WORKERS] = None,
    walkers: Annotated[int, typer.Option(help="emcee walkers per table.")] = 32,
    steps: Annotated[int, typer.Option(help="Maximum MCMC steps per table.")] = 2000,
    seed: Annotated[int, typer.Option(help="Seed; table i uses a stream of (seed, name).")] = 0,
    discrepancy: Annotated[bool, typer.Option(help="Fit a model-discrepancy term.")] = True,
    out_dir: Annotated[
        Path, typer.Option("--out", help="Output folder for batch.parquet and the per-table rows.")
    ] = Path("batch"),
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Fit many samples tables (a material library) as Dask tasks, one summary row per table in
    OUT/batch.parquet; finished tables are kept in OUT/tables/ and skipped on a rerun."""
    from gonio.scaleout.batch import BatchJob, find_tables, run_batch_job
    from gonio.scaleout.cluster import dask_client

    options = _fit_options(model, option, shared, (walkers, steps, seed, discrepancy))
    job = BatchJob(find_tables(tables), out_dir, options)
    with dask_client(scheduler, workers) as client:
        res = run_batch_job(job, client, progress=progress)
    out.print(
        f"{res.table_path}: {res.tables} table(s) ({res.fitted_now} fitted now); {res.wall_s:.1f} s"
    )

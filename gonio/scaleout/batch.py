"""Batches of samples tables fitted as Dask tasks (issue 20): `gonio fit-batch DIR_OR_GLOB`.

One task per table: the client reads the table and sends it (workers need no shared file
system), the worker fits it (fitting.fit.fit_samples) with the seed stream of (seed, the table's
SHA-256) — so a table's result depends on its content, not on its place in the batch or the
worker — and the client writes its one summary row (fitting.texels.result_row, plus ``table``,
``sha256``, ``n_samples``, ``cpu_s``) as soon as it completes to ``OUT/tables/NAME-SHA.parquet``
(atomic, never overwritten; gonio.scaleout.cluster). A rerun skips every table with a row on disk; a
killed worker's task is rerun by Dask. ``OUT/batch.parquet`` gathers the rows, one per table.
"""

from __future__ import annotations

import glob
import time
from dataclasses import dataclass
from pathlib import Path

from gonio.errors import UserError
from gonio.scaleout.cluster import (
    claim_out_dir,
    job_fingerprint,
    read_rows,
    sha256_file,
    write_rows,
)

__all__ = ["BatchJob", "BatchJobResult", "find_tables", "run_batch_job"]


@dataclass(frozen=True)
class BatchJob:
    tables: list[Path]
    out_dir: Path
    options: object  # fitting.fit.FitOptions


@dataclass
class BatchJobResult:
    table_path: Path
    tables: int
    fitted_now: int
    wall_s: float


def find_tables(spec: str) -> list[Path]:
    """The samples tables of a folder (its *.parquet files) or a glob, sorted; UserError when
    there are none."""
    path = Path(spec)
    found = sorted(path.glob("*.parquet")) if path.is_dir() else sorted(map(Path, glob.glob(spec)))
    found = [p for p in found if p.is_file()]
    if not found:
        raise UserError(f"{spec}: no samples tables (*.parquet) there")
    return found


def _fit_table(table, name: str, sha: str, options) -> dict:
    """The task run on a worker: the summary row of one table."""
    from fitting.fit import fit_samples
    from fitting.texels import result_row, texel_seed

    cpu0 = time.process_time()
    good = table.good()
    opt = options.replace(seed=texel_seed(options.seed, int(sha[:12], 16)))
    row = {"table": name, "sha256": sha, "n_samples": len(good)}
    row.update(result_row(fit_samples(good, opt)), cpu_s=time.process_time() - cpu0)
    return row


def run_batch_job(job: BatchJob, client, *, progress: bool = True) -> BatchJobResult:
    """Fit every table of `job` on `client`'s cluster (see the module docstring)."""
    from distributed import as_completed

    from brdfdata.samples import read_samples
    from plumbing.progress import Progress

    t0 = time.perf_counter()
    out_dir = Path(job.out_dir)
    shas = {p: sha256_file(p) for p in job.tables}
    record = job_fingerprint("batch", job.options, 1, 0)
    key = claim_out_dir(out_dir, record)
    (out_dir / "tables").mkdir(exist_ok=True)

    def row_path(p: Path) -> Path:
        return out_dir / "tables" / f"{p.stem}-{shas[p][:12]}.parquet"

    todo = [p for p in job.tables if not row_path(p).exists()]
    futures = {}
    for p in todo:
        table = read_samples(p)
        fut = client.submit(
            _fit_table, table, str(p), shas[p], job.options, key=f"gonio-batch-{key}-{shas[p]}"
        )
        futures[fut] = p
    done = len(job.tables) - len(todo)
    with Progress("fitting tables", len(job.tables), completed=done, enabled=progress) as bar:
        for fut in as_completed(futures):
            p = futures[fut]
            try:
                write_rows(row_path(p), [fut.result()])
            except FileExistsError:  # another client of the same job wrote it first
                pass
            bar.advance()
            fut.release()
    rows = [r for p in job.tables for r in read_rows(row_path(p))]
    out = write_rows(out_dir / "batch.parquet", rows, overwrite=True)
    return BatchJobResult(out, len(job.tables), len(todo), time.perf_counter() - t0)

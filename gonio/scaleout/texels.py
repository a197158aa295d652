"""Per-texel and batch fits as Dask tasks (issue 20): `gonio fit-texels` and `gonio fit-batch`.

The science is in fitting.texels (grouping, the fit of one texel, seeds from (seed, texel));
this module only distributes it. Without a scheduler address a `distributed.LocalCluster` of
one single-threaded worker process per core is started (the fits are CPU-bound Python + numba:
processes, not threads); with one, a `Client` connects to any Dask cluster (`dask scheduler`,
`dask worker tcp://HOST:8786` on other hosts). Workers only compute: each task gets its chunk's
rows of the samples table and returns result rows, and the *client* writes them, so the workers
need no shared file system.

Crash safety: texels are fitted in chunks of ``chunk_texels``; each finished chunk is written by
the client as soon as its task completes, to ``OUT/chunks/chunk-NNNNN.parquet`` atomically and
never overwritten (plumbing.atomic: temp file, fsync, link). A rerun reads ``OUT/job.json``
(what defines the job: the samples file's SHA-256, the fit options, the chunking) and submits
only the chunks without a file — a job with other options is refused, never mixed in. A worker
killed mid-task loses only that task: the scheduler reruns it on another worker (Dask's
``allowed-failures``), and as a chunk is written once, no texel appears twice. When every chunk
is in, ``OUT/texels.parquet`` (one row per texel, sorted) and the maps (gonio.scaleout.maps) are
assembled from the chunk files. Task keys carry the job fingerprint, so a result can be
reused but never confused with another job's on a shared scheduler.
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gonio.errors import UserError
from gonio.scaleout.cluster import (
    claim_out_dir,
    job_fingerprint,
    read_rows,
    sha256_file,
    write_rows,
)

__all__ = ["TexelJob", "TexelJobResult", "run_texel_job"]


@dataclass(frozen=True)
class TexelJob:
    """One `fit-texels` job: the samples file, the output folder, the fit options
    (fitting.fit.FitOptions, typically from fitting.texels.texel_fit_options), texels per task,
    and the fewest good samples a texel needs to be fitted."""

    samples: Path
    out_dir: Path
    options: object  # fitting.fit.FitOptions
    chunk_texels: int = 16
    min_samples: int = 20


@dataclass
class TexelJobResult:
    table_path: Path
    texels: int  # texels in the samples table
    fitted_now: int  # texels fitted by this call (the rest were already on disk)
    chunks_skipped: int
    wall_s: float
    maps: list[Path]


def _fit_chunk(table, texels: list[int], options, min_samples: int) -> list[dict]:
    """The task run on a worker: result rows of one chunk (fitting.texels.fit_texels)."""
    from fitting.texels import fit_texels

    return fit_texels(table, texels, options, min_samples=min_samples)


def _chunk_path(out_dir: Path, k: int) -> Path:
    return out_dir / "chunks" / f"chunk-{k:05d}.parquet"


def run_texel_job(job: TexelJob, client, *, progress: bool = True) -> TexelJobResult:
    """Fit every texel of `job.samples` on `client`'s cluster (see the module docstring)."""
    from brdfdata.samples import read_samples
    from fitting.texels import texel_grid, texel_groups

    t0 = time.perf_counter()
    samples = Path(job.samples)
    table = read_samples(samples)
    groups = texel_groups(table)
    if not groups:
        raise UserError(f"{samples}: no sample lies on a texel (every texel index is −1)")
    if job.chunk_texels < 1:
        raise UserError("--chunk must be ≥ 1")
    record = job_fingerprint(sha256_file(samples), job.options, job.chunk_texels, job.min_samples)
    key = claim_out_dir(Path(job.out_dir), record)
    texels = sorted(groups)
    chunks = [texels[i : i + job.chunk_texels] for i in range(0, len(texels), job.chunk_texels)]
    todo = [k for k in range(len(chunks)) if not _chunk_path(job.out_dir, k).exists()]
    done_texels = sum(len(c) for k, c in enumerate(chunks) if k not in set(todo))
    fitted_now = _run_chunks(client, table, groups, chunks, todo, job, key, done_texels, progress)
    rows = [r for k in range(len(chunks)) for r in read_rows(_chunk_path(job.out_dir, k))]
    rows.sort(key=lambda r: r["texel"])
    out = Path(job.out_dir) / "texels.parquet"
    # Assembled from the chunk files, so rewriting it gives the same table.
    write_rows(out, rows, overwrite=True)
    from gonio.scaleout.maps import write_maps

    n_x, n_y = texel_grid(table)
    size_m = json.loads(table.metadata.get("gonio.texels") or "{}").get("size_m")
    maps = write_maps(rows, n_x, n_y, Path(job.out_dir), job.options, size_m)
    return TexelJobResult(
        out, len(texels), fitted_now, len(chunks) - len(todo), time.perf_counter() - t0, maps
    )


def _run_chunks(client, table, groups, chunks, todo, job, key, done_texels, progress) -> int:
    """Submit the chunks `todo`, write each as it completes; returns the texels fitted."""
    from distributed import as_completed

    from plumbing.progress import Progress

    total = sum(len(c) for c in chunks)
    futures = {}
    for k in todo:
        rows = np.concatenate([groups[t] for t in chunks[k]])
        mask = np.zeros(len(table), dtype=bool)
        mask[rows] = True
        fut = client.submit(
            _fit_chunk,
            table.select(mask),
            chunks[k],
            job.options,
            job.min_samples,
            key=f"gonio-texels-{key}-{k:05d}",
        )
        futures[fut] = k
    fitted = 0
    t0 = time.perf_counter()
    with Progress("fitting texels", total, completed=done_texels, enabled=progress) as bar:
        for fut in as_completed(futures):
            k = futures[fut]
            rows = fut.result()
            with contextlib.suppress(FileExistsError):  # another client of the same job
                write_rows(_chunk_path(job.out_dir, k), rows)
            fitted += len(rows)
            rate = fitted / max(time.perf_counter() - t0, 1e-9)
            bar.update(
                completed=done_texels + fitted,
                description=f"fitting texels ({rate:.2f} texels/s)",
            )
            fut.release()
    return fitted

"""What every Dask job of gonio shares (issue 20): the client, and crash-safe result files.

`dask_client` connects to a scheduler address (`dask scheduler` + `dask worker` processes, on this
or other hosts) or starts a `distributed.LocalCluster` of single-threaded worker processes (the
fits are CPU-bound Python + numba: processes, not threads). Result rows go to Parquet files
written atomically and never overwritten (plumbing.atomic). `claim_out_dir` ties an output
folder to one job (its `job.json`), so a rerun continues the same job and a job with other
inputs is refused rather than mixed in.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gonio.errors import UserError
from plumbing.hashing import sha256_file
from plumbing.inputs import MiB, read_input_text

__all__ = [
    "dask_client",
    "claim_out_dir",
    "job_fingerprint",
    "sha256_file",
    "write_rows",
    "read_rows",
]

JOB_SCHEMA = 1
_ADDRESS = re.compile(r"^(tcp|tls|inproc|ucx|ws|wss)://[^\s/]+(:\d+)?/?$")


def job_fingerprint(samples_sha256: str, options, chunk_texels: int, min_samples: int) -> dict:
    """What defines a job's results (job.json); equal fingerprints give identical rows."""
    import dataclasses

    opts = {k: repr(v) for k, v in sorted(dataclasses.asdict(options).items())}
    return {
        "schema": JOB_SCHEMA,
        "samples_sha256": samples_sha256,
        "options": opts,
        "chunk_texels": int(chunk_texels),
        "min_samples": int(min_samples),
    }


def claim_out_dir(out_dir: Path, record: dict) -> str:
    """Create OUT (or reuse it for the same job); returns the job key. UserError when OUT
    holds another job."""
    from plumbing.atomic import atomic_write_bytes

    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "chunks").mkdir(exist_ok=True)
    path = out_dir / "job.json"
    text = json.dumps(record, indent=1, sort_keys=True)
    if path.exists():
        try:
            old = json.loads(read_input_text(path, "job record", 16 * MiB))
        except (OSError, ValueError):
            raise UserError(
                f"{path}: unreadable; remove {out_dir} or choose another --out"
            ) from None
        if old != record:
            raise UserError(
                f"{out_dir}: holds results of another job (other samples or fit options); "
                "choose another --out or remove it"
            )
    else:
        atomic_write_bytes(path, text.encode())
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None) -> Iterator:
    """A distributed.Client: to `scheduler` (an address such as tcp://host:8786), else to a new
    LocalCluster of `workers` single-threaded worker processes (default: one per core)."""
    import logging

    from distributed import Client, LocalCluster

    if workers is not None and workers < 1:
        raise UserError("--workers must be ≥ 1")
    if scheduler is not None:
        if not _ADDRESS.match(scheduler):
            raise UserError(
                f"--scheduler {scheduler!r}: not a Dask scheduler address (e.g. tcp://host:8786)"
            )
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise UserError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
        with client:
            yield client
        return
    n = workers or os.cpu_count() or 1
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",  # a free port: never clash with another cluster here
        # Task errors reach the client as exceptions; worker logs of a normal shutdown (a
        # heartbeat to a scheduler already closed) are noise on the command line.
        silence_logs=logging.CRITICAL,
    )
    with cluster, Client(cluster) as client:
        yield client


def write_rows(path: Path, rows: list[dict], *, overwrite: bool = False) -> Path:
    """Result rows as a Parquet table, atomically (never overwritten unless asked)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from plumbing.atomic import atomic_write_with

    names: list[str] = []
    for r in rows:
        names.extend(k for k in r if k not in names)
    cols = {}
    for name in names:
        values = [r.get(name) for r in rows]
        if all(isinstance(v, str) or v is None for v in values):
            cols[name] = pa.array(values, pa.string())
        elif all(isinstance(v, bool | np.bool_) or v is None for v in values):
            cols[name] = pa.array(values, pa.bool_())
        elif name in ("texel", "n_samples"):
            cols[name] = pa.array(values, pa.int64())
        else:
            cols[name] = pa.array([np.nan if v is None else float(v) for v in values], pa.float64())
    table = pa.table(cols)
    return atomic_write_with(path, lambda fh: pq.write_table(table, fh), overwrite=overwrite)


def read_rows(path: Path) -> list[dict]:
    import pyarrow.parquet as pq

    return pq.read_table(path).to_pylist()

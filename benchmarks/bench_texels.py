"""Per-texel fitting on Dask (issue 20): recovery on a 32 × 32 textured sample, throughput on 1
and 2 local workers, scheduler overhead per task, memory per worker, and a projection to 64
workers from the measured task times.

Samples: Mitsuba's textured BSDF with Poisson noise at 36 poses per texel (tests/support/texels.py,
the same as the tests). Throughput is measured after a warm-up job on the same cluster (each
worker pays numba's cache load and the imports once: that start-up is reported apart).
Scheduler overhead: the wall time per task of 400 no-op tasks on one worker (submit, schedule,
run, gather), i.e. what a task costs beyond its own work.

Run: ``.venv/bin/python benchmarks/bench_texels.py [--texels 32] [--steps 300] [--skip-recovery]
[--skip-throughput]``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # tests.support.texels

__all__ = ["main"]


def _noop(x: int) -> int:
    return x


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def _throughput(samples: Path, workers: int, steps: int, chunk: int, base: Path) -> dict:
    from gonio.scaleout.cluster import dask_client, read_rows
    from gonio.scaleout.texels import TexelJob, run_texel_job
    from tests.support.texels import fit_options, texel_samples

    t0 = time.perf_counter()
    with dask_client(None, workers) as client:
        start_s = time.perf_counter() - t0
        warm_samples = texel_samples(base / f"warm-{workers}.parquet", 2) and (
            base / f"warm-{workers}.parquet"
        )
        warm = TexelJob(warm_samples, base / f"warm-{workers}", fit_options(steps), chunk_texels=1)
        run_texel_job(warm, client, progress=False)  # one texel per task: every worker warms up
        job = TexelJob(samples, base / f"timed-{workers}", fit_options(steps), chunk_texels=chunk)
        res = run_texel_job(job, client, progress=False)
        rows = read_rows(res.table_path)
        t1 = time.perf_counter()
        n_noop = 400
        futs = [client.submit(_noop, k, pure=False) for k in range(n_noop)]
        client.gather(futs)
        noop_s = (time.perf_counter() - t1) / n_noop
        rss = client.run(_rss_mb)
    return {
        "workers": workers,
        "texels": res.texels,
        "wall_s": res.wall_s,
        "texels_per_s": res.texels / res.wall_s,
        "cpu_s_per_texel": float(np.mean([r["cpu_s"] for r in rows])),
        "cluster_start_s": start_s,
        "task_overhead_s": noop_s,
        "rss_mb": float(np.mean(list(rss.values()))),
    }


def _recovery(samples: Path, material, steps: int, base: Path) -> dict:
    from gonio.scaleout.cluster import dask_client, read_rows
    from gonio.scaleout.texels import TexelJob, run_texel_job
    from simulator.texture import texel_truth
    from tests.support.texels import fit_options

    job = TexelJob(samples, base / "recovery", fit_options(steps), chunk_texels=16)
    with dask_client(None, 2) as client:
        res = run_texel_job(job, client, progress=True)
    rows = read_rows(res.table_path)
    truth = texel_truth(material)
    idx = np.array([r["texel"] for r in rows])
    out: dict = {"texels": len(rows), "wall_s": res.wall_s}
    covered = []
    for name in ("kd_R", "kd_G", "kd_B", "ks", "m"):
        t = truth[name][idx]
        med = np.array([r[f"{name}.median"] for r in rows])
        lo = np.array([r[f"{name}.p2.5"] for r in rows])
        hi = np.array([r[f"{name}.p97.5"] for r in rows])
        cov = (lo <= t) & (t <= hi)
        covered.append(cov)
        out[name] = {
            "median_rel_err": float(np.median(np.abs(med / t - 1.0))),
            "coverage95": float(np.mean(cov)),
        }
    out["coverage95_all"] = float(np.mean(covered))
    out["rhat_max_median"] = float(np.median([r["rhat_max"] for r in rows]))
    out["chi2_red_median"] = float(np.median([r["chi2_red"] for r in rows]))
    return out


def projection(cpu_s_per_texel: float, overhead_s: float, chunk: int, workers: int) -> float:
    """Texels per second on `workers` workers: each worker fits a chunk in chunk·c + o seconds
    (c the measured CPU time per texel, o the per-task overhead), and the one scheduler handles
    at most 1/o tasks per second, i.e. chunk/o texels per second."""
    per_worker = chunk / (chunk * cpu_s_per_texel + overhead_s)
    return min(workers * per_worker, chunk / overhead_s)


def main() -> None:
    from tests.support.texels import texel_samples

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--texels", type=int, default=32)
    # 300 steps: the tests' chains (tests/gonio/test_texels.py); 200 gave 87.8 % coverage on 6 × 6.
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--chunk", type=int, default=16)
    ap.add_argument("--skip-recovery", action="store_true")
    ap.add_argument("--skip-throughput", action="store_true")
    args = ap.parse_args()
    base = Path(tempfile.mkdtemp(prefix="bench-texels-"))
    try:
        small = base / "small.parquet"
        texel_samples(small, 6)
        for workers in () if args.skip_throughput else (1, 2):
            t = _throughput(small, workers, args.steps, 4, base)
            print(
                f"workers {workers}: {t['texels_per_s']:.2f} texels/s ({t['texels']} texels in "
                f"{t['wall_s']:.1f} s), {t['cpu_s_per_texel']:.2f} CPU-s/texel, task overhead "
                f"{1e3 * t['task_overhead_s']:.1f} ms, worker RSS {t['rss_mb']:.0f} MB, "
                f"cluster start {t['cluster_start_s']:.1f} s",
                flush=True,
            )
        if not args.skip_throughput:
            p64 = projection(t["cpu_s_per_texel"], t["task_overhead_s"], args.chunk, 64)
            print(
                f"projection, 64 workers, chunk {args.chunk}: {p64:.1f} texels/s; a 256 × 256 "
                f"map (65 536 texels) in {65536 / p64 / 60:.1f} min",
                flush=True,
            )
        if not args.skip_recovery:
            big = base / "big.parquet"
            material = texel_samples(big, args.texels)
            r = _recovery(big, material, args.steps, base)
            print(f"recovery {args.texels} x {args.texels}: {r}", flush=True)
    finally:
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()

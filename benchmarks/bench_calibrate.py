"""Benchmark: reduce a run of 500 captures (64×64 RAW/DNG, RGGB, 3 brackets each) to samples.

Target (issue 6): ≤ 20 s on 2 cores for the reduce step. The run is simulated once (configs/
scenes/raw.toml with master darks and a flat) and cached in --cache. Run:
    .venv/bin/python benchmarks/bench_calibrate.py [--cache /tmp/gonio-bench-calibrate]
        [--scene configs/scenes/raw.toml] [--profile]
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

__all__ = ["main", "bench"]

REPO = Path(__file__).resolve().parent.parent
EXPOSURES_S = [0.001, 0.004, 0.016]


def _make_run(out: Path, scene_path: Path) -> None:
    from acquisition.config import PlanConfig
    from acquisition.operator import AutoOperator
    from gonio.pipeline import AcquireSpec, acquire

    # 5 × 10 × 10 = 500 poses, all reachable (θ ≤ 72°, Δφ ≥ 20° keeps the arms apart).
    plan = PlanConfig.model_validate(
        {
            "name": "bench",
            "type": "isotropic",
            "theta_i_deg": [10.0, 25.0, 40.0, 55.0, 70.0],
            "theta_o_deg": [0.0, 8.0, 16.0, 24.0, 32.0, 40.0, 48.0, 56.0, 64.0, 72.0],
            "delta_phi_deg": [20.0, 36.0, 52.0, 68.0, 84.0, 100.0, 116.0, 132.0, 148.0, 180.0],
            "exposures_s": EXPOSURES_S,
            "order": "nearest",
            # Master darks per exposure, a flat at the longest, the reference target: the
            # run's own calibration phases.
            "calibration": {"dark": {"count": 16}, "flat": {"count": 32}, "reference": {}},
        }
    )
    acquire(
        out,
        AcquireSpec(
            rig=REPO / "configs" / "rigs" / "sim.toml",
            scene=scene_path,
            progress=False,
            plan=plan,
            operator=AutoOperator(),
        ),
    )


def _complete(run: Path) -> bool:
    from acquisition.store import RunStore, RunStoreError

    try:
        store = RunStore.open(run)
    except RunStoreError:
        return False
    try:
        return store.complete and bool(store.calibration_captures("dark"))
    finally:
        store.close()


def bench(cache: Path, scene_path: Path, profile: bool = False) -> dict:
    from acquisition.store import RunStore
    from calibration.reduce import ReduceOptions, reduce_run

    run = cache / "run"
    if not _complete(run):
        shutil.rmtree(cache, ignore_errors=True)
        cache.mkdir(parents=True)
        t0 = time.perf_counter()
        _make_run(run, scene_path)
        print(f"simulated the run in {time.perf_counter() - t0:.1f} s (cached in {run})")
    store = RunStore.open(run)
    n_frames = store.count("done")
    poses = len({r.pose_index for r in store.captures("done")})
    store.close()
    opts = ReduceOptions(bin_px=2, mode="center")
    t0 = time.perf_counter()
    if profile:
        import cProfile
        import pstats

        prof = cProfile.Profile()
        prof.enable()
    table = reduce_run(run, opts, out=cache / "samples.parquet")
    wall = time.perf_counter() - t0
    if profile:
        prof.disable()
        pstats.Stats(prof).sort_stats("cumulative").print_stats(20)
    return {"poses": poses, "frames": n_frames, "samples": len(table.f), "reduce_s": wall}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/gonio-bench-calibrate"))
    ap.add_argument("--scene", type=Path, default=REPO / "configs" / "scenes" / "raw.toml")
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args(argv if argv is not None else [])
    r = bench(args.cache, args.scene, args.profile)
    print(
        f"reduce: {r['poses']} captures × {len(EXPOSURES_S)} brackets = {r['frames']} DNG frames "
        f"(64×64 RGGB, darks + flat) → {r['samples']} samples in {r['reduce_s']:.2f} s "
        f"({1e3 * r['reduce_s'] / r['frames']:.1f} ms/frame); target ≤ 20 s on 2 cores"
    )


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])

"""Benchmark: acquisition lab time and wall time.

1. Estimated move time of `configs/plans/isotropic.toml` on `configs/rigs/sim.toml`: raster
   (the plan's product order θ_i → θ_o → Δφ), the best of the six raster loop nestings, and
   the travel-optimal order (nearest neighbour + 2-opt). Issue 5 acceptance: the ordering cuts
   estimated move time by ≥ 30 % against raster order.
2. Wall time of a 500-pose simulated acquisition (virtual clock, real dynamixel_sdk against the
   in-process emulator, Mitsuba frames, SQLite manifest). Issue 4 target: ≤ 30 s.

Run: .venv/bin/python benchmarks/bench_acquisition.py [--poses 500] [--skip-run]
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import reachable_poses

from acquisition.config import PlanConfig, load_plan, load_rig
from acquisition.kinematics import Kinematics, Pose, Unreachable
from acquisition.plans import build_plan, park_targets, tour_time_s

__all__ = ["main", "move_time_figures", "acquisition_wall_time"]

REPO = Path(__file__).resolve().parent.parent


def move_time_figures(rig_path: Path, plan_path: Path) -> dict[str, float]:
    rig = load_rig(rig_path)
    cfg = load_plan(plan_path)
    plan = build_plan(rig, cfg)
    # Every loop nesting of the raster, for a fair "best raster" baseline.
    kin = Kinematics(rig)
    roles = ["light_theta", "light_phi", "camera_theta", "camera_phi"]
    axes_lists = {"ti": cfg.theta_i_deg, "to": cfg.theta_o_deg, "dp": cfg.delta_phi_deg}
    park = park_targets(rig)
    start = np.array([park[r] for r in roles])
    best = np.inf
    for nesting in itertools.permutations(axes_lists):
        vecs = []
        for combo in itertools.product(*(axes_lists[k] for k in nesting)):
            d = dict(zip(nesting, combo, strict=True))
            try:
                t = kin.targets(Pose.from_deg(d["ti"], 0.0, d["to"], d["dp"] % 360.0))
            except Unreachable:
                continue
            vecs.append([t[r] for r in roles])
        best = min(best, tour_time_s(rig, np.array(vecs), start))
    # A lower bound for any order: every pose but the first is entered by one leg, which costs
    # at least that pose's cheapest leg; the first is entered from the park position.
    from acquisition.motion import move_time_s

    axes = {r: rig.axis(r) for r in roles}
    vec = np.array([[p.targets[r] for r in roles] for p in plan.poses])
    legs = move_time_s(axes, vec[:, None, :], vec[None, :, :])
    np.fill_diagonal(legs, np.inf)
    cheapest = np.sort(legs.min(axis=1))
    bound = float(cheapest[:-1].sum() + move_time_s(axes, start[None, :], vec).min())
    return {
        "lower_bound_s": bound,
        "poses": len(plan.poses),
        "skipped": len(plan.skipped),
        "raster_s": plan.raster_move_time_s,
        "best_raster_s": float(best),
        "ordered_s": plan.move_time_s,
        "lab_estimate_s": plan.lab_time_s(rig.camera.readout_s, rig.settle_s),
    }


def acquisition_wall_time(n_poses: int = 500, root: str | None = None) -> dict[str, float]:
    """Wall time of one simulated acquisition into a temporary run under `root`. Every frame
    costs fsyncs (frame, directory, WAL commit with synchronous=FULL), so the figure depends
    on the disk as much as on the code: the benchmark reports a tmpfs run and a disk run."""
    from gonio.pipeline import AcquireSpec, acquire

    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    grid = itertools.product(
        np.arange(5.0, 80.0, 5.0), np.arange(0.0, 85.0, 5.0), (0.0, 45.0, 90.0, 135.0, 180.0)
    )
    poses = reachable_poses(rig, grid, n_poses)
    cfg = PlanConfig(name="bench", type="explicit", poses_deg=tuple(poses), exposures_s=(0.002,))
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        t0 = time.perf_counter()
        res = acquire(Path(tmp) / "run", AcquireSpec(rig=rig, plan=cfg, progress=False))
        wall = time.perf_counter() - t0
    assert res.outcome.complete, res.outcome.reason
    return {
        "poses": len(poses),
        "captures": res.outcome.total_done,
        "wall_s": wall,
        "lab_s": res.outcome.lab_time_s,
        "lab_estimate_s": res.lab_estimate_s,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--poses", type=int, default=500)
    ap.add_argument("--skip-run", action="store_true", help="only the move-time estimate")
    args = ap.parse_args(argv if argv is not None else [])
    f = move_time_figures(
        REPO / "configs" / "rigs" / "sim.toml", REPO / "configs" / "plans" / "isotropic.toml"
    )
    print(f"isotropic.toml: {f['poses']} poses ({f['skipped']} unreachable skipped)")
    print(f"  raster (plan order)      {f['raster_s']:8.1f} s")
    print(f"  best raster nesting      {f['best_raster_s']:8.1f} s")
    print(
        f"  ordered (NN + 2-opt)     {f['ordered_s']:8.1f} s   "
        f"cut {1 - f['ordered_s'] / f['raster_s']:.1%} vs raster, "
        f"{1 - f['ordered_s'] / f['best_raster_s']:.1%} vs best raster  (target ≥ 30 %)"
    )
    print(f"  lower bound (any order)  {f['lower_bound_s']:8.1f} s")
    print(f"  estimated lab time       {f['lab_estimate_s']:8.1f} s")
    if args.skip_run:
        return
    roots = [("disk (" + tempfile.gettempdir() + ")", None)]
    if Path("/dev/shm").is_dir():
        roots.insert(0, ("tmpfs (/dev/shm)", "/dev/shm"))
    for label, root in roots:
        r = acquisition_wall_time(args.poses, root)
        print(
            f"simulated acquisition on {label}: {r['poses']} poses, {r['captures']} captures "
            f"in {r['wall_s']:.1f} s wall (target ≤ 30 s); lab time {r['lab_s']:.0f} s "
            f"(estimate {r['lab_estimate_s']:.0f} s)"
        )


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])

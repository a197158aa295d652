"""Benchmark: a 10⁵-pose plan built and ordered in bounded time and memory (issue 22 item 8:
< 60 s and < 1 GB).

Runs `gonio plan --plan BIG --rig configs/rigs/sim.toml` as a subprocess (a hemisphere plan,
θ every 5° to 80°, φ every 18°: 103 041 grid poses) and reports its wall time and peak RSS
(getrusage of the child), then, in this process, where the time goes (grid, reachability,
nearest neighbour, windowed 2-opt) and what the order buys: move time against raster order,
and against the dense n × n ordering at the largest size it is still used for.

Run: .venv/bin/python benchmarks/bench_plan_order.py [--theta-step 5] [--phi-step 18]
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from acquisition import tours
from acquisition.config import PlanConfig, load_rig
from acquisition.kinematics import Kinematics, Pose, Unreachable
from acquisition.plans import _park, _roles, expand_grid, tour_time_s

__all__ = ["main"]

REPO = Path(__file__).resolve().parents[1]
RIG = REPO / "configs" / "rigs" / "sim.toml"


def _cli(plan: Path) -> tuple[float, float]:
    """Wall seconds and peak RSS (MB) of `gonio plan --plan` in a fresh process."""
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "gonio.cli", "plan", "--plan", str(plan), "--rig", str(RIG)],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    wall = time.perf_counter() - t0
    # ru_maxrss of RUSAGE_CHILDREN is the largest child's peak, in kB on Linux.
    return wall, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024


def _vectors(rig, cfg: PlanConfig) -> tuple[np.ndarray, np.ndarray, float]:
    kin = Kinematics(rig)
    roles = _roles(rig)
    t0 = time.perf_counter()
    rows = []
    for deg in expand_grid(cfg, rig):
        try:
            targets = kin.targets(Pose.from_deg(*deg))
        except Unreachable:
            continue
        rows.append([targets[r] for r in roles])
    start = np.array([_park(rig, r) for r in roles])
    return np.array(rows), start, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--theta-step", type=float, default=5.0)
    ap.add_argument("--phi-step", type=float, default=18.0)
    ns = ap.parse_args()
    rig = load_rig(RIG)
    axes = {r: rig.axis(r) for r in _roles(rig)}
    cfg = PlanConfig(
        name="big",
        type="hemisphere",
        theta_step_deg=ns.theta_step,
        phi_step_deg=ns.phi_step,
        exposures_s=(0.002,),
    )
    with tempfile.TemporaryDirectory() as tmp:
        plan = Path(tmp) / "big.toml"
        plan.write_text(
            f'name = "big"\ntype = "hemisphere"\ntheta_step_deg = {ns.theta_step}\n'
            f"phi_step_deg = {ns.phi_step}\nexposures_s = [0.002]\n"
        )
        wall, rss = _cli(plan)
    vectors, start, t_reach = _vectors(rig, cfg)
    n = len(vectors)
    print(
        f"gonio plan --plan (hemisphere, {n} reachable poses): {wall:.1f} s, peak RSS {rss:.0f} MB"
    )

    t0 = time.perf_counter()
    nn = tours._nearest_neighbour_kdtree(axes, vectors, start)
    t_nn = time.perf_counter() - t0
    t0 = time.perf_counter()
    final = tours._windowed_two_opt(axes, vectors, start, nn)
    t_opt = time.perf_counter() - t0
    raster = tour_time_s(rig, vectors, start)
    print(f"  reachability + axis targets: {t_reach:.1f} s")
    hours_nn = tour_time_s(rig, vectors[nn], start) / 3600
    hours = tour_time_s(rig, vectors[final], start) / 3600
    print(f"  nearest neighbour (k-d tree): {t_nn:.1f} s, moves {hours_nn:.2f} h")
    print(f"  windowed 2-opt: {t_opt:.1f} s, moves {hours:.2f} h")
    print(f"  raster order: moves {raster / 3600:.2f} h")

    # The large-plan method against the dense one where both run: the largest dense size.
    m = tours.DENSE_MAX_POSES
    sub = vectors[np.random.default_rng(0).choice(n, m, replace=False)]
    t0 = time.perf_counter()
    dense = tours.order_poses(axes, sub, start)
    t_dense = time.perf_counter() - t0
    t0 = time.perf_counter()
    sparse = tours._windowed_two_opt(
        axes, sub, start, tours._nearest_neighbour_kdtree(axes, sub, start)
    )
    t_sparse = time.perf_counter() - t0
    ratio = tour_time_s(rig, sub[sparse], start) / tour_time_s(rig, sub[dense], start)
    print(
        f"  at {m} poses: dense {t_dense:.1f} s, large-plan method {t_sparse:.1f} s, "
        f"its tour {100 * (ratio - 1):+.1f} % against dense"
    )


if __name__ == "__main__":
    main()

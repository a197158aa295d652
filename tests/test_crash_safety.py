"""Crash safety (issue 5 acceptance): kill -9 the acquisition at random moments, 10 times over a
200-pose plan, resuming each time. The final manifest is complete, with no duplicate captures,
every checksum verifying, every frame on disk listed, and the same set of (pose, bracket) keys
and pose angles as the plan asks for.

The acquisition runs as the real CLI in a subprocess (`python -m gonio.cli acquire`), so the
kill hits the whole process: SQLite, the frame writer and the driver die mid-call.
"""

from __future__ import annotations

import itertools
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from acquisition.config import load_plan, load_rig
from acquisition.plans import build_plan
from acquisition.store import RunStore

REPO = Path(__file__).resolve().parent.parent
THETA_I = (10.0, 20.0, 30.0, 40.0, 50.0)
THETA_O = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0)
DPHI = (30.0, 60.0, 90.0, 135.0, 180.0)  # no Δφ = 0, so every pose is reachable
N_POSES = len(THETA_I) * len(THETA_O) * len(DPHI)  # 200
KILLS = 10
# Arrival tolerance 8 ticks of 4096/turn (DynamixelAxis.tolerance_ticks), gear ratio 1.
ARRIVAL_RAD = 8 * 2 * math.pi / 4096


def _frames(out: Path) -> int:
    d = out / "frames"
    return sum(1 for p in d.iterdir() if not p.name.startswith(".")) if d.exists() else 0


def test_kill_9_ten_times_then_complete(tmp_path: Path) -> None:
    plan_path = tmp_path / "plan200.toml"
    plan_path.write_text(
        'name = "crash200"\ntype = "isotropic"\n'
        f"theta_i_deg = {list(THETA_I)}\ntheta_o_deg = {list(THETA_O)}\n"
        f"delta_phi_deg = {list(DPHI)}\nexposures_s = [0.002]\n"
    )
    out = tmp_path / "run"
    cmd = [
        sys.executable,
        "-m",
        "gonio.cli",
        "acquire",
        "--rig",
        str(REPO / "configs" / "rigs" / "sim.toml"),
        "--plan",
        str(plan_path),
        "--out",
        str(out),
        "--no-progress",
    ]
    rng = np.random.default_rng(20261123)
    killed = 0
    seen = 0
    for _ in range(KILLS):
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        # Wait until this session has captured a random few new frames, then kill at a random
        # moment within the next 20 ms: mid-frame-write, mid-commit, mid-move alike. Counting
        # frames rather than seconds keeps the test independent of the machine's speed (a fast
        # idle machine would otherwise finish the plan before the tenth kill).
        target = seen + int(rng.integers(1, 12))
        deadline = time.monotonic() + 60
        while _frames(out) < target and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.002)
        time.sleep(float(rng.uniform(0.0, 0.02)))
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            killed += 1
        proc.wait()
        seen = _frames(out)
        if RunStore.open(out).complete:
            break
    assert killed == KILLS  # every session was killed mid-run (the plan outlasts 10 kills)
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr

    store = RunStore.open(out)
    assert store.complete
    assert store.verify() == []
    captures = list(store.captures())
    keys = [(c.pose_index, c.bracket_index) for c in captures]
    assert len(keys) == len(set(keys))  # no duplicates
    assert set(keys) == {(i, 0) for i in range(N_POSES)}
    assert store.count("pending") == 0
    on_disk = {f"frames/{p.name}" for p in (out / "frames").iterdir() if not p.name.startswith(".")}
    assert on_disk == {c.frame_path for c in captures}
    # Same poses as the plan: pose index i is the i-th grid combination (expansion order),
    # and the measured angles match it within the arrival tolerance.
    grid = list(itertools.product(THETA_I, THETA_O, DPHI))
    # (Every grid pose is reachable, so no index is missing from the grid.)
    assert build_plan(load_rig(REPO / "configs/rigs/sim.toml"), load_plan(plan_path)).skipped == []
    for c in captures:
        ti, to, dp = grid[c.pose_index]
        assert abs(c.theta_i - math.radians(ti)) <= ARRIVAL_RAD
        assert abs(c.theta_o - math.radians(to)) <= ARRIVAL_RAD
        dphi = (c.phi_o - c.phi_i) % (2 * math.pi)
        assert abs(dphi - math.radians(dp)) <= 2 * ARRIVAL_RAD

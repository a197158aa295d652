"""Adaptive plans (issue 5): a coarse pre-scan, then poses refined around each peak, in one run.

The simulated rig runs the real `gonio acquire` command line, which is killed with SIGKILL
during phase 2 and resumed; the frozen refinement must survive unchanged. Ground truth for
where the refinement should go is the specular direction from geometry (θ_o = θ_i,
φ_o = φ_i + 180°) on a glossy material (Beckmann m = 0.05, a lobe a few degrees wide), not
anything the code under test computes. Finally `calibration.reduce.reduce_run`, unchanged,
reduces the two-phase run.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from acquisition.config import PlanConfig
from acquisition.runlog import read_log
from acquisition.store import RunStore
from calibration.reduce import ReduceOptions, reduce_run
from gonio.pipeline import AcquireSpec, acquire
from tests.support.paths import REPO

THETA_I = (25.0, 45.0)
THETA_O = (0.0, 12.0, 24.0, 36.0, 48.0, 60.0)
DPHI = (180.0, 150.0)
SPAN, STEP = 12.0, 4.0
PLAN_TOML = f"""
name = "adaptive-test"
type = "adaptive"
refine_span_deg = {SPAN}
refine_step_deg = {STEP}
exposure_mode = "auto"

[auto_exposure]
start_s = 0.002
max_s = 0.5
max_brackets = 3

[prescan]
type = "isotropic"
theta_i_deg = {list(THETA_I)}
theta_o_deg = {list(THETA_O)}
delta_phi_deg = {list(DPHI)}
"""
# Every pre-scan pose is reachable on the sim rig (light and camera ≥ 5° apart everywhere).
N_PRESCAN = len(THETA_I) * len(THETA_O) * len(DPHI)


def _unit(theta_deg: float, phi_deg: float) -> np.ndarray:
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(a @ b, -1.0, 1.0))))


def _glossy_scene(tmp: Path) -> Path:
    text = (REPO / "configs" / "scenes" / "demo.toml").read_text()
    assert "alpha = 0.2 " in text
    path = tmp / "glossy.toml"
    path.write_text(text.replace("alpha = 0.2 ", "alpha = 0.05"))
    return path


def test_two_phase_run_killed_in_phase_2_resumes_the_frozen_refinement(tmp_path: Path) -> None:
    plan_path = tmp_path / "adaptive.toml"
    plan_path.write_text(PLAN_TOML)
    scene = _glossy_scene(tmp_path)
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
        "--scene",
        str(scene),
        "--out",
        str(out),
        "--no-progress",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    # Kill without warning once phase 2 has captured a few frames (read from the log).
    deadline = time.monotonic() + 120
    killed = False
    while time.monotonic() < deadline and proc.poll() is None:
        events = read_log(out) if (out / "log.jsonl").exists() else []
        n2 = sum(1 for e in events if e["event"] == "capture" and e["pose"] >= N_PRESCAN)
        if n2 >= 3:
            os.kill(proc.pid, signal.SIGKILL)
            killed = True
            break
        time.sleep(0.02)
    proc.wait()
    assert killed, f"phase 2 never started: {proc.stderr.read().decode()[-2000:]}"

    store = RunStore.open(out)
    assert not store.complete
    frozen = store.meta("refine_plan")
    assert frozen is not None
    assert int(store.meta("refine_offset")) == N_PRESCAN
    store.close()

    rig = REPO / "configs" / "rigs" / "sim.toml"  # resuming needs the trusted rig file
    res = acquire(out, AcquireSpec(rig=rig, progress=False, announce=False))
    assert res.outcome.complete, res.outcome.reason
    store = RunStore.open(out)
    assert store.meta("refine_plan") == frozen  # not re-decided
    refine = PlanConfig.model_validate_json(frozen)
    events = read_log(out)
    reused = [e for e in events if e["event"] == "refine_plan"]
    assert [e["reason"] for e in reused] == ["decided from the pre-scan", "frozen plan reused"]

    # The manifest holds both phases: pre-scan poses 0..N-1, refine poses N.., no key twice,
    # every frame verified and listed.
    keys = [(c.pose_index, c.bracket_index) for c in store.captures()]
    assert len(keys) == len(set(keys))
    poses = {p for p, _ in keys}
    assert poses == set(range(N_PRESCAN + len(refine.poses_deg)))
    assert store.verify() == []
    listed = {c.frame_path for c in store.captures()}
    on_disk = {f"frames/{p.name}" for p in (out / "frames").iterdir() if not p.name.startswith(".")}
    assert on_disk == listed

    # Refinement clusters around the true specular direction of every incidence. The patch is
    # symmetric (± SPAN) about the pre-scan pose nearest to specular, which lies at most half
    # the pre-scan θ_o spacing (6°) from it; the excluded centre and the rig's reach cannot
    # move the centroid of a ±12° patch by more than that, so the centroid is within 6°, while
    # the other pre-scan poses of the incidence are ≥ 6° away from specular.
    spacing = THETA_O[1] - THETA_O[0]
    for ti in THETA_I:
        spec = _unit(ti, 180.0)
        patch = [_unit(p[2], p[3]) for p in refine.poses_deg if p[0] == ti]
        assert len(patch) >= 8
        centroid = np.mean(patch, axis=0)
        centroid /= np.linalg.norm(centroid)
        assert _angle_deg(centroid, spec) < spacing / 2.0, ti
        # And the fine poses reach within one step of the specular direction.
        assert min(_angle_deg(v, spec) for v in patch) <= STEP, ti
    # Every refine pose lies within the patch (± SPAN in θ_o of the peak, which is within
    # half the spacing of specular): none strays across the hemisphere.
    for p in refine.poses_deg:
        assert abs(p[2] - p[0]) <= SPAN + spacing / 2.0

    # calibration.reduce processes the two-phase, auto-exposed run unchanged.
    table = reduce_run(out, ReduceOptions(bin_px=8))
    ids_by_pose = {c.id: c.pose_index for c in store.captures()}
    reduced_poses = {ids_by_pose[int(i)] for i in np.unique(table.extra["capture_id"])}
    assert any(p >= N_PRESCAN for p in reduced_poses) and any(p < N_PRESCAN for p in reduced_poses)
    assert np.all(np.isfinite(table.f[table.flags == 0]))


def test_lab_estimate_bounds_phase_2(tmp_path: Path) -> None:
    """The estimate printed before the run: phase 1, plus an upper bound on phase 2 that the
    measured phase-2 lab time (rig clock, from the log) stays under."""
    plan = PlanConfig(
        name="ad",
        type="adaptive",
        prescan=PlanConfig(theta_i_deg=THETA_I, theta_o_deg=THETA_O, delta_phi_deg=DPHI),
        refine_span_deg=SPAN,
        refine_step_deg=STEP,
        exposures_s=(0.002, 0.016),
    )
    from acquisition.config import load_rig
    from simulator.scene import load_scene

    scene = load_scene(_glossy_scene(tmp_path))
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    res = acquire(
        tmp_path / "run",
        AcquireSpec(rig=rig, plan=plan, scene=scene, progress=False, announce=False),
    )
    assert res.outcome.complete, res.outcome.reason
    est = res.extra["lab_estimate"]
    assert est["total_max_s"] == res.lab_estimate_s == est["phase1_s"] + est["phase2_max_s"]
    events = read_log(tmp_path / "run")
    start2 = next(e for e in events if e["event"] == "phase_start" and e["phase"] == 2)
    end = next(e for e in events if e["event"] == "session_end")
    assert 0 < end["lab_s"] - start2["lab_s"] <= est["phase2_max_s"]
    assert (
        res.outcome.refine_poses
        == json.loads(RunStore.open(tmp_path / "run").meta("refine_plan"))["poses_deg"].__len__()
    )

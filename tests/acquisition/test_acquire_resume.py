"""Acquisition on the simulated rig: interrupted runs resume; complete runs are never touched.

Real parts throughout: the real dynamixel_sdk talks to the Protocol 2.0 emulator over the
`dxlsim://` pyserial URL, frames are real EXR files, the manifest is SQLite.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from acquisition.config import PlanConfig, load_rig
from acquisition.plans import build_plan
from acquisition.rig import build_rig
from acquisition.runner import _StopFlag, run_acquisition
from acquisition.store import RunStore, RunStoreError
from gonio.backends import prepare_backends
from gonio.pipeline import AcquireSpec, acquire
from tests.support.paths import REPO

SMALL_PLAN = PlanConfig(
    name="small",
    theta_i_deg=(20.0, 50.0),
    theta_o_deg=(0.0, 30.0, 60.0),
    delta_phi_deg=(180.0, 90.0),
    exposures_s=(0.002, 0.016),
)


def _rig():
    return load_rig(REPO / "configs" / "rigs" / "sim.toml")


def test_interrupted_run_resumes_to_the_same_set(tmp_path: Path) -> None:
    rig_cfg = _rig()
    out = tmp_path / "run"
    # First session: request a stop after 5 captures (what SIGINT does).
    flag = _StopFlag()
    res = acquire(out, AcquireSpec(rig=rig_cfg, plan=SMALL_PLAN, progress=False))
    assert res.outcome.complete  # a full reference run first, in another directory
    ref = {(c.pose_index, c.bracket_index) for c in RunStore.open(out).captures()}

    out2 = tmp_path / "run2"
    world = prepare_backends(rig_cfg)
    assert world is not None
    rig = build_rig(rig_cfg)
    plan = build_plan(rig_cfg, SMALL_PLAN)
    import tomli_w

    store = RunStore.create(out2, tomli_w.dumps({"note": "partial"}))
    outcome = run_acquisition(
        store,
        rig,
        plan,
        progress=False,
        stop=flag,
        on_capture=lambda n: flag.set("interrupted (test)") if n == 5 else None,
    )
    rig.close()
    assert not outcome.complete and outcome.reason == "interrupted (test)"
    assert store.count("done") == 5  # the capture in progress was finished, nothing more
    assert ("stop", "interrupted (test)") in [(k, m) for _, k, m in store.events()]
    # Safe state: light off, torque off on every servo.
    assert not world.light.is_on
    assert all(world.bus.servo(a.id).register("torque_enable") == 0 for a in rig_cfg.axes)
    # Second session resumes and completes.
    rig = build_rig(rig_cfg)
    outcome = run_acquisition(store, rig, plan, progress=False)
    rig.close()
    assert outcome.complete
    got = [(c.pose_index, c.bracket_index) for c in store.captures()]
    assert len(got) == len(set(got))  # no duplicates
    assert set(got) == ref
    assert store.verify() == []


def test_complete_run_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "run"
    acquire(out, AcquireSpec(rig=_rig(), plan=SMALL_PLAN, progress=False))
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    with pytest.raises(RunStoreError, match="complete"):
        acquire(out, AcquireSpec(rig=_rig(), plan=SMALL_PLAN, progress=False))
    after = {
        p: p.stat().st_mtime_ns for p in out.rglob("*") if not p.name.endswith(("-wal", "-shm"))
    }
    assert {p: t for p, t in before.items() if p in after} == after


def test_kill_9_then_resume_via_cli(tmp_path: Path) -> None:
    out = tmp_path / "run"
    cmd = [
        sys.executable,
        "-m",
        "gonio.cli",
        "acquire",
        "--rig",
        str(REPO / "configs" / "rigs" / "sim.toml"),
        "--plan",
        str(REPO / "configs" / "plans" / "demo.toml"),
        "--out",
        str(out),
        "--no-progress",
        "--yes",  # the demo plan's calibration phases: the operator has prepared them
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # Wait until some frames exist, then kill without warning.
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if (out / "frames").exists() and len(list((out / "frames").iterdir())) >= 10:
            break
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not RunStore.open(out).complete
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    store = RunStore.open(out)
    assert store.complete and store.verify() == []
    keys = [(c.pose_index, c.bracket_index) for c in store.captures()]
    assert len(keys) == len(set(keys)) == 63 * 2
    # Every frame on disk is in the manifest (nothing orphaned or lost).
    listed = {c.frame_path for c in store.captures()}
    on_disk = {f"frames/{p.name}" for p in (out / "frames").iterdir() if not p.name.startswith(".")}
    assert on_disk == listed

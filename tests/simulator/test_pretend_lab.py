"""A pretend lab in CI (issue 14 item 7): the servo bus and light emulators in a separate process
on pseudo-terminals, configs/rigs/lab-example.toml pointed at them (device paths and the camera
backend only), the wall clock, the unmodified command line — rig check, acquire with the plan's
calibration phases and scripted operator answers, calibrate, fit; and kill -9 mid-run, resume.

Truth for the fit: the demo scene's material (kd = (1 − 0.25)·ρ, ks = 0.25, m = 0.2), read from
the scene file, not from any earlier run.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from acquisition.store import RunStore
from tests.support.pretend_lab import DEMO_SCENE, REPO, gonio, pretend_lab, write_lab_files

# heavy and waits: scheduled first, beside a repeat pool (tests/conftest.py).
pytestmark = [pytest.mark.timeout(900), pytest.mark.heavy(57), pytest.mark.waits]


def _done(run: Path) -> tuple[int, int]:
    """(calibration frames, measurement frames) marked done in a live manifest, read-only."""
    db = run / "manifest.sqlite"
    if not db.exists():
        return 0, 0
    try:
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
        try:
            cal = conn.execute(
                "SELECT COUNT(*) FROM calibration_captures WHERE status = 'done'"
            ).fetchone()[0]
            meas = conn.execute("SELECT COUNT(*) FROM captures WHERE status = 'done'").fetchone()[0]
        finally:
            conn.close()
        return int(cal), int(meas)
    except sqlite3.Error:  # not created yet
        return 0, 0


def _assert_all_data(run: Path, n_cal: int, n_meas: int) -> None:
    """Complete; each capture once; every checksum verifies; every file on disk is listed."""
    store = RunStore.open(run)
    try:
        assert store.complete
        meas = list(store.captures())
        cal = store.calibration_captures()
        keys = [(c.pose_index, c.bracket_index) for c in meas]
        cal_keys = [(c.kind, c.take, c.seq) for c in cal]
        assert len(keys) == len(set(keys)) == n_meas
        assert len(cal_keys) == len(set(cal_keys)) == n_cal
        assert store.verify() == []
        listed = {c.frame_path for c in meas} | {c.frame_path for c in cal}
        on_disk = {
            str(p.relative_to(run))
            for sub in ("frames", "calibration")
            for p in (run / sub).rglob("*")
            if p.is_file() and not p.name.startswith(".") and "f_ref" not in p.name
        }
        assert on_disk == listed
    finally:
        store.close()


def _lab_state(lab_dir: Path) -> dict:
    return json.loads((lab_dir / "state.json").read_text())


# darks 4 × 2 exposures, flat 4, reference 3 poses × 2 exposures; 2 × 3 poses × 2 brackets
N_CAL, N_MEAS = 4 * 2 + 4 + 3 * 2, 6 * 2


def test_lab_rig_end_to_end_on_the_pretend_lab(tmp_path: Path) -> None:
    t0 = time.monotonic()
    lab_dir = tmp_path / "lab"
    rig, plan, answers = write_lab_files(tmp_path, lab_dir)
    run = tmp_path / "run"
    with pretend_lab(rig, lab_dir):
        check = gonio("rig", "check", "--rig", str(rig), "--scene", str(DEMO_SCENE))
        assert check.returncode == 0, check.stdout + check.stderr
        for words in ("gonio simulated camera", "256 × 256", "black level: 240", "LIGHTSIM"):
            assert words in check.stdout, (words, check.stdout)
        res = gonio(
            "acquire", "--rig", str(rig), "--plan", str(plan), "--scene", str(DEMO_SCENE),
            "--out", str(run), "--answers", str(answers), "--no-progress",
        )  # fmt: skip
        assert res.returncode == 0, res.stderr
    # The lab is left safe, read from the emulators' own state (not from what we sent).
    state = _lab_state(lab_dir)
    assert state["torque_enable"] and not any(state["torque_enable"].values())
    assert state["light_on"] is False and state["pty_errors"] == []
    _assert_all_data(run, N_CAL, N_MEAS)
    doc = tomllib.loads((run / "run.toml").read_text())
    # What calibration uses is the rig file's description, frozen into the run.
    assert doc["camera"]["resolution"] == [256, 256]
    assert doc["camera"]["fx"] == pytest.approx(0.012 / 4.8e-6)
    assert doc["camera"]["color_filter"] == "RGGB" and doc["sample"]["size_m"] == 0.05

    cal = gonio("calibrate", str(run))
    assert cal.returncode == 0, cal.stderr
    # ... and prints the samples' uncertainty budget, GUM style: one row per component the
    # table's metadata records, with its type (the words may wrap in the table's cells)
    from brdfdata.samples import read_samples
    from fitting.budget import read_budget

    budget = read_budget(read_samples(run / "samples.parquet").metadata)
    assert budget and "Uncertainty budget" in cal.stdout
    for comp in budget:
        assert comp["component"].split()[0] in cal.stdout, (comp, cal.stdout)
    fit = gonio(
        "fit", str(run / "samples.parquet"), "--no-mcmc",
        "--option", "fresnel=none", "--option", "shadowing=smith-rational",
    )  # fmt: skip
    assert fit.returncode == 0, fit.stderr
    params = json.loads((run / "fit-torrance-sparrow.json").read_text())["parameters"]
    scene = tomllib.loads(DEMO_SCENE.read_text())["material"]
    w, rho = scene["weight"], scene["first"]["reflectance"]
    # ~9 000 samples at SNR ≈ 50: the statistical error of m and kd is < 0.1 %; the
    # region-mean binning of `calibrate`'s default biases m by ≈ +2e-4 relative (ReduceOptions).
    # 1 % leaves room for both and still fails on any radiometric or geometric mistake of the
    # lab path (a wrong pixel pitch alone is 300 %, a 0.5° pose error several % on m).
    assert params["m"]["map"] == pytest.approx(scene["second"]["alpha"], rel=0.01)
    for c, r in zip("RGB", rho, strict=True):
        assert params[f"kd_{c}"]["map"] == pytest.approx((1 - w) * r, rel=0.01)
        assert params[f"ks_{c}"]["map"] == pytest.approx(w, rel=0.01)
    print(f"pretend lab end to end: {time.monotonic() - t0:.1f} s wall")


def _acquire_cmd(rig: Path, plan: Path, run: Path, answers: Path) -> list[str]:
    return [
        sys.executable, "-m", "gonio.cli", "acquire", "--rig", str(rig), "--plan", str(plan),
        "--scene", str(DEMO_SCENE), "--out", str(run), "--answers", str(answers), "--no-progress",
    ]  # fmt: skip


def _kill_when(proc: subprocess.Popen, run: Path, ready) -> tuple[int, int]:
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        n = _done(run)
        if ready(*n):
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the run finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    return _done(run)


def test_kill_9_on_the_pretend_lab_then_resume(tmp_path: Path) -> None:
    t0 = time.monotonic()
    lab_dir = tmp_path / "lab"
    rig, plan, answers = write_lab_files(tmp_path, lab_dir)
    run = tmp_path / "run"
    cmd = _acquire_cmd(rig, plan, run, answers)
    with pretend_lab(rig, lab_dir):
        # First kill in the middle of the flat (8 darks, then flats), the second in the middle
        # of the measurement poses: both phases must resume where they stopped.
        killed = [
            _kill_when(subprocess.Popen(cmd, cwd=REPO, **_quiet()), run, lambda c, m: c >= 10),
            _kill_when(subprocess.Popen(cmd, cwd=REPO, **_quiet()), run, lambda c, m: m >= 4),
        ]
        assert killed[0][0] < N_CAL and killed[1][1] < N_MEAS, killed
        assert not RunStore.open(run).complete
        res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stderr
    state = _lab_state(lab_dir)
    assert not any(state["torque_enable"].values()) and state["light_on"] is False
    _assert_all_data(run, N_CAL, N_MEAS)
    wall = time.monotonic() - t0
    print(f"pretend lab kill -9 ×2 + resume: {wall:.1f} s wall; killed at {killed}")


def _quiet() -> dict:
    return {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
